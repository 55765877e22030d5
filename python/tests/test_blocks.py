"""The stages alone: dis_flow against the Rust `flow` example, nhhd against
the reference decompositions in fixtures/hhd, segment."""

from __future__ import annotations

import json

import numpy as np
import pytest

import optical_tactile as ot
from conftest import FIXTURES, PRESS, example, run


def read_flo(path) -> np.ndarray:
    """A Middlebury .flo file as a float32 (H, W, 2) array."""
    data = np.fromfile(path, dtype="<f4")
    assert data[0] == np.float32(202021.25), "bad .flo magic"
    w, h = np.frombuffer(data[1:3].tobytes(), dtype="<i4")
    return data[3:].reshape(h, w, 2)


@pytest.mark.parametrize("preset", ["accurate", "fast"])
def test_dis_flow_equals_flow_example_bit_for_bit(preset, tmp_path):
    ref, cur = PRESS / "000000.png", PRESS / "000006.png"
    out = tmp_path / "flow.flo"
    run([example("flow"), ref, cur, "--preset", preset, "--repeat", "1", "--out", out])
    expected = read_flo(out)
    got = ot.dis_flow(ot.read_image(ref), ot.read_image(cur), preset=preset)
    assert got.dtype == np.float32 and got.shape == expected.shape == (200, 1600, 2)
    assert np.abs(got).max() > 0.5  # the press moved the markers
    assert got.tobytes() == expected.tobytes()


def test_dis_flow_of_a_frame_with_itself_is_zero_and_dtypes_agree():
    ref = ot.read_image(PRESS / "000000.png")
    cur = ot.read_image(PRESS / "000007.png")
    assert np.abs(ot.dis_flow(ref, ref, preset="fast")).max() < 1e-3
    a = ot.dis_flow(ref, cur, preset="fast")
    b = ot.dis_flow(ref.astype(np.uint8), cur.astype(np.uint8), preset="fast")
    assert np.array_equal(a, b)


@pytest.mark.parametrize("case", ["analytic_17x23", "press_32x32", "random_12x40"])
def test_nhhd_matches_the_reference_decomposition(case):
    d = FIXTURES / "hhd" / case
    dx, dy = map(float, (d / "spacing.txt").read_text().split())
    u, v = np.load(d / "u.npy"), np.load(d / "v.npy")
    dd, rr, hh, D, R = ot.nhhd(u, v, dx, dy)
    for got, name in [(D, "D"), (R, "R")]:
        want = np.load(d / f"{name}.npy")
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9 * np.abs(want).max())
    for field, name in [(dd, "d"), (rr, "r"), (hh, "h")]:
        for k, comp in enumerate("uv"):
            want = np.load(d / f"{name}_{comp}.npy")
            np.testing.assert_allclose(
                field[..., k], want, rtol=1e-9, atol=1e-9 * max(np.abs(want).max(), 1e-300)
            )
    # The three parts add up to the field.
    np.testing.assert_allclose(dd + rr + hh, np.stack([u, v], axis=-1), atol=1e-9)
    # float32 input is decomposed too.
    D32 = ot.nhhd(u.astype(np.float32), v.astype(np.float32), dx, dy)[3]
    np.testing.assert_allclose(D32, D, rtol=1e-4, atol=1e-4 * np.abs(D).max())


def test_segment_finds_the_two_rods():
    ref = ot.read_image(PRESS / "000000.png")
    cur = ot.read_image(PRESS / "000007.png")
    flow = ot.dis_flow(ref, cur, preset="accurate")
    patches = ot.segment(flow, "low")
    assert len(patches) == 2
    left, right = sorted(patches, key=lambda p: p.bbox[0])
    # The rods press at columns ~700 and ~900 of the strip.
    assert left.bbox[0] < 700 < left.bbox[0] + left.bbox[2]
    assert right.bbox[0] < 900 < right.bbox[0] + right.bbox[2]
    assert all(p.flow_sum > 0 and p.area > 0 for p in patches)
    # No motion, no patch; thresholds above the motion, no patch.
    assert ot.segment(np.zeros_like(flow)) == []
    assert ot.segment(flow, {"magnitude": 50.0}) == []


