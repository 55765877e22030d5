"""Type stubs of the native module (re-exported by ``optical_tactile``)."""

from __future__ import annotations

import os
import pathlib
from typing import Callable, Iterable, Iterator, Literal, Optional, Union

import numpy as np
import numpy.typing as npt

__version__: str

#: A frame: ``uint8``, ``uint16`` or ``float32`` (8-bit scale), grey
#: ``(H, W)`` or colour ``(H, W, 3)`` (also ``(H, W, 1)``, ``(H, W, 4)``);
#: each row's pixels contiguous in memory.
Frame = Union[
    npt.NDArray[np.uint8], npt.NDArray[np.uint16], npt.NDArray[np.float32]
]
#: A preset name (``"low"``, ``"mid"``, ``"high"``) or a dict with some of
#: ``magnitude`` (px), ``sum``, ``erode``, ``dilate`` (px), ``shape``
#: (``"rect"``, ``"cross"``, ``"ellipse"``).
ThresholdsArg = Union[Literal["low", "mid", "high"], dict[str, Union[float, int, str]]]
#: A DIS flow preset.
PresetName = Literal["ultrafast", "fast", "medium", "accurate", "balanced", "fine"]
#: ``(x, y, w, h)`` in pixels.
Box = tuple[int, int, int, int]
Vec3 = tuple[float, float, float]
PathLike = Union[str, os.PathLike[str]]

class OpticalTactileError(Exception):
    """Base class of every error the library raises."""

class InvalidInputError(OpticalTactileError, ValueError):
    """Bad input: shape, size, layout, NaN, a parameter out of range."""

class FormatError(OpticalTactileError, ValueError):
    """A file's content is malformed or unusable."""

class MissingFileError(OpticalTactileError, FileNotFoundError):
    """A file or directory the call needs does not exist."""

class FileError(OpticalTactileError, OSError):
    """Reading or writing a file failed (other than it missing)."""

class Calibration:
    """A sensor's calibration: the fitted maps from raw quantities to mm and
    N, with the crop, thresholds and flow settings they were fitted with."""

    @staticmethod
    def load(path: PathLike) -> Calibration:
        """Loads a calibration JSON file."""
    @staticmethod
    def from_json(text: str) -> Calibration:
        """Reads a calibration from its JSON text."""
    def to_json(self) -> str:
        """The calibration as JSON text."""
    def save(self, path: PathLike) -> None:
        """Writes the calibration to a JSON file."""
    @property
    def crop(self) -> Box:
        """The crop of the camera frame the calibration's pixels refer to."""
    @property
    def thresholds(self) -> dict[str, Union[float, int, str]]:
        """The segmentation thresholds it was fitted with."""
    @property
    def flow_preset(self) -> Optional[str]:
        """The flow preset it was fitted with, if recorded."""
    @property
    def test_mae(self) -> Optional[dict[str, float]]:
        """The test split's mean absolute errors (n, x_mm, y_mm, fx, fy, fz)."""

class RawContact:
    """The raw quantities of one contact patch, px of the cropped image."""

    x_px: float
    y_px: float
    ds1: float
    ds2: float
    dn: float
    d_pf: float
    d_sensor: Vec3
    area_px: int
    box_px: Box
    strength: float
    local_force: Optional[Vec3]

class Contact:
    """One contact: location (mm) and force (N) in the sensor frame."""

    id: int
    #: ``(x, y, z)``, mm (``None`` for a raw sensor's patch).
    location_mm: Optional[Vec3]
    #: ``(Fx, Fy, Fz)``, N; a press has ``Fz < 0`` (``None`` for a raw sensor).
    force_n: Optional[Vec3]
    #: Contact point, px of the cropped image.
    x_px: float
    y_px: float
    #: Frames in a row it has been held without a detection.
    missed: int
    #: The force came from the calibration's fallback maps.
    fallback: bool
    #: Outside what the calibration knows (extrapolated).
    out_of_domain: bool
    raw: RawContact
    @property
    def force_magnitude(self) -> Optional[float]:
        """Magnitude of the force, N."""

