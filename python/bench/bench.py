"""Benchmark of the Python package, in one run:

1. the per-frame overhead of ``Sensor.process`` called from Python against
   the library's own ``process()`` on the same 1920x1080 frame (a simulated
   camera frame with the 1600x200 sensing strip inside it, two rods pressing),
   for ``float32``, ``uint8`` and ``uint8`` colour frames: the Python call is timed around the
   call, the library's ``process()`` inside the bindings around the Rust call
   (``Sensor.last_process_ms``), both on the same calls;
2. ``optical_tactile.dis_flow`` against OpenCV's ``cv2.DISOpticalFlow``
   (opencv-python) on the same 1920x1080 ``uint8`` pair, same preset, both
   computing both pyramids per call, each on all cores; with each flow's
   average endpoint error against the simulator's true motion.

Medians over the repeats (after a warm-up). Run from the repository root
with the package and opencv-python installed:

    python python/bench/bench.py [--repeat 60] [--flow-repeat 30]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import numpy as np

import optical_tactile as ot

HERE = os.path.dirname(os.path.abspath(__file__))
CALIBRATION = os.path.join(HERE, "..", "..", "fixtures", "calibration.json")


def median(xs):
    return statistics.median(xs)


def frames_1080p(flow: bool = False):
    """Reference and two-rod press (2.0 N and 1.5 N) of the simulated
    1920x1080 camera, and the strip's crop."""
    sim = ot.SyntheticSensor(seed=1, full_frame=True)
    ref, _ = sim.render([], index=0)
    rods = [ot.Press(-20.0, (0.0, 0.0, -2.0), 5.0), ot.Press(20.0, (0.0, 0.0, -1.5), 5.0)]
    cur, truth = sim.render(rods, index=1, flow=flow)
    return ref, cur, truth, sim.crop


def bench_sensor(repeat: int) -> None:
    ref, cur, _, crop = frames_1080p()
    cal = ot.Calibration.load(CALIBRATION)
    print(f"## Sensor.process on a {cur.shape[1]}x{cur.shape[0]} frame (strip crop {crop})")
    print(f"median of {repeat} calls after 5 warm-up calls\n")
    print("| input | Python call (ms) | library process() (ms) | overhead (ms) | overhead (% of frame) |")
    print("|---|---|---|---|---|")
    inputs = [
        ("float32 grey", lambda a: a),
        ("uint8 grey", lambda a: a.astype(np.uint8)),
        ("uint8 colour (H, W, 3)", lambda a: np.repeat(a[..., None], 3, axis=-1).astype(np.uint8)),
    ]
    for name, conv in inputs:
        r, c = conv(ref), conv(cur)
        sensor = ot.Sensor.from_calibration(cal, crop=crop, force_crop=True)
        sensor.set_reference(r)
        calls, libs, over = [], [], []
        t_s = 0.0
        for k in range(repeat + 5):
            t_s += 0.02
            t0 = time.perf_counter()
            contacts = sensor.process(c, t_s)
            dt = (time.perf_counter() - t0) * 1e3
            if k >= 5:
                lib = sensor.last_process_ms
                calls.append(dt)
                libs.append(lib)
                over.append(dt - lib)
        assert len(contacts) == 2, contacts
        mc, ml, mo = median(calls), median(libs), median(over)
        print(f"| {name} | {mc:.2f} | {ml:.2f} | {mo:.3f} | {100 * mo / ml:.1f} % |")
    print()


def aepe(flow, truth, border=16):
    d = flow[border:-border, border:-border] - truth[border:-border, border:-border]
    return float(np.sqrt((d**2).sum(-1)).mean())


def bench_flow(repeat: int) -> None:
    try:
        import cv2
    except ImportError:
        print("## dis_flow against cv2.DISOpticalFlow: skipped (pip install opencv-python)")
        return
    ref, cur, truth, (x, y, w, h) = frames_1080p(flow=True)
    r8, c8 = ref.astype(np.uint8), cur.astype(np.uint8)
    print(
        f"## dis_flow against cv2.DISOpticalFlow (OpenCV {cv2.__version__}, "
        f"{cv2.getNumThreads()} threads) on the same {r8.shape[1]}x{r8.shape[0]} uint8 pair"
    )
    print(f"median of {repeat} calls after 2 warm-up calls; AEPE on the strip, px\n")
    print("| preset | optical_tactile (ms) | OpenCV (ms) | ratio | AEPE ours | AEPE OpenCV |")
    print("|---|---|---|---|---|---|")
    presets = [
        ("ultrafast", cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST),
        ("fast", cv2.DISOPTICAL_FLOW_PRESET_FAST),
        ("medium", cv2.DISOPTICAL_FLOW_PRESET_MEDIUM),
    ]
    strip = (slice(y, y + h), slice(x, x + w))
    for name, cv_preset in presets:
        dis = cv2.DISOpticalFlow_create(cv_preset)
        ours, theirs = [], []
        for k in range(repeat + 2):
            t0 = time.perf_counter()
            f_ours = ot.dis_flow(r8, c8, preset=name)
            t1 = time.perf_counter()
            f_cv = dis.calc(r8, c8, None)
            t2 = time.perf_counter()
            if k >= 2:
                ours.append((t1 - t0) * 1e3)
                theirs.append((t2 - t1) * 1e3)
        mo, mt = median(ours), median(theirs)
        e_ours = aepe(f_ours[strip], truth[strip])
        e_cv = aepe(f_cv[strip], truth[strip])
        print(f"| {name} | {mo:.2f} | {mt:.2f} | {mt / mo:.2f}x | {e_ours:.3f} | {e_cv:.3f} |")
    print()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=60, help="timed Sensor.process calls")
    ap.add_argument("--flow-repeat", type=int, default=30, help="timed flow calls per preset")
    args = ap.parse_args()
    print(
        f"optical_tactile {ot.__version__}, numpy {np.__version__}, Python "
        f"{platform.python_version()}, {os.cpu_count()} cores\n"
    )
    bench_sensor(args.repeat)
    bench_flow(args.flow_repeat)


if __name__ == "__main__":
    main()
