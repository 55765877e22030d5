#!/usr/bin/env python3
"""OpenCV DIS baseline on the same PNGs our `flow` example reads.

usage: python3 tools/opencv_dis_baseline.py REF.png CUR.png [--truth truth.flo]
           [--presets ultrafast,fast,medium] [--threads 1,2] [--repeat 10]
           [--ours flow.flo ...]

For each preset and thread count prints one line
    opencv <preset> threads=<n> compute_ms=<median> [aepe=<px> bias=<u>,<v>]
timing `calc` only (median over --repeat runs after one warm-up), with AEPE
over the image minus a 16 px border, like examples/flow.rs. `--ours F.flo`
(with --truth) first prints `ours <F.flo> aepe=<px>` for a flow our
examples/flow wrote on the same pair, with the same metric (5 decimals, so
near-ties between ours and OpenCV are visible).
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


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("ref")
    ap.add_argument("cur")
    ap.add_argument("--truth")
    ap.add_argument("--presets", default="ultrafast,fast,medium")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--ours", action="append", default=[])
    a = ap.parse_args()
    i0 = cv2.imread(a.ref, cv2.IMREAD_GRAYSCALE)
    i1 = cv2.imread(a.cur, cv2.IMREAD_GRAYSCALE)
    if i0 is None or i1 is None:
        raise SystemExit("cannot read the images")
    truth = read_flo(a.truth) if a.truth else None
    for path in a.ours:
        if truth is None:
            raise SystemExit("--ours needs --truth")
        print(f"ours {path} aepe={aepe_bias(read_flo(path), truth)[0]:.5f}", flush=True)
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
                line += f" aepe={aepe:.5f} bias={bu:+.4f},{bv:+.4f}"
            print(line, flush=True)


if __name__ == "__main__":
    main()