def test_simulated_pair_through_the_sensor(calibration, tmp_path):
    n = ot.simulate("pair", tmp_path / "pair", frames=4, force_n=2.0, force2_n=2.0)
    assert n == 4
    frames = list(ot.Sequence(tmp_path / "pair"))
    assert len(frames) == 4
    sensor = ot.Sensor.from_calibration(calibration)
    sensor.set_reference(frames[0][2])
    last = sensor.process(frames[-1][2], frames[-1][1])
    assert len(last) == 2
    # The synthetic sensor in memory renders the same frames (same seed and index).
    sim = ot.SyntheticSensor(seed=1)
    assert sim.crop == (0, 0, 1600, 200)
    img, flow = sim.render([], index=0)
    assert flow is None and img.shape == (200, 1600)
    assert np.array_equal(img, frames[0][2])
    press = ot.Press(-20.0, (0.0, 0.0, -2.0), 5.0)
    img, flow = sim.render([press], index=1, flow=True)
    assert flow.shape == (200, 1600, 2) and np.abs(flow).max() > 0.5
    with pytest.raises(ValueError, match="scenario"):
        ot.simulate("hover", tmp_path / "x")
    with pytest.raises(ValueError, match="spacing_mm"):
        ot.simulate("pair", tmp_path / "x", spacing=10)
    # Counts are bounded before anything is written; the library checks the rest.
    with pytest.raises(ValueError, match="frames"):
        ot.simulate("pair", tmp_path / "big", frames=10**12)
    with pytest.raises(ValueError, match="repeats"):
        ot.simulate("characterization", tmp_path / "big", repeats=10**6)
    with pytest.raises(ValueError, match="frames"):
        ot.simulate("single", tmp_path / "big", frames=1)
    with pytest.raises(ValueError, match="force"):
        ot.simulate("single", tmp_path / "big", force_n=float("nan"))
    with pytest.raises(TypeError, match="frames"):
        ot.simulate("single", tmp_path / "big", frames=-1)
    assert not (tmp_path / "big").exists() or not any((tmp_path / "big").iterdir())


def test_simulated_fingertip_sensor(tmp_path):
    # Presses of round tips anywhere on the flat gel: 320x240 frames, and
    # truth in both surface coordinates.
    n = ot.simulate("presses", tmp_path / "p", sensor="fingertip", presses=3, seed=2)
    assert n == 4
    frames = list(ot.Sequence(tmp_path / "p"))
    assert frames[0][2].shape == (240, 320)
    truth = [json.loads(line) for line in open(tmp_path / "p" / "truth.jsonl")]
    loaded = [c for r in truth for c in r["contacts"]]
    assert len(loaded) == 3
    assert any(c["y_mm"] != 0.0 for c in loaded)
    assert all(abs(c["x_mm"]) < 12.0 and abs(c["y_mm"]) < 9.0 for c in loaded)
    # Another press seed: other presses on the same sensor.
    ot.simulate("presses", tmp_path / "q", sensor="fingertip", presses=3, seed=2, press_seed=3)
    other = [c for r in map(json.loads, open(tmp_path / "q" / "truth.jsonl")) for c in r["contacts"]]
    assert len(other) == 3 and other != loaded
    assert (tmp_path / "q" / "000000.png").read_bytes() == (tmp_path / "p" / "000000.png").read_bytes()
    # The flat protocol writes the geometry `calibrate` reads.
    ot.simulate("characterization", tmp_path / "c", sensor="fingertip", subset=2)
    geometry = json.loads((tmp_path / "c" / "geometry.json").read_text())
    assert geometry["kind"] == "flat"
    # A pair on the flat gel: two spheres 8 mm apart on its centre line;
    # spheres set too far apart to fit on the gel are refused.
    ot.simulate("pair", tmp_path / "pair", sensor="fingertip", frames=3)
    last = json.loads(open(tmp_path / "pair" / "truth.jsonl").read().splitlines()[-1])
    assert sorted(c["x_mm"] for c in last["contacts"]) == [-4.0, 4.0]
    assert all(c["y_mm"] == 0.0 for c in last["contacts"])
    with pytest.raises(ValueError, match="spacing_mm"):
        ot.simulate("pair", tmp_path / "far", sensor="fingertip", spacing_mm=30.0)
    # A position sweep on the strip: one load moved in equal steps.
    ot.simulate("single", tmp_path / "s", frames=4, x_mm=10.0, sweep_to_mm=12.0)
    xs = [r["contacts"][0]["x_mm"] for r in map(json.loads, open(tmp_path / "s" / "truth.jsonl")) if r["contacts"]]
    assert len(xs) == 3 and xs[0] < xs[1] < xs[2]
    with pytest.raises(ValueError, match="sensor"):
        ot.simulate("presses", tmp_path / "x", sensor="cylinder")
    with pytest.raises(ValueError, match="x_max_mm"):
        ot.simulate("presses", tmp_path / "x", sensor="fingertip", x_max_mm=5.0)


