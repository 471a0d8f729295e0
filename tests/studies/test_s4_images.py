"""S4 from pixels (opnav.studies.s4_images): `opnav run samples/s4_approach.toml --mode images` on a short arc."""

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from opnav.cli import main

ROOT = Path(__file__).resolve().parents[2]
S4 = str(ROOT / "samples" / "s4_approach.toml")
#: 21 samples a minute apart: the fewest the study takes (20) and a few seconds of frames.
SHORT = ["--set", "duration_hours=0.35", "--set", "image_step_s=60"]


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    out = tmp_path_factory.mktemp("s4") / "images"
    assert main(["run", S4, "--out", str(out), "--mode", "images", "--no-progress", "--workers", "1", *SHORT]) == 0
    return out, json.loads((out / "summary.json").read_text())


def _chunk_records_and_truths(out: Path):
    """The loop's Mars records and each frame's true Mars, as the chunks saved them."""
    from opnav.records import read_csv
    from opnav.sim.results import result_from_json

    records, truths = [], {}
    for done in sorted((out / "stream").glob("*.done.json")):
        result = result_from_json(json.loads(done.read_text()), read_csv(done.with_name(
            done.name.replace(".done.json", ".records.csv"))))
        records += [r for r in result.records if r.kind == "radec" and r.target == "mars"]
        truths.update(result.truths)
    return records, truths


def test_the_measured_mars_line_of_sight_is_within_3_sigma_of_the_truth(images):
    from opnav.sim.checks import radec_errors

    out, summary = images
    records, truths = _chunk_records_and_truths(out)
    assert len(records) == summary["image_mode"]["mars_records"] == 21
    chi2 = radec_errors(records, truths)["mars"]["chi2"]
    # each record's 2-D error against the frame's true apparent centre, under its own covariance
    assert max(chi2) < stats.chi2.ppf(0.9973, 2)
    assert summary["image_mode"]["wrong_body"]["count"] == 0
    assert summary["image_mode"]["wrong_body"]["checked"] == 21


def test_image_mode_feeds_eq1_and_the_three_federated_runs(images):
    out, summary = images
    image = summary["image_mode"]
    assert summary["mode"] == "images" and image["samples"] == 21 and image["position_records"] == 21
    assert set(summary["filters"]) == {"exact", "registered", "unregistered"}
    assert all(run["refused"] == 0 for run in summary["filters"].values())
    noise = image["achieved_noise"]
    # the sun sensor's noise as stated (2" per axis) within the chi-square bounds of 42 squares,
    # widened only by the tracker's attitude error it carries (a fraction of an arcsecond)
    low, high = (np.sqrt(stats.chi2.ppf(p, 42) / 42) for p in (0.0005, 0.9995))
    assert 2.0 * low < noise["sun"]["rms_per_axis_arcsec"] < np.hypot(2.0, 0.5) * high
    # Mars from a 7"/px frame: well below a pixel
    assert noise["mars"]["rms_per_axis_arcsec"] < 7.0 / 10
    arrays = np.load(out / "evaluation.npz")
    assert arrays["sample_image_adu"].ndim == 2 and np.all(np.isfinite(arrays["sample_fit_xy_px"]))
    from opnav.studies.report_s4 import FIGURES, IMAGE_FIGURES

    html = (out / "report.html").read_text()
    assert all(f"<figure id='fig-{name}'" in html for name in FIGURES + IMAGE_FIGURES)
    assert "From pixels: what the frames gave against the truth" in html


