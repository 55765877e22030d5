"""Shared paths and helpers of the package's tests."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

import optical_tactile as ot

REPO = Path(__file__).resolve().parents[2]
FIXTURES = REPO / "fixtures"
PRESS = FIXTURES / "press"
CALIBRATION = FIXTURES / "calibration.json"


def _example_dirs() -> list[Path]:
    dirs = []
    if os.environ.get("OPTICAL_TACTILE_EXAMPLES"):
        dirs.append(Path(os.environ["OPTICAL_TACTILE_EXAMPLES"]))
    targets = [os.environ.get("CARGO_TARGET_DIR"), str(REPO / "target")]
    for t in targets:
        if t:
            dirs += [Path(t) / "release" / "examples", Path(t) / "debug" / "examples"]
    return dirs


def example(name: str) -> Path:
    """The built Rust example `name` (built by `cargo test` or `cargo build
    --example NAME`); skips the test if none is found, unless
    OPTICAL_TACTILE_REQUIRE_EXAMPLES=1 (CI), where that fails it."""
    for d in _example_dirs():
        p = d / name
        if p.is_file() and os.access(p, os.X_OK):
            return p
    message = (
        f"the Rust example `{name}` is not built (cargo build --release --example {name}; "
        "OPTICAL_TACTILE_EXAMPLES=DIR names its folder)"
    )
    if os.environ.get("OPTICAL_TACTILE_REQUIRE_EXAMPLES") == "1":
        pytest.fail(message)
    pytest.skip(message)


def run(args: list) -> str:
    """Runs a command, failing the test with its output if it fails."""
    p = subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, f"{args} exited {p.returncode}:\n{p.stdout}\n{p.stderr}"
    return p.stdout


@pytest.fixture(scope="session")
def calibration() -> ot.Calibration:
    return ot.Calibration.load(CALIBRATION)


@pytest.fixture(scope="session")
def press_frames() -> list:
    """The bundled press as (name, t_s, float32 image), reference first."""
    return list(ot.Sequence(PRESS))


def track(sensor: ot.Sensor, frames: list, convert=lambda img: img) -> list:
    """Runs `sensor` over `frames` (first one the reference): per processed
    frame, (name, t_s, contacts)."""
    _, _, reference = frames[0]
    sensor.set_reference(convert(reference))
    return [(name, t, sensor.process(convert(img), t)) for name, t, img in frames[1:]]
