"""S3 from pixels: star sensor and UV Earth sensor frames along the GEO arc -> starlight records."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2

from opnav.ephemeris.cache import default_cached_ephemeris
from opnav.errors import InputError
from opnav.measurements import ProbeMeasurementModel
from opnav.studies import s3, s3_images
from opnav.studies.s3_images import calibrate_limb_altitude

SHORT = s3.Settings(duration_hours=0.1)  # 36 epochs, one chunk


def _simulate_pixels(tmp_path_factory, noisy_frames=None):
    """The short arc from pixels, and the Earth sensor's limb calibration the run made (its
    noise-free and noisy rendered frames are most of the run's time); ``noisy_frames``: that many
    noisy frames in the calibration instead of its 200."""
    out = tmp_path_factory.mktemp("s3_images")
    calibrations = []
    real = s3_images.calibrate_limb_altitude

    def recorded(*args, **kwargs):
        if noisy_frames is not None:
            kwargs["noisy_frames"] = noisy_frames
        calibrations.append(real(*args, **kwargs))
        return calibrations[-1]

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(s3_images, "calibrate_limb_altitude", recorded)
        sim = s3.simulate_images(SHORT, 4, out, progress=False, workers=1)
    (calibration,) = calibrations
    return out, sim, calibration


@pytest.fixture(scope="module")
def pixels_full_calibration(tmp_path_factory):
    """The run as the study makes it (limb calibration from 200 noisy frames)."""
    return _simulate_pixels(tmp_path_factory)


@pytest.fixture(scope="module")
def pixels(tmp_path_factory):
    """The run with its limb calibrated from 50 noisy frames: a standard error of 0.0064 km (measured)
    instead of 0.003 km, inside the study's limb_altitude_sigma_km = 0.01 km (the run checks it)."""
    return _simulate_pixels(tmp_path_factory, noisy_frames=50)


def check_records_from_pixels(sim):
    assert len(sim.records) == sim.epochs.size == 36  # every epoch measured
    model = ProbeMeasurementModel("earth", ephemeris=default_cached_ephemeris())
    index = np.searchsorted(sim.epochs, [r.t_tdb_s for r in sim.records])
    errors = [r.value - model.predict(r, sim.truth[i]) for r, i in zip(sim.records, index)]
    stat = np.array([e @ np.linalg.solve(r.covariance, e) for e, r in zip(errors, sim.records)])
    assert stat.max() < chi2.ppf(1 - 1e-4, 2)
    assert chi2.ppf(0.0005, 2 * stat.size) < stat.sum() < chi2.ppf(0.9995, 2 * stat.size)
    # arcsecond-class: the study's sensors are 5" and 20" (3-sigma)
    sigmas = np.sqrt([np.diag(r.covariance) for r in sim.records])
    assert np.median(sigmas) < 2.0 * 4.848e-6
    facts = sim.facts
    assert facts["tracked_stars"]["used"] > 36 * 10 and facts["tracked_stars"]["misidentified"] == 0
    assert facts["tracking"]["acquisitions"] == 1 and facts["tracking"]["losses_of_lock"] == 0
    # the frames carry light time and aberration; so does the filters' model
    assert sim.navigation.light_time and sim.navigation.aberration


@pytest.mark.slow
def test_starlight_records_from_pixels_match_the_truth_within_their_covariance(pixels_full_calibration):
    check_records_from_pixels(pixels_full_calibration[1])


def test_starlight_records_from_pixels_match_the_truth_within_their_covariance_50_frame_calibration(pixels):
    """Fast sibling of the test above: the same 36 epochs and bounds, the limb calibrated from 50
    noisy frames instead of 200."""
    check_records_from_pixels(pixels[1])


@pytest.mark.slow
def test_an_interrupted_s3_image_run_reads_back_its_finished_chunks(pixels_full_calibration):
    """The whole second run, limb calibration included (it is made again, to the same answer)."""
    out, first, _ = pixels_full_calibration
    again = s3.simulate_images(SHORT, 4, out, progress=False, workers=1)
    assert again.facts["chunks_reused"] == 1
    assert [r.value.tolist() for r in again.records] == [r.value.tolist() for r in first.records]


def test_an_interrupted_s3_image_run_reads_back_its_finished_chunks_after_its_calibration(pixels, monkeypatch):
    """Fast sibling of the test above: the second run is given the first run's limb calibration
    (the same settings and arc start: the same answer) instead of rendering its frames again."""
    out, first, calibration = pixels
    asked = []
    monkeypatch.setattr(s3_images, "calibrate_limb_altitude", lambda *args, **kwargs: asked.append(args) or calibration)
    again = s3.simulate_images(SHORT, 4, out, progress=False, workers=1)
    assert len(asked) == 1
    assert again.facts["chunks_reused"] == 1
    assert [r.value.tolist() for r in again.records] == [r.value.tolist() for r in first.records]


def test_the_calibrated_limb_lies_below_the_sharp_edge_equivalent():
    """The UV horizon (flat to 40 km, then an 8 km scale height) is equivalent to a sharp edge at
    48 km; blurred on a curved limb its steepest fall lies ~sigma^2 / 2R inwards (0.4 km)."""
    ephemeris = default_cached_ephemeris()
    truth = s3.simulate(replace(SHORT, duration_hours=12.0), 1)
    first = calibrate_limb_altitude(SHORT, truth.truth[0], float(truth.epochs[0]), ephemeris, rolls=2, noisy_frames=20)
    later = calibrate_limb_altitude(SHORT, truth.truth[-1], float(truth.epochs[-1]), ephemeris, rolls=2, noisy_frames=20)
    assert 47.0 < first[0] < 48.0
    # half a day later the nadir sensor sees the same limb: the two agree within their standard errors
    assert 0.0 < first[1] < 0.02 and abs(first[0] - later[0]) < 4.0 * np.hypot(first[1], later[1])


def test_s3_image_settings_are_checked():
    with pytest.raises(InputError, match="earth_sensor_fov_deg"):
        s3.Settings(earth_sensor_fov_deg=10.0)
    with pytest.raises(InputError, match="star_sensor_px"):
        s3.Settings(star_sensor_px=10)
    with pytest.raises(InputError, match="limb_altitude_sigma_km"):
        s3.Settings(limb_altitude_sigma_km=0.0)
