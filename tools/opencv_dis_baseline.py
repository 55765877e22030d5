#!/usr/bin/env python3
"""OpenCV DIS baseline on the same PNGs our `flow` example reads.

usage: python3 tools/opencv_dis_baseline.py REF.png CUR.png [--truth truth.flo]
           [--presets ultrafast,fast,medium] [--threads 1,2] [--repeat 10]
           [--ours flow.flo ...] [--points markers.csv]

For each preset and thread count prints one line
    opencv <preset> threads=<n> compute_ms=<median> [aepe=<px> bias=<u>,<v>]
timing `calc` only (median over --repeat runs after one warm-up), with AEPE
over the image minus a 16 px border, like examples/flow.rs. `--ours F.flo`
(with --truth) first prints `ours <F.flo> aepe=<px>` for a flow our
examples/flow wrote on the same pair, with the same metric (5 decimals, so
near-ties between ours and OpenCV are visible). `--points markers.csv` (with
--truth; the `x_px,y_px` file `simulate shear` writes) adds the endpoint error
at those points (flow and truth sampled bilinearly at each point's reference
position): `pts_mean=<px> pts_max=<px>`.
Needs `pip install opencv-python-headless numpy`.
"""
import argparse
import statistics
import time

import cv2
import numpy as np

PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}
BORDER = 16


def read_flo(path):
    with open(path, "rb") as f:
        if f.read(4) != b"PIEH":
            raise SystemExit(f"{path}: not a .flo file")
        w, h = np.frombuffer(f.read(8), dtype="<i4")
        data = np.frombuffer(f.read(), dtype="<f4")
    return data.reshape(h, w, 2)


def aepe_bias(flow, truth):
    """AEPE and mean error (u, v) over the image minus a BORDER px border."""
    b = BORDER
    d = (flow - truth)[b:-b, b:-b]
    return float(np.mean(np.hypot(d[..., 0], d[..., 1]))), d[..., 0].mean(), d[..., 1].mean()


def read_points(path):
    """(x, y) rows of a CSV with a header line."""
    return np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def sample(img, x, y):
    """Bilinear samples of img (h, w, c) at float positions, clamped."""
    h, w = img.shape[:2]
    x = np.clip(x, 0, w - 1)
    y = np.clip(y, 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(int), w - 2)
    y0 = np.minimum(np.floor(y).astype(int), h - 2)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    top = img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx
    bot = img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bot * fy


def point_errors(flow, truth, pts):
    """Mean and largest endpoint error at the points."""
    d = sample(flow, pts[:, 0], pts[:, 1]) - sample(truth, pts[:, 0], pts[:, 1])
    e = np.hypot(d[:, 0], d[:, 1])
    return float(e.mean()), float(e.max())


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("ref")
    ap.add_argument("cur")
    ap.add_argument("--truth")
    ap.add_argument("--presets", default="ultrafast,fast,medium")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--ours", action="append", default=[])
    ap.add_argument("--points")
    a = ap.parse_args()
    i0 = cv2.imread(a.ref, cv2.IMREAD_GRAYSCALE)
    i1 = cv2.imread(a.cur, cv2.IMREAD_GRAYSCALE)
    if i0 is None or i1 is None:
        raise SystemExit("cannot read the images")
    truth = read_flo(a.truth) if a.truth else None
    if a.points and truth is None:
        raise SystemExit("--points needs --truth")
    pts = read_points(a.points) if a.points else None

    def at_points(flow):
        if pts is None:
            return ""
        mean, worst = point_errors(flow, truth, pts)
        return f" pts_mean={mean:.5f} pts_max={worst:.5f}"

    for path in a.ours:
        if truth is None:
            raise SystemExit("--ours needs --truth")
        ours = read_flo(path)
        print(f"ours {path} aepe={aepe_bias(ours, truth)[0]:.5f}{at_points(ours)}", flush=True)
    for name in a.presets.split(","):
        for nt in [int(t) for t in a.threads.split(",")]:
            cv2.setNumThreads(nt)
            dis = cv2.DISOpticalFlow_create(PRESETS[name])
            flow = dis.calc(i0, i1, None)  # warm-up
            times = []
            for _ in range(a.repeat):
                t = time.perf_counter()
                flow = dis.calc(i0, i1, None)
                times.append((time.perf_counter() - t) * 1e3)
            line = f"opencv {name} threads={nt} compute_ms={statistics.median(times):.3f}"
            if truth is not None:
                aepe, bu, bv = aepe_bias(flow, truth)
                line += f" aepe={aepe:.5f} bias={bu:+.4f},{bv:+.4f}" + at_points(flow)
            print(line, flush=True)


if __name__ == "__main__":
    main()
