"""Bad input raises a Python exception with the library's message; nothing
panics, aborts or hangs."""

from __future__ import annotations

import numpy as np
import pytest

import optical_tactile as ot
from conftest import FIXTURES, PRESS


@pytest.fixture()
def sensor(calibration, press_frames):
    s = ot.Sensor.from_calibration(calibration)
    s.set_reference(press_frames[0][2])
    return s


FRAME = np.zeros((200, 1600), np.float32)


def test_exception_hierarchy():
    assert issubclass(ot.InvalidInputError, ot.OpticalTactileError)
    assert issubclass(ot.InvalidInputError, ValueError)
    assert issubclass(ot.FormatError, ValueError)
    assert issubclass(ot.MissingFileError, FileNotFoundError)
    assert issubclass(ot.FileError, OSError)


@pytest.mark.parametrize(
    "frame",
    [
        pytest.param(FRAME.astype(np.int32), id="int32"),
        pytest.param(FRAME.astype(np.float64), id="float64"),
        pytest.param(FRAME.astype(">f4"), id="big-endian"),
        pytest.param(FRAME.astype(bool), id="bool"),
        pytest.param(FRAME.tolist(), id="list"),
        pytest.param(None, id="None"),
    ],
)
def test_wrong_dtype_or_type_is_a_type_error(sensor, frame):
    with pytest.raises(TypeError, match="uint8, uint16 or float32|numpy.ndarray"):
        sensor.process(frame, 1.0)


@pytest.mark.parametrize(
    "frame, match",
    [
        (np.zeros((200, 1600, 2), np.float32), "shape"),
        (np.zeros((1, 200, 1600, 3), np.uint8), "shape"),
        (np.zeros(1600, np.uint8), "shape"),
        (np.zeros((0, 1600), np.uint8), "empty|small"),
        (np.zeros((100, 1600), np.uint8), "expected 1600x200, got 1600x100"),
        (np.zeros((200, 3200), np.float32)[:, ::2], "contiguous"),
        (np.zeros((1600, 200), np.float32).T, "contiguous"),
        (np.zeros((200, 1600, 3), np.uint8)[:, :, 1], "contiguous"),
        (np.zeros((1, 16385), np.uint8), "larger than the largest frame"),
        (np.zeros((5800, 5800), np.uint8), "larger than the largest frame"),
    ],
)
def test_wrong_shape_layout_or_size_is_a_value_error(sensor, frame, match):
    with pytest.raises(ot.InvalidInputError, match=match):
        sensor.process(frame, 1.0)


def test_nan_and_infinity_are_value_errors(sensor, calibration, press_frames):
    bad = FRAME.copy()
    bad[10, 20] = np.nan
    with pytest.raises(ValueError, match="non-finite|NaN|finite"):
        sensor.process(bad, 1.0)
    bad[10, 20] = np.inf
    with pytest.raises(ValueError, match="non-finite|NaN|finite"):
        sensor.process(bad, 1.0)
    fresh = ot.Sensor.from_calibration(calibration)
    bad[10, 20] = np.nan
    with pytest.raises(ValueError):
        fresh.set_reference(bad)
    with pytest.raises(ValueError, match="t_s"):
        sensor.process(FRAME, float("nan"))
    with pytest.raises(ValueError):
        ot.dis_flow(bad, FRAME)
    with pytest.raises(ValueError, match="non-finite"):
        ot.nhhd(np.full((4, 4), np.nan), np.zeros((4, 4)))
    # The sensor still works after the errors.
    _, t, img = press_frames[-1]
    assert len(sensor.process(img, t)) == 2


def test_no_reference_yet(calibration):
    for s in (ot.Sensor.from_calibration(calibration), ot.Sensor.raw()):
        with pytest.raises(ot.OpticalTactileError, match="reference"):
            s.process(FRAME, 0.0)


def test_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.json"):
        ot.Calibration.load(tmp_path / "nope.json")
    with pytest.raises(FileNotFoundError):
        ot.read_image(tmp_path / "nope.png")
    with pytest.raises(ot.OpticalTactileError):
        ot.Sequence(tmp_path / "empty-or-missing")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError):
        ot.Calibration.load(bad)
    with pytest.raises(ValueError):
        ot.Calibration.from_json('{"version": 99}')
    png = tmp_path / "bad.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 40)
    with pytest.raises(ot.FormatError):
        ot.read_image(png)
    with pytest.raises(OSError):
        ot.read_image(tmp_path)  # a directory


def test_building_blocks_check_their_input():
    a = np.zeros((20, 30), np.float32)
    with pytest.raises(ot.InvalidInputError, match="expected 30x20, got 31x20"):
        ot.dis_flow(a, np.zeros((20, 31), np.float32))
    with pytest.raises(ValueError, match="preset"):
        ot.dis_flow(a, a, preset="slow")
    with pytest.raises(ValueError):
        ot.nhhd(np.zeros((4, 5)), np.zeros((5, 4)))
    with pytest.raises(ValueError, match="2-D"):
        ot.nhhd(np.zeros(5), np.zeros(5))
    with pytest.raises(TypeError):
        ot.nhhd(np.zeros((4, 4), np.int64), np.zeros((4, 4)))
    with pytest.raises(ValueError):
        ot.nhhd(np.zeros((4, 4)), np.zeros((4, 4)), dx=0.0)
    with pytest.raises(ValueError, match="shape"):
        ot.segment(np.zeros((20, 30, 3), np.float32))
    with pytest.raises(TypeError):
        ot.segment(np.zeros((20, 30, 2), np.float64))
    with pytest.raises(ValueError, match="unknown key"):
        ot.segment(np.zeros((20, 30, 2), np.float32), {"magnitud": 1.0})
    with pytest.raises(ValueError, match="magnitude"):
        ot.segment(np.zeros((20, 30, 2), np.float32), {"magnitude": -1.0})
    with pytest.raises(ValueError, match="erode"):
        ot.segment(np.zeros((20, 30, 2), np.float32), {"erode": 100000})


def test_calibrate_on_too_few_tests_is_a_clear_error():
    with pytest.raises(ot.OpticalTactileError, match="train|sample|fit"):
        ot.calibrate(FIXTURES / "characterization")
    with pytest.raises(FileNotFoundError):
        ot.calibrate(PRESS)  # no tests.csv