class Sensor:
    """The tactile sensor: an unloaded reference frame, then frames in,
    contacts out. The GIL is released while a frame is processed."""

    @staticmethod
    def from_calibration(
        calibration: Calibration,
        *,
        thresholds: Optional[ThresholdsArg] = None,
        preset: Optional[PresetName] = None,
        crop: Optional[Box] = None,
        force_crop: bool = False,
        exposure: Literal["auto", "gain-offset", "offset", "off"] | None = None,
        filter: bool = False,
        hold: Optional[int] = None,
        rereference: bool = True,
        channel: Literal["green", "luma"] = "green",
        color_order: Literal["rgb", "bgr"] = "rgb",
        dot_tracking: Optional[bool] = None,
        dot_fit: Optional[bool] = None,
    ) -> Sensor:
        """A calibrated sensor; the keywords override the calibration's settings."""
    @staticmethod
    def raw(
        *,
        crop: Optional[Box] = None,
        thresholds: Optional[ThresholdsArg] = None,
        preset: Optional[PresetName] = None,
        exposure: Literal["auto", "gain-offset", "offset", "off"] = "auto",
        channel: Literal["green", "luma"] = "green",
        color_order: Literal["rgb", "bgr"] = "rgb",
        dot_tracking: bool = True,
        dot_fit: bool = True,
    ) -> Sensor:
        """A sensor without calibration: patches with raw quantities in px."""
    def set_reference(self, frame: Frame) -> None:
        """Takes ``frame`` (nothing touching the skin) as the reference."""
    def process(self, frame: Frame, t_s: float) -> list[Contact]:
        """The contacts of ``frame``, taken at ``t_s`` seconds."""
    @property
    def calibrated(self) -> bool: ...
    @property
    def crop(self) -> Optional[Box]: ...
    @property
    def rereferenced(self) -> bool:
        """Whether the last frame became the new reference."""
    @property
    def last_process_ms(self) -> float:
        """The library's ``process()`` time of the last frame, ms."""
    def timings(self) -> dict[str, float]:
        """Time per stage of the last frame, ms: ``crop``, ``flow``, ``segment``,
        ``hhd``, ``contacts`` (calibration), ``tracking``, ``total``."""

class Sequence:
    """The PNG frames of a directory, in name order, as ``(name, t_s, image)``."""

    def __init__(
        self, path: PathLike, *, channel: Literal["green", "luma"] = "green", fps: float = 50.0
    ) -> None: ...
    def __len__(self) -> int: ...
    def __iter__(self) -> Iterator[tuple[str, float, npt.NDArray[np.float32]]]: ...
    def __next__(self) -> tuple[str, float, npt.NDArray[np.float32]]: ...
    @property
    def paths(self) -> list[pathlib.Path]: ...

class Patch:
    """One contact patch of :func:`segment`."""

    bbox: Box
    core: Box
    flow_sum: float
    area: int

class Press:
    """One rod pressing on the synthetic sensor (sensor frame)."""

    x_mm: float
    force_n: Vec3
    diameter_mm: float
    contact_width_mm: Optional[float]
    def __init__(self, x_mm: float, force_n: Vec3, diameter_mm: float = 5.0) -> None: ...
    @staticmethod
    def pad(x_mm: float, force_n: Vec3, width_mm: float) -> Press: ...

class SyntheticSensor:
    """The physics-based synthetic marker sensor."""

    def __init__(self, *, seed: int = 1, full_frame: bool = False) -> None: ...
    @property
    def crop(self) -> Box:
        """The sensing strip's rectangle in the rendered frame."""
    def render(
        self, presses: list[Press] = ..., *, index: int = 0, flow: bool = False
    ) -> tuple[npt.NDArray[np.float32], Optional[npt.NDArray[np.float32]]]:
        """Frame ``index`` under ``presses``, and the true flow if asked for."""

