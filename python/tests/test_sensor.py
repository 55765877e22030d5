"""The calibrated and raw sensor on the bundled press, against the Rust
`track` example."""

from __future__ import annotations

import json

import numpy as np
import pytest

import optical_tactile as ot
from conftest import CALIBRATION, FIXTURES, PRESS, example, run, track


def contact_fields(c: ot.Contact) -> dict:
    """A contact as the fields of a `track --out` JSON Lines record."""
    r = c.raw
    return {
        "id": c.id,
        "x_mm": c.location_mm[0],
        "y_mm": c.location_mm[1],
        "z_mm": c.location_mm[2],
        "fx_n": c.force_n[0],
        "fy_n": c.force_n[1],
        "fz_n": c.force_n[2],
        "x_px": c.x_px,
        "y_px": c.y_px,
        "d_pf": r.d_pf,
        "dx": r.d_sensor[0],
        "dy": r.d_sensor[1],
        "dz": r.d_sensor[2],
        "area_px": r.area_px,
        "fallback": c.fallback,
        "out_of_domain": c.out_of_domain,
        "missed": c.missed,
    } | (
        {}
        if c.force_sigma_n is None
        else dict(zip(("fx_sigma_n", "fy_sigma_n", "fz_sigma_n"), c.force_sigma_n))
    )


def read_jsonl(path) -> list:
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def test_readme_press_has_twelve_contacts(calibration, press_frames):
    sensor = ot.Sensor.from_calibration(calibration)
    found = track(sensor, press_frames)
    assert sum(len(cs) for _, _, cs in found) == 12
    # Two rods, from frame 000002 on; the left one (negative x) is the stronger.
    for name, _, cs in found:
        assert len(cs) == (0 if name == "000001.png" else 2), name
        if cs:
            left, right = sorted(cs, key=lambda c: c.location_mm[0])
            assert left.location_mm[0] < 0 < right.location_mm[0]
            assert left.force_n[2] < 0 and right.force_n[2] < 0
    last = found[-1][2]
    assert {c.id for c in last} == {c.id for c in found[1][2]}  # identities kept


def test_sensor_equals_track_example(calibration, press_frames, tmp_path):
    out = tmp_path / "contacts.jsonl"
    run([example("track"), PRESS, "--calibration", CALIBRATION, "--out", out, "--quiet"])
    expected = read_jsonl(out)
    sensor = ot.Sensor.from_calibration(calibration)
    found = track(sensor, press_frames)
    assert [r["frame"] for r in expected] == [name for name, _, _ in found]
    for rec, (name, t, cs) in zip(expected, found):
        assert rec["t_s"] == t
        got = [contact_fields(c) for c in cs]
        assert got == rec["contacts"], name


def test_evaluate_equals_the_evaluate_example(calibration, press_frames, tmp_path):
    truth = PRESS / "truth.jsonl"
    out, scores = tmp_path / "contacts.jsonl", tmp_path / "scores.json"
    run([example("track"), PRESS, "--calibration", CALIBRATION, "--out", out, "--quiet"])
    run([example("evaluate"), out, truth, "--bands", "20", "--worst", "3", "--json", scores])
    expected = json.loads(scores.read_text())
    assert ot.evaluate(out, truth, band_mm=20.0, worst=3) == expected
    # The sensor's own contacts, frame by frame: the same scores but the
    # latency, which only a contacts file records.
    found = track(ot.Sensor.from_calibration(calibration), press_frames)
    pairs = [(name, cs) for name, _, cs in found]
    got = ot.evaluate(pairs, truth, band_mm=20.0, worst=3)
    assert got["matched"] == 12 and got["false_contacts"] == 0
    assert got["median_latency_ms"] is None
    for key, value in expected.items():
        if "latency" not in key:
            assert got[key] == value, key
    # Nothing to score, bad options and a raw sensor's patches are refused.
    with pytest.raises(ValueError, match="nothing to score"):
        ot.evaluate([("elsewhere.png", [])], truth)
    with pytest.raises(ValueError, match="gate_mm"):
        ot.evaluate(out, truth, gate_mm=0.0)
    with pytest.raises(ValueError, match="worst"):
        ot.evaluate(out, truth, worst=10**6)
    raw = track(ot.Sensor.raw(), press_frames)
    with pytest.raises(ValueError, match="calibrated"):
        ot.evaluate([(name, cs) for name, _, cs in raw], truth)
    with pytest.raises(TypeError):
        ot.evaluate(5, truth)
    with pytest.raises(FileNotFoundError):
        ot.evaluate(tmp_path / "none.jsonl", truth)


