"""Frame -> measurements on S1-like frames from the project renderer; CLIs; bad frames."""

import json
import math

import numpy as np
import pytest
from astropy.io import fits
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from opnav.camera import Camera
from opnav.catalog import synthetic_catalog
from opnav.cli import main
from opnav.constants import ARCSEC_RAD
from opnav.ephemeris import default_ephemeris
from opnav.epochs import parse_epoch
from opnav.errors import FrameError
from opnav.image.header import wcs_attitude
from opnav.image.pipeline import PipelineOptions, process_directory, process_frame
from opnav.light import apparent_direction
from opnav.records import FLAG_PHASE_CORRECTED, read_csv
from opnav.render import Observer, render_frame, write_frame

# S1 camera design used here: 13 um pixels, f = 762.7 mm (3.52"/px, 1.0 deg across 1024 px),
# 150 mm aperture, 1 s exposure, 8 e- read noise, gain 2 e-/ADU; 512 x 512 px to keep tests fast.
CAMERA = Camera(512, 512, 762.7, 13.0, aperture_mm=150.0, exposure_s=1.0, read_noise_e=8.0, gain_e_per_adu=2.0, full_well_e=1e5)


@pytest.fixture(scope="module")
def ephemeris():
    return default_ephemeris()


def _local_catalog(rng, centre_icrf, n=150, radius_deg=0.6):
    """Synthetic stars (V 6-11, ~130 per deg^2) in a cap around ``centre_icrf``."""
    return synthetic_catalog(n, rng=rng, vmag_range=(6.0, 11.0), centre_icrf=centre_icrf,
                             radius_rad=math.radians(radius_deg))


