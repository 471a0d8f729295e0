"""``opnav solve FRAMES... --json``: many frames in one process, the WCS as the field-of-view hint, a line per frame."""

import json
import math

import numpy as np
import pytest
from astropy.io import fits
from scipy.spatial.transform import Rotation
from test_starid import render_stars

from opnav.camera import Camera
from opnav.catalog import load_catalog
from opnav.cli import main
from opnav.frames import radec_to_unit
from opnav.render.frames_io import wcs_header

CAMERA = Camera.from_fov(20.0, 640, 480)
#: Two pointings (camera -> ICRF) of the frames.
ATTITUDES = (Rotation.from_euler("zyx", [83.8, 5.4, 30.0], degrees=True),
             Rotation.from_euler("zyx", [200.0, -40.0, -75.0], degrees=True))


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("OPNAV_CACHE", str(tmp_path / "cache"))


def _fits(path, image, header):
    fits.PrimaryHDU(image.astype(np.float32), header=header).writeto(path)
    return str(path)


@pytest.fixture
def frames(tmp_path):
    """Two star frames whose WCS pixel scales differ by 0.03 % (as two fits of one camera would), a frame of
    noise with a WCS, and a truncated file."""
    catalog = load_catalog()
    paths = []
    for k, attitude in enumerate(ATTITUDES):
        image = render_stars(CAMERA, attitude, catalog, np.random.default_rng(k), vmag_limit=6.0)
        header = wcs_header(CAMERA.replace(focal_length_mm=CAMERA.focal_length_mm * (1.0 + 3e-4 * k)), attitude)
        header["DATE-OBS"] = "2014-07-15T00:58:52"
        header["EXPTIME"] = 2.0
        paths.append(_fits(tmp_path / f"stars{k}.fits", image, header))
    noise = 100.0 + np.random.default_rng(4).normal(0.0, 10.0, (480, 640))
    paths.insert(1, _fits(tmp_path / "noise.fits", noise, wcs_header(CAMERA, ATTITUDES[0])))
    bad = tmp_path / "truncated.fits"
    _fits(bad, noise, wcs_header(CAMERA, ATTITUDES[0]))
    bad.write_bytes(bad.read_bytes()[:20000])
    paths.append(str(bad))
    return paths


def _separation_deg(record, attitude) -> float:
    solved = radec_to_unit(math.radians(record["ra_deg"]), math.radians(record["dec_deg"]))
    return math.degrees(math.acos(np.clip(solved @ attitude.apply([0.0, 0.0, 1.0]), -1.0, 1.0)))


def test_every_frame_gives_a_line_and_a_failing_frame_does_not_stop_the_others(frames, tmp_path, capsys):
    assert main(["solve", *frames, "--json"]) == 2  # one unusable file
    out, err = capsys.readouterr()
    records = [json.loads(line) for line in out.splitlines()]
    assert [record["image"] for record in records] == frames
    solved = [records[0], records[2]]
    for record, attitude in zip(solved, ATTITUDES):
        assert "error" not in record
        assert _separation_deg(record, attitude) < 20.0 / 640
        assert record["hint"] == "wcs" and record["hint_fov_deg"] == pytest.approx(20.0, rel=1e-3)
        assert record["hint_offset_deg"] < 20.0 / 640
        assert record["fov_searched_deg"] == [[round(0.9 * record["hint_fov_deg"], 3), round(1.1 * record["hint_fov_deg"], 3)]]
        # DATE-OBS is the start of the exposure (FITS), the stars are moved to its middle
        assert record["star_epoch"] == "2014-07-15T00:58:53.000"
    assert records[1]["exit_status"] == 1 and "no solution" in records[1]["error"]
    assert records[3]["exit_status"] == 2 and "truncated.fits" in records[3]["error"]
    messages = [line for line in err.splitlines() if line.startswith("opnav solve:")]  # besides the build's progress
    assert len(messages) == 2 and "noise.fits" in messages[0] and "truncated.fits" in messages[1]
    # the two WCS fields of view snap to one index, built once
    assert len(list((tmp_path / "cache").glob("starid-*"))) == 1
    # without the unusable file the status is the no-solution one
    assert main(["solve", *frames[:3], "--json"]) == 1
    assert main(["solve", frames[0], frames[2]]) == 0
    text = capsys.readouterr().out.splitlines()
    assert len(text) == 3 + 2 and text[-1].startswith(frames[2]) and "hint: wcs" in text[-1]


def test_fov_and_no_wcs_options_override_the_wcs(frames, capsys):
    assert main(["solve", frames[0], "--fov", "21", "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["hint"] == "fov" and record["fov_searched_deg"] == [[18.9, 23.1]]
    assert record["hint_offset_deg"] < 20.0 / 640  # the WCS is still compared with the answer
    assert main(["solve", frames[0], "--no-wcs", "--fov", "21", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["hint"] == "fov"


def test_a_sparse_frame_no_index_solves_is_tracked_from_its_wcs_pointing(tmp_path, capsys):
    """Five stars to V 4 in a 20-degree field: no pattern has a fifth star to confirm it, so lost in space
    gives up; matched around the WCS pointing they are identified (``"method": "tracking"``). A WCS 30
    degrees off, or none (``--no-wcs``), gives no solution, never a wrong one."""
    image = render_stars(CAMERA, ATTITUDES[0], load_catalog(), np.random.default_rng(0), vmag_limit=4.0)
    sparse = _fits(tmp_path / "sparse.fits", image, wcs_header(CAMERA, ATTITUDES[0]))
    header = wcs_header(CAMERA, ATTITUDES[0])
    header["CRVAL2"] += 30.0
    wrong_wcs = _fits(tmp_path / "wrong_wcs.fits", image, header)
    assert main(["solve", sparse, wrong_wcs, "--json"]) == 1
    tracked, failed = (json.loads(line) for line in capsys.readouterr().out.splitlines())
    assert tracked["method"] == "tracking" and tracked["hint"] == "wcs"
    assert _separation_deg(tracked, ATTITUDES[0]) < 20.0 / 640 and tracked["matched"] >= 4
    assert "tracked from the WCS pointing" in failed["error"] and failed["exit_status"] == 1
    assert main(["solve", sparse, "--no-wcs", "--fov", "20", "--json"]) == 1