def test_raw_sensor_equals_track_raw(press_frames, tmp_path):
    out = tmp_path / "raw.jsonl"
    run([example("track"), PRESS, "--raw", "--out", out, "--quiet"])
    expected = read_jsonl(out)
    found = track(ot.Sensor.raw(), press_frames)
    assert sum(len(r["contacts"]) for r in expected) > 0
    for rec, (name, _, cs) in zip(expected, found, strict=True):
        got = [
            {
                "x_px": c.x_px,
                "y_px": c.y_px,
                "box_px": list(c.raw.box_px),
                "strength": c.raw.strength,
                "ds1": c.raw.ds1,
                "ds2": c.raw.ds2,
                "dn": c.raw.dn,
                "d_pf": c.raw.d_pf,
                "area_px": c.raw.area_px,
            }
            for c in cs
        ]
        assert got == rec["contacts"], name
        assert all(c.location_mm is None and c.force_n is None for c in cs)


def _summary(found):
    return [
        (name, [(c.id, c.location_mm, c.force_n, c.x_px, c.y_px) for c in cs])
        for name, _, cs in found
    ]


@pytest.mark.parametrize(
    "convert",
    [
        pytest.param(lambda img: img.astype(np.uint8), id="uint8"),
        pytest.param(lambda img: img.astype(np.uint16) * np.uint16(257), id="uint16"),
        pytest.param(
            lambda img: np.stack([np.zeros_like(img), img, np.full_like(img, 7.0)], axis=-1),
            id="float32-rgb",
        ),
        pytest.param(
            lambda img: np.stack([img, img, img], axis=-1).astype(np.uint8), id="uint8-rgb"
        ),
        pytest.param(
            lambda img: np.pad(img.astype(np.uint8), ((3, 5), (2, 9)))[3:-5, 2:-9],
            id="uint8-crop-view",
        ),
        pytest.param(lambda img: np.pad(img, ((1, 1), (4, 4)))[1:-1, 4:-4], id="float32-crop-view"),
    ],
)
def test_dtypes_and_layouts_give_the_same_contacts(calibration, press_frames, convert):
    want = _summary(track(ot.Sensor.from_calibration(calibration), press_frames))
    got = _summary(track(ot.Sensor.from_calibration(calibration), press_frames, convert))
    assert got == want


def test_colour_order_and_luma(calibration, press_frames):
    """Luma of an RGB frame equals luma of the same frame stored as BGR with
    color_order="bgr", and differs from the frame read as RGB."""

    def rgb(img):
        return np.stack([img, img * 0.5, np.zeros_like(img)], axis=-1).astype(np.uint8)

    def bgr(img):
        return np.ascontiguousarray(rgb(img)[..., ::-1])

    def run_luma(order, convert):
        s = ot.Sensor.from_calibration(calibration, channel="luma", color_order=order)
        return _summary(track(s, press_frames, convert))

    want = run_luma("rgb", rgb)
    assert sum(len(cs) for _, cs in want) > 0
    assert run_luma("bgr", bgr) == want
    assert run_luma("rgb", bgr) != want
    with pytest.raises(ValueError, match="color_order"):
        ot.Sensor.from_calibration(calibration, color_order="rgba")
    with pytest.raises(ValueError, match="channel"):
        ot.Sensor.raw(channel="red")


def test_overrides_change_the_sensor(calibration, press_frames):
    # The calibration's crop is the whole 1600x200 strip; another crop is
    # refused unless forced.
    with pytest.raises(ValueError, match="force_crop"):
        ot.Sensor.from_calibration(calibration, crop=(0, 0, 800, 200))
    s = ot.Sensor.from_calibration(calibration, crop=(0, 0, 800, 200), force_crop=True)
    assert s.crop == (0, 0, 800, 200)
    found = track(s, press_frames)
    # Only the left rod lies in the left half.
    assert max(len(cs) for _, _, cs in found) == 1
    # The most robust thresholds miss the weakest frames' presses.
    high = track(
        ot.Sensor.from_calibration(calibration, thresholds={"magnitude": 0.9, "sum": 20000}),
        press_frames,
    )
    default = track(ot.Sensor.from_calibration(calibration), press_frames)
    assert sum(map(len, (c for _, _, c in high))) < sum(map(len, (c for _, _, c in default)))
    # Kalman smoothing keeps the contacts and changes their estimates.
    smooth = track(ot.Sensor.from_calibration(calibration, filter=True), press_frames)
    assert [len(cs) for _, _, cs in smooth] == [len(cs) for _, _, cs in default]
    assert _summary(smooth) != _summary(default)
    # Another flow preset measures other raw quantities.
    fast = track(ot.Sensor.from_calibration(calibration, preset="fast"), press_frames)
    assert _summary(fast) != _summary(default)
    with pytest.raises(ValueError, match="preset"):
        ot.Sensor.from_calibration(calibration, preset="slowest")
    with pytest.raises(ValueError, match="thresholds"):
        ot.Sensor.from_calibration(calibration, thresholds="medium")
    with pytest.raises(ValueError, match="exposure"):
        ot.Sensor.from_calibration(calibration, exposure="sometimes")


