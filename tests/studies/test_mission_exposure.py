"""The navigation camera's exposure law (opnav.studies.mission_exposure): the ladder of settings, and the
`peak` law against the renderer's own expected electrons, for a point-like asteroid far out, the same
asteroid resolved near, and the Moon's phased disk."""

from pathlib import Path

import numpy as np
import pytest

from opnav.errors import InputError
from opnav.observer import Observer
from opnav.render.frame import RenderOptions, render_frame
from opnav.sim.sensors import Sky, loop_sources
from opnav.studies import mission
from opnav.studies.mission_exposure import EXPOSURE_STEP, exposure_ladder, frame_exposures, ladder_exposure, peak_rate_e_s
from opnav.studies.mission_images import navigation_camera, pointing
from opnav.studies.settings import load_run_file

SAMPLES = Path(__file__).resolve().parents[2] / "samples"


def test_the_ladder_is_the_settings_a_factor_apart_and_a_frame_gets_the_longest_not_above_the_wanted():
    ladder = exposure_ladder(1e-4, 2.0)
    assert ladder[0] == 1e-4 and ladder[-1] <= 2.0 < ladder[-1] * EXPOSURE_STEP
    np.testing.assert_allclose(ladder[1:] / ladder[:-1], EXPOSURE_STEP)
    wanted = np.array([5e-5, 1e-4, 1.5e-4, 0.3, 1.9, 50.0, np.inf])
    got = ladder_exposure(wanted, 1e-4, 2.0)
    np.testing.assert_allclose(got, [1e-4, 1e-4, 1e-4, 0.2048, 1.6384, 1.6384, 1.6384])
    inside = (wanted >= 1e-4) & (wanted <= ladder[-1])
    assert np.all(got[inside] <= wanted[inside]) and np.all(got[inside] > wanted[inside] / EXPOSURE_STEP)


def test_bad_exposure_law_keys_are_named():
    with pytest.raises(InputError, match="camera_peak_fraction must be in"):
        mission.Settings(camera_peak_fraction=1.5)
    with pytest.raises(InputError, match="camera_exposure_limits_s must be"):
        mission.Settings(camera_exposure_limits_s=(1.0, 1e-3))
    with pytest.raises(InputError, match="camera_exposure_limits_s must be"):
        mission.Settings(camera_exposure_limits_s=(0.0, 1.0))


def _frames(run_file: Path, target: str, rows, **changes):
    """(settings, body, pointing attitudes, epochs, r, v, ephemeris) of ``rows`` of a sample's record epochs."""
    from dataclasses import replace

    settings = replace(load_run_file(run_file).settings, **changes)
    sim = mission.simulate(settings, 1)
    eph = mission.truth_ephemeris(settings)
    r_c, v_c = eph.state(settings.center, sim.epochs[rows], center="ssb")
    r, v = sim.truth[rows, :3] + r_c, sim.truth[rows, 3:] + v_c
    _, ephemeris, _ = loop_sources(Sky(kernels=tuple(settings.kernels)), catalog=False)
    attitudes, _ = pointing(target, sim.epochs[rows], r, v, ephemeris)
    return settings, mission.mission_bodies(settings)[target], attitudes, sim.epochs[rows], r, v, ephemeris


@pytest.mark.parametrize("run_file, target, rows, changes", [
    # the asteroid far out (~1e6 km, 0.04 px: a point source) and at the end (1,000 km, ~38 px, 45 deg phase)
    ("asteroid_approach.toml", "opnav38", [0, -1], dict(camera_fov_deg=2.0, camera_px=512)),
    # the Moon's phased disk (~70-90 deg phase), 7 to 100 px across
    ("cislunar.toml", "moon", [0, 60, -1], {}),
])
def test_the_peak_law_brings_the_rendered_brightest_pixel_between_half_and_all_of_the_stated_fraction(
        run_file, target, rows, changes):
    """Each frame exposed as the law says, rendered by the renderer (its expected electrons, no noise): the
    brightest pixel is between fraction / EXPOSURE_STEP and fraction of the full well, and the law's
    predicted rate is the rendered one to 3 %."""
    settings, body, attitudes, epochs, r, v, ephemeris = _frames(
        SAMPLES / run_file, target, rows, camera_exposure_law="peak", camera_peak_fraction=0.5,
        camera_exposure_limits_s=(1e-7, 100.0), **changes)
    options = RenderOptions(supersample=2, sun_keepout_margin_rad=0.0)
    camera = navigation_camera(settings, target, 1.0)
    exposures = frame_exposures(settings, target, body, camera, attitudes, epochs, r, v, ephemeris,
                                options.psf.sigma_px)
    for i, t in enumerate(epochs):
        observer = Observer(float(t), r[i], v[i])
        frame = render_frame(navigation_camera(settings, target, float(exposures[i])), attitudes[i], observer,
                             targets=(body,), ephemeris=ephemeris, options=options, rng=np.random.default_rng(0))
        peak = float(frame.signal_e.max()) / camera.full_well_e
        assert 0.5 / EXPOSURE_STEP <= peak <= 0.5, (i, exposures[i], peak)
        predicted = peak_rate_e_s(body, camera, attitudes[i], observer, ephemeris, options.psf.sigma_px)
        assert predicted * exposures[i] / camera.full_well_e == pytest.approx(peak, rel=0.03)


def test_the_fixed_law_is_camera_exposure_s_per_target():
    settings, body, attitudes, epochs, r, v, ephemeris = _frames(SAMPLES / "cislunar.toml", "earth", [3, 4])
    got = frame_exposures(settings, "earth", body, navigation_camera(settings, "earth", 1.0), attitudes, epochs, r, v,
                          ephemeris, 1.0)
    np.testing.assert_array_equal(got, [settings.camera_exposure_s[1]] * 2)


@pytest.mark.slow
def test_frames_at_several_exposures_give_the_same_records_in_one_process_and_in_two(tmp_path):
    """The approach's last 3 hours (6 epochs, the body 5-38 px across) take several exposure settings, so
    several loops: measured in this process and spread over 2 processes, the records are the same."""
    from dataclasses import replace

    from opnav.studies.mission_images import measure

    settings = replace(load_run_file(SAMPLES / "asteroid_approach.toml").settings, start="2027-06-15T21:00:00")
    sim = mission.simulate(settings, 38)
    eph = mission.truth_ephemeris(settings)
    r_c, v_c = eph.state(settings.center, sim.epochs, center="ssb")
    r, v = sim.truth[:, :3] + r_c, sim.truth[:, 3:] + v_c
    got = [measure(settings, 38, sim.epochs, r, v, tmp_path / f"w{workers}", key="k", workers=workers)
           for workers in (1, 2)]
    assert len(np.unique(got[0].exposures["opnav38"])) >= 2
    assert len(got[0].records) == len(sim.epochs)
    assert [(m.t_tdb_s, list(m.value), m.covariance.tolist()) for m in got[0].records] == \
        [(m.t_tdb_s, list(m.value), m.covariance.tolist()) for m in got[1].records]