def test_characterization_writes_sweeps(tmp_path):
    # Sweeps every 60 mm of arc from point 2 to point 14: 5 images per sweep,
    # two sweeps, beside two tests of the protocol.
    ot.simulate("characterization", tmp_path / "c", subset=2, sweep_step_mm=60.0)
    lines = (tmp_path / "c" / "sweeps.csv").read_text().splitlines()
    assert lines[0] == "sweep,frame,reference,indenter_mm,force_n,x_mm,y_mm,fx_n,fy_n,fz_n"
    rows = [line.split(",") for line in lines[1:]]
    assert len(rows) == 10
    assert sorted({r[0] for r in rows}) == ["0", "1"]
    assert all((tmp_path / "c" / r[1]).exists() for r in rows)
    # With the tilted sweeps, two more whose loads lean each way along the strip.
    ot.simulate(
        "characterization", tmp_path / "t", subset=2, sweep_step_mm=60.0, tilted_sweeps=True
    )
    lines = (tmp_path / "t" / "sweeps.csv").read_text().splitlines()
    rows = [line.split(",") for line in lines[1:]]
    assert sorted({r[0] for r in rows}) == ["0", "1", "2", "3"]
    fx = {r[0]: float(r[7]) for r in rows}
    assert fx["2"] > 0.4 and fx["3"] < -0.4 and abs(fx["0"]) < 0.05
    # A subset alone writes none; a negative step is refused.
    ot.simulate("characterization", tmp_path / "d", subset=2)
    assert not (tmp_path / "d" / "sweeps.csv").exists()
    with pytest.raises(ValueError, match="sweep_step_mm"):
        ot.simulate("characterization", tmp_path / "e", subset=1, sweep_step_mm=-1.0)


def test_characterization_writes_spot_checks(tmp_path):
    # Spot checks after the tests: split `spot`, point 0, the protocol's rods.
    ot.simulate("characterization", tmp_path / "c", subset=2, spot_checks=3)
    lines = (tmp_path / "c" / "tests.csv").read_text().splitlines()
    head = lines[0].split(",")
    rows = [dict(zip(head, line.split(","))) for line in lines[1:]]
    assert [r["split"] for r in rows].count("spot") == 3
    for r in rows[2:]:
        assert r["split"] == "spot" and r["point"] == "0"
        assert float(r["indenter_mm"]) in (2.0, 5.0, 10.0)
        assert (tmp_path / "c" / r["frame"]).exists()
    with pytest.raises(ValueError, match="spot_checks"):
        ot.simulate("characterization", tmp_path / "e", subset=1, spot_checks=10**9)


def test_simulate_takes_the_command_lines_sensor_flags(tmp_path):
    # The same sensor options make the same frames as the command line's flags.
    flags = (
        "--sensor fingertip --random-markers --coverage 0.2 --marker-depth-mm 0.3,0.8 "
        "--youngs-kpa 800 --noise-read 2 --exposure-steps 1,0.02,3 --contact-light -0.3"
    )
    run([example("simulate"), "single", "--out", tmp_path / "cli", "--frames", "3", "--no-flow", "-q"]
        + flags.split())
    ot.simulate(
        "single", tmp_path / "py", frames=3, sensor="fingertip", random_markers=True,
        coverage=0.2, marker_depth_mm=(0.3, 0.8), youngs_kpa=800.0, noise_read=2.0,
        exposure_steps=(1, 0.02, 3), contact_light=-0.3,
    )
    names = sorted(p.name for p in (tmp_path / "cli").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "py").iterdir())
    for name in names:
        assert (tmp_path / "cli" / name).read_bytes() == (tmp_path / "py" / name).read_bytes(), name
    # And other options other frames.
    ot.simulate("single", tmp_path / "grid", frames=3, sensor="fingertip", pitch_px=26.0)
    assert (tmp_path / "grid" / "000001.png").read_bytes() != (tmp_path / "py" / "000001.png").read_bytes()
    # What does not make a sensor is refused before anything is written.
    for bad in [
        dict(sensor="fingertip", dot_grid=True),
        dict(random_markers=True),
        dict(exposure_steps=(1,)),
        dict(exposure_steps=(0, 0.02)),
        dict(exposure_steps=(float("nan"), 0.02)),
        dict(exposure_steps=(1, float("nan"))),
        dict(drift=(0.05, 4.0)),
        dict(marker_depth_mm=(3.0, 1.0)),
        dict(markers=10**11),
        dict(coverage=2.0),
        dict(contact_light=5.0),
    ]:
        with pytest.raises(ValueError):
            ot.simulate("single", tmp_path / "bad", frames=3, **bad)
        assert not (tmp_path / "bad").exists() or not any((tmp_path / "bad").iterdir()), bad
    with pytest.raises(TypeError):
        ot.simulate("single", tmp_path / "bad", frames=3, youngs_kpa="soft")
    with pytest.raises(ValueError, match="youngs_kpa"):
        ot.simulate("single", tmp_path / "bad", frames=3, young_kpa=70.0)