def test_as_array_is_a_structured_batch(calibration, press_frames):
    found = track(ot.Sensor.from_calibration(calibration), press_frames)
    batch = ot.as_array([], batch=[(k, t, cs) for k, (_, t, cs) in enumerate(found)])
    assert batch.dtype == ot.CONTACT_DTYPE
    assert len(batch) == 12
    last = found[-1][2]
    rows = batch[batch["frame"] == len(found) - 1]
    assert list(rows["id"]) == [c.id for c in last]
    assert list(rows["fz_n"]) == [c.force_n[2] for c in last]
    # The bundled calibration carries a force uncertainty: every contact a sigma.
    assert list(rows["fz_sigma_n"]) == [c.force_sigma_n[2] for c in last]
    assert (rows["fz_sigma_n"] > 0).all()
    assert list(rows["t_s"]) == [found[-1][1]] * len(last)
    raw = ot.as_array(track(ot.Sensor.raw(), press_frames)[-1][2])
    assert len(raw) > 0 and np.isnan(raw["x_mm"]).all() and (raw["strength"] > 0).all()
    assert np.isnan(raw["fz_sigma_n"]).all()


def test_calibration_round_trips_and_describes_itself(calibration, tmp_path):
    assert calibration.crop == (0, 0, 1600, 200)
    assert calibration.flow_preset == "fine"
    assert set(calibration.thresholds) == {"magnitude", "sum", "erode", "dilate", "shape"}
    path = tmp_path / "cal.json"
    calibration.save(path)
    again = ot.Calibration.load(path)
    assert again.to_json() == calibration.to_json()
    assert ot.Calibration.from_json(calibration.to_json()).crop == calibration.crop


def test_sequence_and_read_image(press_frames):
    seq = ot.Sequence(PRESS)
    assert len(seq) == 8
    names = [n for n, _, _ in press_frames]
    assert names == [f"{k:06}.png" for k in range(8)]
    assert [t for _, t, _ in press_frames] == [k / 50 for k in range(8)]
    img = ot.read_image(PRESS / "000003.png")
    assert img.dtype == np.float32 and img.shape == (200, 1600)
    assert np.array_equal(img, press_frames[3][2])


def test_frame_larger_than_the_crop(calibration, press_frames):
    """A camera frame with the strip inside it: integer frames are converted
    within the crop only, and give the contacts of the float32 frame."""

    def canvas(img):
        out = np.full((280, 1700), 255.0, np.float32)
        out[40:240, 60:1660] = img
        return out

    def sensor():
        return ot.Sensor.from_calibration(calibration, crop=(60, 40, 1600, 200), force_crop=True)

    want = _summary(track(sensor(), press_frames, canvas))
    assert sum(len(cs) for _, cs in want) == 12
    for convert in (
        lambda img: canvas(img).astype(np.uint8),
        lambda img: (canvas(img).astype(np.uint16) * np.uint16(257)),
        lambda img: np.repeat(canvas(img)[..., None], 3, axis=-1).astype(np.uint8),
    ):
        assert _summary(track(sensor(), press_frames, convert)) == want
    # The same contacts as the strip alone with the calibration's own crop.
    strip = _summary(track(ot.Sensor.from_calibration(calibration), press_frames))
    assert [[(c[0], c[3], c[4]) for c in cs] for _, cs in want] == [
        [(c[0], c[3], c[4]) for c in cs] for _, cs in strip
    ]


def test_dot_tracking_follows_the_calibration_unless_overridden(tmp_path):
    """The flat fingertip sensor's calibration follows its dots one by one:
    the Python sensor does as `track` does, and `dot_tracking=False` reads
    the flow alone, `dot_fit=False` the patches' sums. A raw sensor follows
    the dots and fits their field too, as `track --raw` does, unless asked
    not to."""
    flat = FIXTURES / "flat_press"
    cal_path = FIXTURES / "flat_calibration.json"
    frames = list(ot.Sequence(flat))
    cal = ot.Calibration.load(cal_path)
    out = tmp_path / "flat.jsonl"
    run([example("track"), flat, "--calibration", cal_path, "--out", out, "--quiet"])
    expected = read_jsonl(out)
    followed = track(ot.Sensor.from_calibration(cal), frames)
    assert [[c.location_mm[0] for c in cs] for _, _, cs in followed] == [
        [c["x_mm"] for c in r["contacts"]] for r in expected
    ]
    alone = track(ot.Sensor.from_calibration(cal, dot_tracking=False), frames)
    xs = lambda found: [round(c.location_mm[0], 9) for _, _, cs in found for c in cs]
    assert xs(followed) and xs(alone) != xs(followed)
    # The dots' fitted field: on as the calibration says, off on request.
    unfitted = track(ot.Sensor.from_calibration(cal, dot_fit=False), frames)
    assert xs(unfitted) and xs(unfitted) != xs(followed)
    raw = lambda **kw: [c.raw.ds1 for _, _, cs in track(ot.Sensor.raw(**kw), frames) for c in cs]
    assert raw() == raw(dot_tracking=True) == raw(dot_fit=True)
    assert raw() != raw(dot_tracking=False)
    assert raw() != raw(dot_fit=False)
    out = tmp_path / "raw.jsonl"
    run([example("track"), flat, "--raw", "--out", out, "--quiet"])
    assert raw() == [c["ds1"] for r in read_jsonl(out) for c in r["contacts"]]
