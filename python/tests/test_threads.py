"""Frames processed from several Python threads at once; the GIL is released
while a frame is processed (checked by progress, not by time)."""

from __future__ import annotations

import sys
import threading
import time

import optical_tactile as ot
from conftest import track


def _summary(found):
    return [(n, [(c.id, c.location_mm, c.force_n) for c in cs]) for n, _, cs in found]


def test_two_threads_two_sensors_give_the_sequential_results(calibration, press_frames):
    want = _summary(track(ot.Sensor.from_calibration(calibration), press_frames))
    results, errors = {}, []

    def worker(k):
        try:
            results[k] = _summary(track(ot.Sensor.from_calibration(calibration), press_frames))
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(e)

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert results[0] == want and results[1] == want


def test_one_sensor_shared_by_two_threads(calibration, press_frames):
    sensor = ot.Sensor.from_calibration(calibration)
    sensor.set_reference(press_frames[0][2])
    counts, errors = [], []

    def worker():
        try:
            for _, t, img in press_frames[1:]:
                counts.append(len(sensor.process(img, t)))
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(e)

    threads = [threading.Thread(target=worker) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert len(counts) == 2 * (len(press_frames) - 1)
    assert all(n <= 2 for n in counts)


def progress_during(calls) -> int:
    """How many times a second Python thread got to run while `calls` were
    inside the library. With a switch interval far longer than the test,
    the interpreter never takes the GIL from the calling thread: the other
    thread can only run where the call itself releases the GIL, so the count
    is 0 if it does not, whatever the timing."""
    counter = [0]
    stop = threading.Event()

    def spin():
        while not stop.is_set():
            counter[0] += 1
            time.sleep(0)  # gives the GIL back after each step

    old = sys.getswitchinterval()
    sys.setswitchinterval(1000.0)
    spinner = threading.Thread(target=spin)
    try:
        spinner.start()
        progressed = 0
        for call in calls:
            before = counter[0]
            call()
            progressed += counter[0] - before
    finally:
        stop.set()
        spinner.join()
        sys.setswitchinterval(old)
    return progressed


def test_the_gil_is_released_while_a_frame_is_processed(calibration, press_frames):
    sensor = ot.Sensor.from_calibration(calibration)
    sensor.set_reference(press_frames[0][2])
    calls = [lambda img=img, t=t: sensor.process(img, t) for _, t, img in press_frames[1:]]
    assert progress_during(calls) > 0


def test_the_gil_is_released_by_dis_flow(press_frames):
    ref, cur = press_frames[0][2], press_frames[-1][2]
    assert progress_during([lambda: ot.dis_flow(ref, cur)] * 3) > 0


def test_the_check_can_fail():
    """The same check on a call that keeps the GIL sees no progress."""

    def busy():
        x = 0
        for k in range(200_000):
            x += k
        return x

    assert progress_during([busy] * 3) == 0
