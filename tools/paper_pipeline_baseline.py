#!/usr/bin/env python3
"""The paper's per-frame pipeline in Python, timed on an image sequence.

usage: python3 tools/paper_pipeline_baseline.py SEQ_DIR [--crop X,Y,W,H]
           [--thresholds low|mid|high | --magnitude PX --sum S --erode K --dilate K]
           [--threads 2] [--rounds 3]
           [--track TRACK_BIN ... [--track-args "ARGS"]]

What the paper describes (Aucone et al., "Multi-contact Sensing
Methodology"), with the libraries it names, run frame by frame against the
first (unloaded) frame of SEQ_DIR:

1. OpenCV's DISOpticalFlow, preset FAST, default parameters, on the whole
   (cropped) image;
2. segmentation: |flow| > magnitude, erosion and dilation with square
   kernels, external contours, one bounding box per contour, boxes whose
   summed |flow| is below `sum` dropped, the unmodified flow cut per box;
3. per patch, the natural HHD at full resolution with unit spacing: the
   pynhhd transcription of tools/nhhd_reference.py (numpy.gradient,
   ln(r)/(2 pi), scipy.signal.fftconvolve), all of its outputs;
4. per patch, the raw quantities: contact point = argmin D, shear sums,
   Dn = sum |d|, d_PF = max D - min D (the calibration polynomials, a few
   dozen multiplications, are left out).

The thresholds are this library's presets (full-resolution pixels), so that
both pipelines see the same thresholds; the paper adds no margin around a
box, so neither does this script.

Per frame it times each stage (time.perf_counter) and the whole frame
without reading the PNG, and prints the median, 90th percentile and largest
over the frames, ms. `--rounds N` runs the sequence N times and takes every
frame's median over the rounds.

`--track BIN` (the built `track` example, e.g. target/release/examples/track;
repeatable, to compare builds) runs it on the same sequence after each round
(`BIN SEQ_DIR --quiet --timings` plus `--track-args`), reads the median of
its `process` column (the whole `TactileSensor::process` call, reading
excluded) and prints, per binary, its per-stage medians (median over the
rounds) and the ratio of the paper pipeline's median to its median: all
measured in the same minutes on the same machine.

Needs numpy, scipy and opencv-python-headless (OpenCV 4.x or 5.x).
"""
import argparse
import os
import statistics
import subprocess
import sys
import time

import cv2
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from nhhd_reference import nhhd  # noqa: E402

# This library's threshold presets (src/segment/mod.rs: Thresholds::LOW, MID,
# HIGH): |flow| px, summed |flow|, erosion and dilation kernel sides, px.
PRESETS = {
    "low": (0.15, 1500.0, 5, 15),
    "mid": (0.35, 2000.0, 9, 21),
    "high": (0.55, 3000.0, 9, 21),
}
STAGES = ("flow", "segment", "nhhd", "raw", "frame")


def read_gray(path, crop):
    img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SystemExit(f"cannot read {path}")
    if img.ndim == 3:
        img = img[:, :, 1]  # the green channel (OpenCV's order is BGR)
    if img.dtype != np.uint8:
        img = (img.astype(np.float64) / 257.0).round().astype(np.uint8)
    if crop is not None:
        x, y, w, h = crop
        if x + w > img.shape[1] or y + h > img.shape[0]:
            raise SystemExit(f"crop {crop} outside the {img.shape[1]}x{img.shape[0]} frame")
        img = img[y:y + h, x:x + w]
    return np.ascontiguousarray(img)


def segment(flow, magnitude, sum_min, erode, dilate):
    """The paper's threshold segmentation: boxes (x, y, w, h) of the patches."""
    mag = np.hypot(flow[..., 0], flow[..., 1])
    mask = (mag > magnitude).astype(np.uint8)
    mask = cv2.erode(mask, np.ones((erode, erode), np.uint8))
    mask = cv2.dilate(mask, np.ones((dilate, dilate), np.uint8))
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    boxes = []
    for c in contours:
        x, y, w, h = cv2.boundingRect(c)
        if mag[y:y + h, x:x + w].sum() >= sum_min:
            boxes.append((x, y, w, h))
    return boxes


def raw_quantities(u, v, dec, x0, y0):
    d_pot = dec["D"]
    iy, ix = np.unravel_index(np.argmin(d_pot), d_pot.shape)
    return dict(
        x_px=x0 + ix,
        y_px=y0 + iy,
        ds1=float(u.sum()),
        ds2=float(v.sum()),
        dn=float(np.hypot(dec["d_u"], dec["d_v"]).sum()),
        d_pf=float(d_pot.max() - d_pot.min()),
    )