def test_a_sun_outside_the_sun_sensor_field_is_one_line(tmp_path, capsys):
    out = tmp_path / "blind"
    # the Sun is 124 deg from Mars: a sun sensor 60 deg from the camera and 30 deg wide never sees it
    code = main(["run", S4, "--out", str(out), "--mode", "images", "--no-progress", "--workers", "1", *SHORT,
                 "--set", "sun_sensor_from_camera_deg=60"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    assert "outside the 30.00 deg half-angle field" in err and "only 0 of 21 samples" in err


@pytest.mark.parametrize("key, value, match", [
    ("image_step_s", "90", "image_step_s must be a positive multiple of the 60 s fusion step"),
    ("angle_step_s", "0", "angle_step_s must be a positive multiple"),
    ("sun_sensor_sigma_arcsec", "-1", "sun_sensor_sigma_arcsec must be a positive number"),
    ("sun_sensor_bias_arcsec", "1,2,3", "sun_sensor_bias_arcsec"),
])
def test_bad_image_settings_are_one_line(tmp_path, capsys, key, value, match):
    code = main(["run", S4, "--out", str(tmp_path / "x"), "--mode", "images", "--no-progress", "--set",
                 f"{key}={value}"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and match in err


def test_measurement_mode_at_the_image_cadence_registers_to_the_sampled_epochs(tmp_path):
    """angle_step_s=600: one angle sample per ten fusion epochs; registered and unregistered get one
    record per sample (the registered ones after three samples), the Doppler records unchanged."""
    from opnav.studies.s4 import Settings, build_case

    case = build_case(Settings(duration_hours=4.0, angle_step_s=600.0), 3)
    positions = [r for r in case.cases["exact"] if r.kind == "position"]
    assert len(positions) == 24 and np.allclose(np.diff([r.t_tdb_s for r in positions]), 600.0)
    registered = [r for r in case.cases["registered"] if r.kind == "position"]
    held = [r for r in case.cases["unregistered"] if r.kind == "position"]
    assert len(registered) == 22 and len(held) == 24
    # each lands on the fusion epoch its sample leads by lead_s
    assert np.allclose([r.t_tdb_s for r in held], [r.t_tdb_s + 30.0 for r in positions])


def test_the_velocity_sensor_solution_that_removes_the_aberration():
    """The three radial velocities of one epoch (Sun, Canopus, Vega) are linear in the velocity: from a
    prior with the true position and a velocity 173 m/s off, one step recovers the truth; a prior
    position 1,700 km off tilts the Sun's line by |dr|/|r|, an error of the Sun's row of at most that
    times the transverse velocity, which the solve maps into the velocity."""
    from opnav.records import Measurement
    from opnav.studies.s4 import clocks, initial_state, sensor_model, Settings, STARS_HIP, true_states
    from opnav.studies.s4_images import doppler_velocity

    clock = clocks(Settings(duration_hours=4.0), 600.0)
    x0 = initial_state(clock.t0)
    t = float(clock.velocity_epochs[0])
    truth = true_states(clock.t0, x0, np.array([t]))[0]
    model, stars = sensor_model()
    records = []
    sources = [(0, "sun", -truth[:3] / np.linalg.norm(truth[:3]))] + [(hip, name, u) for name, (hip, u) in stars.items()]
    for star_id, target, direction in sources:
        template = Measurement(t, "radial_velocity", [0.0], [[1e-6]], target=target, sensor="velocity",
                               star_id=star_id, star_unit_icrf=direction)
        records.append(Measurement(t, "radial_velocity", model.predict(template, truth), [[1e-6]], target=target,
                                   sensor="velocity", star_id=star_id, star_unit_icrf=direction))
    assert len(records) == 1 + len(STARS_HIP)
    off = np.array([0.0, 0.0, 0.0, 0.1, 0.1, 0.1])
    assert np.linalg.norm(doppler_velocity(model, records, truth + off) - truth[3:]) < 1e-9
    dr = np.array([1000.0, 1000.0, 1000.0])
    bound = np.linalg.norm(np.cross(truth[3:], truth[:3] / np.linalg.norm(truth[:3]))) * np.linalg.norm(dr) / \
        np.linalg.norm(truth[:3])
    error = np.linalg.norm(doppler_velocity(model, records, truth + np.concatenate([dr, off[3:]])) - truth[3:])
    # the Sun row's error, at most the bound, goes through the solve's inverse (0.68 of the bound here)
    assert 0.0 < error < 2 * bound