def read_image(
    path: PathLike, *, channel: Literal["green", "luma"] = "green"
) -> npt.NDArray[np.float32]:
    """An image file as the library reads it: float32 grey (H, W)."""

def dis_flow(
    reference: Frame,
    current: Frame,
    *,
    preset: PresetName = "accurate",
    channel: Literal["green", "luma"] = "green",
    color_order: Literal["rgb", "bgr"] = "rgb",
) -> npt.NDArray[np.float32]:
    """Dense optical flow (H, W, 2) from ``reference`` to ``current``, px."""

def nhhd(
    u: npt.NDArray[np.floating], v: npt.NDArray[np.floating], dx: float = 1.0, dy: float = 1.0
) -> tuple[
    npt.NDArray[np.float64],
    npt.NDArray[np.float64],
    npt.NDArray[np.float64],
    npt.NDArray[np.float64],
    npt.NDArray[np.float64],
]:
    """Natural Helmholtz-Hodge decomposition: ``(d, r, h, D, R)``."""

def segment(
    flow: npt.NDArray[np.float32],
    thresholds: Optional[ThresholdsArg] = None,
    *,
    margin: int = 10,
    scale: float = 1.0,
) -> list[Patch]:
    """The contact patches of a flow (H, W, 2)."""

def simulate(
    scenario: Literal[
        "single", "pair", "presses", "shear", "characterization", "perches", "mapping", "rest"
    ],
    out: PathLike,
    *,
    seed: int = 1,
    flow: bool = False,
    fps: float = 50.0,
    full_frame: bool = False,
    sensor: Literal["strip", "fingertip"] = "strip",
    **options: object,
) -> int:
    """Writes a synthetic recording into ``out``; returns the frames written.

    ``options`` are the scenario's (``force_n``, ``frames``, ``subset``, ...)
    and the sensor's, as the ``simulate`` command's flags: ``random_markers``,
    ``dot_grid``, ``youngs_kpa``, ``poisson``, ``layer_mm``, ``coverage``,
    ``markers``, ``marker_depth_mm=(min, max)``, ``pitch_px``, ``dot_px``,
    ``jitter_px``, ``noise_read``, ``flicker``,
    ``exposure_steps=(every, gain[, offset[, levels]])``,
    ``drift=(gain, offset, period)``, ``contact_light``, ``contact_shading``."""

def evaluate(
    predictions: Union[PathLike, Iterable[tuple[str, list[Contact]]]],
    truth: PathLike,
    *,
    gate_mm: float = 10.0,
    beyond_n: float = 0.3,
    worst: int = 5,
    band_mm: Optional[float] = None,
) -> dict[str, object]:
    """Scores predicted contacts (a contacts file, or ``(frame name, contacts)``
    pairs of a calibrated sensor) against a ``truth.jsonl``, as the ``evaluate``
    command does; the scores as its ``--json`` writes them."""

def calibrate(
    dataset_dir: PathLike,
    *,
    thresholds: Optional[Union[Literal["auto"], ThresholdsArg]] = None,
    preset: Optional[PresetName] = None,
    crop: Optional[Box] = None,
    sweeps: bool = True,
    measured_columns: bool = False,
    relocation: Optional[Literal["clear", "best"]] = None,
    shear_free_columns: bool = False,
    spread_channel: bool = True,
    weighted_profiles: bool = False,
    dot_tracking: Optional[bool] = None,
    dot_fit: bool = True,
    light_box: Optional[int] = None,
    geometry: Optional[str] = None,
    progress: Optional[Callable[[str, int, int], object]] = None,
) -> Calibration:
    """Fits a calibration from a characterization dataset, as the ``calibrate``
    command does with the flags of the same names; ``sweeps=False`` is
    ``--no-sweeps``, ``None`` leaves a choice to the dataset."""