def process(dis, ref, cur, thresholds):
    """One frame: per-stage times (ms) and the raw quantities per patch."""
    t = {}
    t0 = time.perf_counter()
    flow = dis.calc(ref, cur, None)
    t1 = time.perf_counter()
    boxes = segment(flow, *thresholds)
    t2 = time.perf_counter()
    decs = []
    for x, y, w, h in boxes:
        u = flow[y:y + h, x:x + w, 0].astype(np.float64)
        v = flow[y:y + h, x:x + w, 1].astype(np.float64)
        decs.append((u, v, nhhd(u, v, 1.0, 1.0), x, y))
    t3 = time.perf_counter()
    raws = [raw_quantities(u, v, dec, x, y) for u, v, dec, x, y in decs]
    t4 = time.perf_counter()
    t["flow"], t["segment"] = (t1 - t0) * 1e3, (t2 - t1) * 1e3
    t["nhhd"], t["raw"] = (t3 - t2) * 1e3, (t4 - t3) * 1e3
    t["frame"] = (t4 - t0) * 1e3
    return t, raws, boxes


def quantile(v, q):
    v = sorted(v)
    return v[round((len(v) - 1) * q)]


def run_track(a, binary):
    cmd = [binary, a.seq, "--quiet", "--timings"] + a.track_args.split()
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{out.stderr}{out.stdout}")
    lines = (out.stdout + out.stderr).splitlines()
    header = next(line for line in lines if line.startswith("ms ") and "process" in line)
    median = next(line for line in lines if line.startswith("median"))
    cols = header.split()[1:]
    vals = [float(x) for x in median.split()[1:]]
    return dict(zip(cols, vals))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("seq")
    ap.add_argument("--crop")
    ap.add_argument("--thresholds", choices=sorted(PRESETS), default="low")
    ap.add_argument("--magnitude", type=float)
    ap.add_argument("--sum", type=float)
    ap.add_argument("--erode", type=int)
    ap.add_argument("--dilate", type=int)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--track", action="append", default=[])
    ap.add_argument("--track-args", default="")
    a = ap.parse_args()
    crop = tuple(int(v) for v in a.crop.split(",")) if a.crop else None
    if crop is not None and len(crop) != 4:
        raise SystemExit("--crop takes X,Y,W,H")
    th = list(PRESETS[a.thresholds])
    for k, v in enumerate((a.magnitude, a.sum, a.erode, a.dilate)):
        if v is not None:
            th[k] = v
    names = sorted(n for n in os.listdir(a.seq) if n.lower().endswith(".png"))
    if len(names) < 2:
        raise SystemExit(f"{a.seq}: needs a reference and at least one frame")
    frames = [read_gray(os.path.join(a.seq, n), crop) for n in names]
    ref, rest = frames[0], frames[1:]
    cv2.setNumThreads(a.threads)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_FAST)
    dis.calc(ref, rest[0], None)  # warm-up

    per_frame = [{s: [] for s in STAGES} for _ in rest]
    track_runs = {b: [] for b in a.track}
    patches = largest = 0
    for _ in range(a.rounds):
        for k, cur in enumerate(rest):
            t, _, boxes = process(dis, ref, cur, th)
            for s in STAGES:
                per_frame[k][s].append(t[s])
            patches = max(patches, len(boxes))
            for _, _, w, h in boxes:
                largest = max(largest, w * h)
        for b in a.track:
            track_runs[b].append(run_track(a, b))
    print(
        f"paper pipeline (OpenCV {cv2.__version__} DIS FAST, {a.threads} threads; "
        f"thresholds {th[0]} px / {th[1]} / {th[2]} / {th[3]}): {len(rest)} frames x "
        f"{a.rounds} rounds, at most {patches} patches, the largest {largest} px"
    )
    print(f"{'ms':<8}" + "".join(f" {s:>9}" for s in STAGES))
    med = {s: [statistics.median(f[s]) for f in per_frame] for s in STAGES}
    for label, q in (("median", 0.5), ("p90", 0.9), ("max", 1.0)):
        print(f"{label:<8}" + "".join(f" {quantile(med[s], q):>9.2f}" for s in STAGES))
    paper = quantile(med["frame"], 0.5)
    for b, runs in track_runs.items():
        cols = list(runs[0])
        print(f"track {b} ({' '.join([a.seq] + a.track_args.split())}), medians over {len(runs)} rounds:")
        print(f"{'ms':<8}" + "".join(f" {c:>9}" for c in cols))
        print(f"{'median':<8}" + "".join(f" {statistics.median(r[c] for r in runs):>9.2f}" for c in cols))
        ours = statistics.median(r["process"] for r in runs)
        rounds = ", ".join(f"{r['process']:.2f}" for r in runs)
        print(
            f"median process {ours:.2f} ms (rounds: {rounds}); paper pipeline median "
            f"{paper:.2f} ms; ratio {paper / ours:.1f}x"
        )


if __name__ == "__main__":
    main()
