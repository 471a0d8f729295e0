"""The mission from pixels (opnav.studies.mission_images): the pointing law, the records checked against
the truth, and a short image-mode run of the sample whose records sit inside their own covariance."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from opnav.cli import main
from opnav.constants import ARCSEC_RAD
from opnav.errors import InputError
from opnav.measurements import ProbeMeasurementModel
from opnav.records import Measurement
from opnav.studies import mission
from opnav.studies.mission_images import body_attitude, check_records
from opnav.studies.settings import load_run_file

SAMPLE = Path(__file__).resolve().parents[2] / "samples" / "cislunar.toml"


def test_the_pointing_law_puts_the_target_on_the_boresight_and_the_sun_on_plus_x():
    rng = np.random.default_rng(3)
    for _ in range(50):
        u, s = rng.standard_normal((2, 3))
        u, s = u / np.linalg.norm(u), s / np.linalg.norm(s)
        R = body_attitude(u, s)
        assert np.allclose(R.apply([0.0, 0.0, 1.0]), u, atol=1e-12)
        sun_body = R.inv().apply(s)
        assert sun_body[0] > 0.0 and abs(sun_body[1]) < 1e-12  # in the x-z half-plane, +x side
        assert np.isclose(np.linalg.det(R.as_matrix()), 1.0)
    with pytest.raises(InputError, match="in line"):
        body_attitude(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0]))


def test_check_records_counts_a_record_of_the_wrong_body_and_the_noise_it_has():
    """Records drawn about the truth at 2 arcsec come back with ~2 arcsec achieved noise and chi-square
    ~1 per axis; a Moon record carrying the Earth's direction is one wrong-body record and a gross error."""
    settings = mission.Settings(stop="2027-03-10T11:00:00")
    t0, epochs = mission.record_epochs(settings)
    truth = mission.truth_states(settings, epochs)
    model = ProbeMeasurementModel(settings.center)
    rng = np.random.default_rng(8)
    sigma = 2.0 * ARCSEC_RAD
    records = []
    for t, x in zip(epochs, truth):
        for target in ("moon", "earth"):
            probe = Measurement(t, "radec", [0.0, 0.0], sigma**2 * np.eye(2), target=target)
            value = model.predict(probe, x) + rng.normal(0.0, sigma, 2) * [1.0 / np.cos(model.predict(probe, x)[1]), 1.0]
            records.append(replace(probe, value=value))
    checks = check_records(records, epochs, truth, model, ("moon", "earth"))
    for target in ("moon", "earth"):
        entry = checks[target]
        assert entry["records"] == len(epochs) and entry["wrong_body"] == 0 and entry["gross_errors"] == 0
        # 2 N draws of a unit normal: the mean square within its 99.9 % chi-square interval
        n = 2 * len(epochs)
        assert stats.chi2.ppf(0.0005, n) / n < entry["chi2_per_axis"] < stats.chi2.ppf(0.9995, n) / n
    earth = model.predict(Measurement(epochs[0], "radec", [0.0, 0.0], np.eye(2), target="earth"), truth[0])
    wrong = replace(records[0], value=earth)
    checks = check_records([wrong], epochs, truth, model, ("moon", "earth"))
    assert checks["moon"]["wrong_body"] == 1 and checks["moon"]["gross_errors"] == 1


def test_image_mode_refuses_what_it_does_not_do(tmp_path):
    with pytest.raises(InputError, match="starlight records are measurement mode's"):
        mission.simulate_images(mission.Settings(starlight_target="earth", starlight_stars_radec_deg=((10.0, 5.0),)),
                                1, tmp_path)
    with pytest.raises(InputError, match="target_ephemeris_sigma_km is measurement mode's"):
        mission.simulate_images(mission.Settings(target_ephemeris_sigma_km=1.0), 1, tmp_path)
    with pytest.raises(InputError, match="camera_exposure_s must be one positive value or one per target"):
        mission.Settings(camera_exposure_s=(1e-5, 2e-6, 1e-3))
    with pytest.raises(InputError, match="image mode has no shape or reflectance for 'venus'"):
        mission.mission_bodies(mission.Settings(targets=("venus",)))


def test_three_hours_of_the_sample_from_pixels(tmp_path):
    """Three epochs of the sample (both bodies in the frame): every record inside its own covariance
    (chi-square at the 1 - 1e-6 quantile), no wrong body, the tracker's guide stars all right."""
    out = tmp_path / "img"
    args = ["run", str(SAMPLE), "--out", str(out), "--filters", "ekf", "--no-progress", "--workers", "1",
            "--set", "start=2027-02-28T03:00:00", "--set", "stop=2027-02-28T06:00:00"]
    assert load_run_file(SAMPLE).mode == "images"
    assert main(args) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["mode"] == "images"
    images = summary["facts"]["images"]
    assert images["wrong_body"] == 0 and images["gross_errors"] == 0
    assert images["tracked_stars"]["misidentified"] == 0 and images["tracked_stars"]["used"] > 0
    for target in ("moon", "earth"):
        assert images["records"][target]["records"] == 3
    assert summary["filters"]["ekf"]["accepted"] == 6
