"""Contacts (3D location in mm, 3D force in N) from the camera frames of a
marker-based optical tactile sensor.

Frames are NumPy arrays (``uint8``, ``uint16`` or ``float32`` on the 8-bit
scale; grey ``(H, W)`` or colour ``(H, W, 3)``); contacts come out as
:class:`Contact` objects, or as a structured array with :func:`as_array`.

>>> import optical_tactile as ot
>>> cal = ot.Calibration.load("fixtures/calibration.json")
>>> sensor = ot.Sensor.from_calibration(cal)
>>> frames = ot.Sequence("fixtures/press")
>>> name, t_s, reference = next(frames)
>>> sensor.set_reference(reference)
>>> sum(len(sensor.process(image, t_s)) for name, t_s, image in frames)
12

The pipeline's stages are usable alone: :func:`dis_flow`, :func:`nhhd`,
:func:`segment`; :func:`simulate` and :class:`SyntheticSensor` make
synthetic recordings, :func:`calibrate` fits a calibration and
:func:`evaluate` scores contacts against a recording's truth. Errors derive
from :class:`OpticalTactileError` (bad input also from ``ValueError``, a
missing file from ``FileNotFoundError``).
"""

from __future__ import annotations

from typing import Iterable, Optional

import numpy as np

from ._native import (
    Calibration,
    Contact,
    FileError,
    FormatError,
    InvalidInputError,
    MissingFileError,
    OpticalTactileError,
    Patch,
    Press,
    RawContact,
    Sensor,
    Sequence,
    SyntheticSensor,
    __version__,
    calibrate,
    dis_flow,
    evaluate,
    nhhd,
    read_image,
    segment,
    simulate,
)

__all__ = [
    "CONTACT_DTYPE",
    "Calibration",
    "Contact",
    "FileError",
    "FormatError",
    "InvalidInputError",
    "MissingFileError",
    "OpticalTactileError",
    "Patch",
    "Press",
    "RawContact",
    "Sensor",
    "Sequence",
    "SyntheticSensor",
    "__version__",
    "as_array",
    "calibrate",
    "dis_flow",
    "evaluate",
    "nhhd",
    "read_image",
    "segment",
    "simulate",
]

#: The fields of :func:`as_array`: one row per contact. ``frame`` and
#: ``t_s`` say which frame it belongs to; location and force are NaN for a
#: raw sensor's patches, the force sigmas also for a calibration without an
#: uncertainty model.
CONTACT_DTYPE = np.dtype(
    [
        ("frame", np.int64),
        ("t_s", np.float64),
        ("id", np.uint64),
        ("x_mm", np.float64),
        ("y_mm", np.float64),
        ("z_mm", np.float64),
        ("fx_n", np.float64),
        ("fy_n", np.float64),
        ("fz_n", np.float64),
        ("fx_sigma_n", np.float64),
        ("fy_sigma_n", np.float64),
        ("fz_sigma_n", np.float64),
        ("x_px", np.float64),
        ("y_px", np.float64),
        ("missed", np.uint32),
        ("fallback", np.bool_),
        ("out_of_domain", np.bool_),
        ("dx", np.float64),
        ("dy", np.float64),
        ("dz", np.float64),
        ("d_pf", np.float64),
        ("area_px", np.uint64),
        ("strength", np.float64),
    ]
)


def as_array(
    contacts: Iterable[Contact],
    *,
    frame: int = -1,
    t_s: float = float("nan"),
    batch: Optional[Iterable[tuple[int, float, Iterable[Contact]]]] = None,
) -> np.ndarray:
    """Contacts as a structured array of :data:`CONTACT_DTYPE`, one row each.

    ``as_array(contacts, frame=k, t_s=t)`` tags the rows of one frame;
    ``as_array([], batch=[(k, t, contacts), ...])`` stacks many frames (a
    recording) into one array, e.g. to plot forces against time.
    """
    rows = []
    frames = [(frame, t_s, contacts)] if batch is None else batch
    for k, t, cs in frames:
        for c in cs:
            loc = c.location_mm if c.location_mm is not None else (np.nan,) * 3
            force = c.force_n if c.force_n is not None else (np.nan,) * 3
            sigma = c.force_sigma_n if c.force_sigma_n is not None else (np.nan,) * 3
            r = c.raw
            rows.append(
                (k, t, c.id, *loc, *force, *sigma, c.x_px, c.y_px, c.missed, c.fallback,
                 c.out_of_domain, *r.d_sensor, r.d_pf, r.area_px, r.strength)
            )
    return np.array(rows, dtype=CONTACT_DTYPE)