def test_calibrate_takes_the_command_lines_choices(tmp_path):
    # The strip with sweeps: each of `calibrate`'s fit flags lands in the file.
    ot.simulate("characterization", tmp_path / "s", subset=300, sweep_step_mm=20.0)

    def fitted(path, **options):
        return json.loads(ot.calibrate(path, thresholds="mid", **options).to_json())

    calls = []
    plain = json.loads(
        ot.calibrate(tmp_path / "s", thresholds="mid", progress=lambda *a: calls.append(a)).to_json()
    )
    # Progress: each stage counted up to its total (the workers report in
    # any order), the fit last.
    stages = [c[0] for c in calls]
    assert stages[0] == "tests" and stages[-2:] == ["fit", "fit"] and "sweeps" in stages
    for stage in ("tests", "sweeps"):
        done = [d for s, d, _ in calls if s == stage]
        total = {t for s, _, t in calls if s == stage}
        assert len(total) == 1 and max(done) == total.pop() and len(done) <= 101
    assert fitted(tmp_path / "s") == plain

    def fails(stage, done, total):
        raise RuntimeError(f"stop at {stage} {done}/{total}")

    with pytest.raises(RuntimeError, match="stop at tests"):
        ot.calibrate(tmp_path / "s", thresholds="mid", progress=fails)
    assert plain["column_correction"] is not None and "anchor" in plain["profile"]
    assert "spread" in plain["profile"] and "relocation" not in plain["profile"]
    assert fitted(tmp_path / "s", sweeps=False).get("column_correction") is None
    assert "anchor" not in fitted(tmp_path / "s", measured_columns=True)["profile"]
    assert fitted(tmp_path / "s", relocation="best")["profile"]["relocation"] == "best"
    assert "spread" not in fitted(tmp_path / "s", spread_channel=False)["profile"]
    # The flat fingertip's dot grid: its dots followed unless told not, the
    # `fine` flow and no light box unless asked, as `calibrate` decides.
    ot.simulate("characterization", tmp_path / "f", sensor="fingertip", subset=300)
    tip = fitted(tmp_path / "f")
    assert fitted(tmp_path / "f", geometry="flat:24x18") == tip  # its geometry.json's
    dots = tip["pipeline"]
    assert dots["dot_tracking"] and dots["flow_preset"] == "fine"
    assert "light_box_px" not in dots
    asked = fitted(tmp_path / "f", dot_tracking=False, preset="dense", light_box=24)["pipeline"]
    assert not asked.get("dot_tracking", False) and asked["flow_preset"] == "dense"
    assert asked["light_box_px"] == 24
    # Random markers on the fingertip: the denser flow on frames divided by
    # their own light.
    ot.simulate("characterization", tmp_path / "r", sensor="fingertip", random_markers=True, subset=300)
    beads = fitted(tmp_path / "r")["pipeline"]
    assert beads["flow_preset"] == "dense" and beads["light_box_px"] > 0
    assert not beads.get("dot_tracking", False)
    # Bad choices are refused before any work.
    with pytest.raises(ValueError, match="relocation"):
        ot.calibrate(tmp_path / "s", relocation="sometimes")
    with pytest.raises(ValueError, match="light_box"):
        ot.calibrate(tmp_path / "s", light_box=10**9)
    with pytest.raises(ValueError):
        ot.calibrate(tmp_path / "s", preset="blurry")
    with pytest.raises(ValueError, match="crop"):
        ot.calibrate(tmp_path / "s", crop=(0, 0, 5000, 100))
    for geometry in ["flat", "flat:24", "flat:0x18", "cylinder"]:
        with pytest.raises(ValueError, match="geometry|length_mm|width_mm"):
            ot.calibrate(tmp_path / "s", geometry=geometry)