def _s1_frame(rng, ephemeris, *, range_km=15e6, phase_deg=50.0):
    """Observer ``range_km`` from Mars on the Sun side (phase ~``phase_deg``), camera at Phobos."""
    t = float(parse_epoch("2014-07-15T00:00:00", "utc")) + rng.uniform(0, 86400.0)
    r_mars, v_mars = ephemeris.state("mars", t)
    to_sun = ephemeris.position("sun", t) - r_mars
    to_sun /= np.linalg.norm(to_sun)
    side = np.cross(to_sun, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    a = math.radians(phase_deg)
    r_obs = r_mars + range_km * (math.cos(a) * to_sun + math.sin(a) * side)
    v_obs = v_mars + rng.normal(0.0, 3.0, 3)
    observer = Observer(t, r_obs, v_obs)
    z = apparent_direction(lambda tt: ephemeris.position("phobos", tt), t, r_obs, v_obs)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    pointing = Rotation.from_matrix(np.column_stack([x, np.cross(z, x), z])) * Rotation.from_rotvec(
        np.r_[rng.uniform(-3e-4, 3e-4, 2), rng.uniform(-np.pi, np.pi)]
    )
    catalog = _local_catalog(rng, pointing.apply([0.0, 0.0, 1.0]))
    result = render_frame(CAMERA, pointing, observer, catalog=catalog, targets=("phobos",), ephemeris=ephemeris, rng=rng)
    return result, catalog


def test_s1_moon_radec_is_accurate_and_its_covariance_honest(tmp_path, ephemeris):
    rng = np.random.default_rng(41)
    z2, sigmas, errors = [], [], []
    for k in range(5):
        result, catalog = _s1_frame(rng, ephemeris)
        path, _ = write_frame(tmp_path / f"s1_{k}.fits", result.image, result.header, result.truth)
        frame = process_frame(path, camera=CAMERA, catalog=catalog, ephemeris=ephemeris,
                              options=PipelineOptions(targets=("phobos",)), rng=k)
        assert frame.n_stars_matched >= 10 and "attitude_prior" not in frame.flags
        (rec,) = frame.records
        assert rec.kind == "radec" and rec.target == "phobos" and rec.flags & FLAG_PHASE_CORRECTED
        truth = result.truth.target("phobos")
        err = np.array([math.remainder(rec.value[0] - truth.ra_rad, 2 * math.pi), rec.value[1] - truth.dec_rad])
        z2.append(err @ np.linalg.solve(rec.covariance, err))
        sigmas.append(math.sqrt(rec.covariance[1, 1]))
        errors.append(np.hypot(err[0] * math.cos(truth.dec_rad), err[1]))
    # S1 acceptance: error consistent with the covariance, and 1 sigma <= 0.1"
    assert np.sum(z2) <= chi2.ppf(0.999, 2 * len(z2))
    assert max(sigmas) <= 0.1 * ARCSEC_RAD
    assert max(errors) <= 3 * 0.1 * ARCSEC_RAD


def test_wcs_attitude_matches_the_rendered_attitude(tmp_path, ephemeris):
    result, _ = _s1_frame(np.random.default_rng(7), ephemeris)
    R, f_px, (cx, cy) = wcs_attitude(result.header, "mem")
    assert (R.inv() * result.truth.R_icrf_cam).magnitude() < 1e-9
    assert f_px == pytest.approx(CAMERA.focal_length_px, rel=1e-9)
    assert (cx, cy) == pytest.approx((CAMERA.cx_px, CAMERA.cy_px))


def test_process_directory_skips_bad_frames_and_writes_records(tmp_path, ephemeris):
    rng = np.random.default_rng(8)
    frames = tmp_path / "frames"
    for k in range(2):
        result, catalog = _s1_frame(rng, ephemeris)
        write_frame(frames / f"f{k}.fits", result.image, result.header, result.truth)
    raw = (frames / "f1.fits").read_bytes()
    (frames / "f2.fits").write_bytes(raw[: len(raw) // 3])  # truncated
    blank_header = result.header.copy()
    fits.PrimaryHDU(np.zeros(CAMERA.shape, np.uint16), header=blank_header).writeto(frames / "f3.fits")
    out = tmp_path / "m.csv"
    results = process_directory(frames, out, camera=CAMERA, catalog=catalog, ephemeris=ephemeris,
                                options=PipelineOptions(targets=("phobos",)), rng=1, progress=False)
    assert [r.frame_id for r in results] == ["f0", "f1"]
    meta = json.loads(out.with_suffix(".json").read_text())
    assert set(meta["skipped"]) == {"f2.fits", "f3.fits"}
    assert "truncated" in meta["skipped"]["f2.fits"] or "corrupt" in meta["skipped"]["f2.fits"]
    assert "blank" in meta["skipped"]["f3.fits"]
    records = read_csv(out)
    assert len(records) == 2 and all(r.problem() is None for r in records)


def test_bad_frames_raise_frame_errors(tmp_path):
    with pytest.raises(FrameError, match="not found"):
        process_frame(tmp_path / "none.fits")
    png = tmp_path / "x.png"
    from PIL import Image

    Image.fromarray(np.zeros((20, 20, 3), np.uint8)).save(png)
    with pytest.raises(FrameError, match="FITS frame"):
        process_frame(png)


def test_cli_centroid_json_and_process(tmp_path, ephemeris, capsys):
    result, _ = _s1_frame(np.random.default_rng(9), ephemeris)
    path, _ = write_frame(tmp_path / "frames" / "a.fits", result.image, result.header, result.truth)
    assert main(["centroid", str(path), "--json"]) == 0
    sources = json.loads(capsys.readouterr().out)["sources"]
    assert {"x", "y", "flux", "snr", "sigma_x", "sigma_y"} <= set(sources[0])
    truth = result.truth.stars.xy_px[result.truth.stars.electrons > 2e4]
    xy = np.array([[s["x"], s["y"]] for s in sources])
    dist = np.min(np.hypot(*(xy[None, :, :] - truth[:, None, :]).transpose(2, 0, 1)), axis=1)
    inside = np.all((truth > 10) & (truth < 500), axis=1)
    assert np.all(dist[inside] < 0.05), "bright stars found to well under 0.05 px"
    out = tmp_path / "m.csv"
    assert main(["process", str(tmp_path / "frames"), "--out", str(out), "--no-catalog", "--no-progress"]) == 0
    assert out.exists() and "1 frames" in capsys.readouterr().out
    assert main(["centroid", str(tmp_path / "nothing.fits")]) == 2
    assert "not found" in capsys.readouterr().err


def test_s3_earth_limb_starlight_elevation_from_rendered_uv_frames(ephemeris):
    """S3: GEO UV Earth sensor (30 deg, 512 px) frames from the project renderer (soft UV limb)."""
    from opnav.constants import RADIUS_KM
    from opnav.frames import radec_to_unit
    from opnav.image.targets import fit_limb, limb_points, starlight_measurements
    from opnav.render import RenderOptions
    from opnav.studies.s3 import earth_sensor_view

    rng = np.random.default_rng(30)
    camera = Camera.from_fov(30.0, 512, 512)
    t = float(parse_epoch("2001-01-01T06:00:00", "utc"))
    for k in range(2):
        observer, attitude = earth_sensor_view(t, ephemeris, rng)
        frame = render_frame(camera, attitude, observer, targets=("earth",), ephemeris=ephemeris, rng=rng,
                             options=RenderOptions(supersample=2))
        truth = frame.truth.target("earth")
        pts = limb_points(frame.image.astype(float), truth.xy_cof_px + rng.uniform(-3, 3, 2),
                          truth.angular_radius_rad * camera.focal_length_px)
        fit = fit_limb(pts, camera, rng=k)
        star = radec_to_unit(rng.uniform(0, 2 * np.pi), rng.uniform(-1, 1))
        res = starlight_measurements(fit, attitude, np.zeros((3, 3)), star, body_radius_km=RADIUS_KM["earth"],
                                     limb_altitude_km=48.0, limb_altitude_sigma_km=1.0)
        centre = attitude.apply(camera.unproject(truth.xy_cof_px))
        beta = math.acos(float(centre @ star)) - math.asin(RADIUS_KM["earth"] / truth.range_km)
        err = res.elevation_rad - beta
        sigma = math.sqrt(res.var_elevation_rad2)
        # S3: UV Earth sensor 20" (3 sigma)
        assert abs(err) <= 20.0 * ARCSEC_RAD and 3 * sigma <= 20.0 * ARCSEC_RAD
        assert abs(err) <= 3.3 * sigma


def test_image_stage_does_not_import_the_renderer():
    """The image stage predicts bodies with opnav.bodies/observer/photometry, shared with the
    renderer; it never imports opnav.render (a fresh interpreter, so other tests do not count)."""
    import subprocess
    import sys

    code = ("import sys, opnav.image.pipeline, opnav.image.starid, opnav.image.targets; "
            "print(sorted(m for m in sys.modules if m.startswith('opnav.render')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
