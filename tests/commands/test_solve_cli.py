"""``opnav solve`` on synthetic frames of the packaged catalog, in every supported file format."""

import json
import math

import numpy as np
import pytest
import tifffile
from astropy.io import fits
from PIL import Image
from scipy.spatial.transform import Rotation
from test_starid import render_stars, to_jpeg

from opnav.camera import Camera
from opnav.catalog import load_catalog
from opnav.cli import main
from opnav.frames import radec_to_unit

CAMERA = Camera.from_fov(20.0, 640, 480)
#: Pointing at RA 83.8 deg, Dec -5.4 deg (Orion), image up at position angle 30 deg.
RA_DEG, DEC_DEG, ROLL_DEG = 83.8, -5.4, 30.0


def _truth() -> Rotation:
    """Camera -> ICRF with the boresight at (RA, Dec) and image up (-y) at position angle ROLL."""
    boresight = radec_to_unit(math.radians(RA_DEG), math.radians(DEC_DEG))
    east = np.cross([0.0, 0.0, 1.0], boresight)
    east /= np.linalg.norm(east)
    north = np.cross(boresight, east)
    roll = math.radians(ROLL_DEG)
    up = math.cos(roll) * north + math.sin(roll) * east
    # Columns: camera x, y, z in ICRF; y points down the image.
    x_axis = np.cross(-up, boresight)
    return Rotation.from_matrix(np.column_stack([x_axis, -up, boresight]))


@pytest.fixture(scope="module")
def frame():
    return render_stars(CAMERA, _truth(), load_catalog(), np.random.default_rng(3), vmag_limit=6.0)


@pytest.fixture(autouse=True)
def _cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("OPNAV_CACHE", str(tmp_path_factory.getbasetemp() / "opnav-cache"))


def _write(path, frame):
    suffix = path.suffix
    if suffix == ".fits":
        fits.PrimaryHDU(frame.astype(np.float32)).writeto(path)
    elif suffix == ".tif":
        tifffile.imwrite(path, frame.astype(np.uint16))
    elif path.name.endswith("bayer.tif"):
        tifffile.imwrite(path, _mosaic(frame, "RGGB").astype(np.uint16))
    elif path.name.endswith("rgb.png"):
        mono = to_jpeg(frame, quality=100).astype(np.uint8)
        Image.fromarray(np.stack([mono] * 3, axis=-1)).save(path)
    elif suffix == ".png":
        Image.fromarray(frame.astype(np.uint16)).save(path)
    else:
        Image.fromarray(to_jpeg(frame).astype(np.uint8)).save(path, quality=95)
    return path


#: Relative response of the red, green and blue filters of the mosaic test frame (a colour camera's
#: green pixels see most of a white star's light).
FILTER_RESPONSE = {"R": 0.45, "G": 1.0, "B": 0.6}


def _mosaic(frame, pattern):
    """A raw Bayer mosaic of a grey frame: each pixel keeps its filter's share of the light."""
    response = np.array([[FILTER_RESPONSE[c] for c in pattern[:2]], [FILTER_RESPONSE[c] for c in pattern[2:]]])
    rows, cols = np.indices(frame.shape)
    return frame * response[rows % 2, cols % 2]


@pytest.mark.parametrize("name", ["frame.fits", "frame.tif", "frame16.png", "frame_rgb.png", "frame.jpg", "frame_bayer.tif"])
def test_solve_prints_the_pointing(frame, tmp_path, capsys, name):
    path = _write(tmp_path / name, frame)
    bayer = ["--bayer", "rggb"] if "bayer" in name else []
    assert main(["solve", str(path), "--fov", "21", "--json", *bayer]) == 0
    record = json.loads(capsys.readouterr().out)
    pixel_deg = 20.0 / 640
    separation = math.degrees(math.acos(np.clip(
        radec_to_unit(math.radians(record["ra_deg"]), math.radians(record["dec_deg"]))
        @ radec_to_unit(math.radians(RA_DEG), math.radians(DEC_DEG)), -1.0, 1.0)))
    assert separation < pixel_deg
    assert abs((record["roll_deg"] - ROLL_DEG + 180.0) % 360.0 - 180.0) < 0.05
    assert abs(record["fov_deg"] - 20.0) < 0.05
    assert record["matched"] >= 10
    assert 0.0 < record["solve_ms"] <= record["total_ms"]


def test_unknown_bayer_pattern_is_refused(frame, tmp_path, capsys):
    path = _write(tmp_path / "frame_bayer.tif", frame)
    with pytest.raises(SystemExit) as exit_info:
        main(["solve", str(path), "--fov", "21", "--bayer", "RGBG"])
    assert exit_info.value.code == 2
    assert "--bayer" in capsys.readouterr().err


def test_no_solution_exits_1(tmp_path, capsys):
    noise = 100.0 + np.random.default_rng(4).normal(0.0, 10.0, (480, 640))
    path = _write(tmp_path / "noise.fits", noise)
    assert main(["solve", str(path), "--fov", "20"]) == 1
    assert "no solution" in capsys.readouterr().err


@pytest.mark.parametrize("kind", ["black", "saturated", "truncated", "nan"])
def test_bad_files_exit_2_with_a_message(frame, tmp_path, capsys, kind):
    path = tmp_path / "bad.fits"
    if kind == "black":
        fits.PrimaryHDU(np.zeros((480, 640), np.uint16)).writeto(path)
    elif kind == "saturated":
        fits.PrimaryHDU(np.full((480, 640), 65535, np.uint16)).writeto(path)
    elif kind == "nan":
        fits.PrimaryHDU(np.full((480, 640), np.nan, np.float32)).writeto(path)
    else:
        fits.PrimaryHDU(frame.astype(np.float32)).writeto(path)
        path.write_bytes(path.read_bytes()[: 20000])
    assert main(["solve", str(path), "--fov", "20", "--json"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("opnav solve: error:") and len(err.strip().splitlines()) == 1


def test_the_frame_date_moves_the_stars_and_is_reported(frame, tmp_path, capsys):
    # the synthetic frame holds the stars at the catalog epoch: solved at that date (from the
    # header's DATE-OBS or --epoch) it is the same answer, and the record says which date it used
    path = tmp_path / "dated.fits"
    header = fits.Header()
    header["DATE-OBS"] = "1991-04-02T13:30:00"
    fits.PrimaryHDU(frame.astype(np.float32), header=header).writeto(path)
    assert main(["solve", str(path), "--fov", "21", "--json"]) == 0
    dated = json.loads(capsys.readouterr().out)
    assert dated["star_epoch"].startswith("1991-04-02T13:30:00")
    assert main(["solve", str(_write(tmp_path / "plain.fits", frame)), "--fov", "21", "--json"]) == 0
    plain = json.loads(capsys.readouterr().out)
    assert plain["star_epoch"] == "catalog"
    assert abs(dated["ra_deg"] - plain["ra_deg"]) < 1e-4 and abs(dated["dec_deg"] - plain["dec_deg"]) < 1e-4
    assert main(["solve", str(path), "--fov", "21", "--epoch", "2024-13-45"]) == 2
    assert "2024-13-45" in capsys.readouterr().err


def test_the_command_process_solves_its_frames_as_a_call_does(frame, tmp_path, capsys):
    """``opnav solve`` as a process of its own keeps the garbage collector out of its start-up and the
    first frame (opnav.cli): its frames, and the frames after the first, get the records that the same
    solve called inside this process prints (times aside)."""
    import subprocess
    import sys

    paths = [str(_write(tmp_path / name, frame)) for name in ("a.fits", "b.tif")] + [str(tmp_path / "a.fits")]
    assert main(["solve", *paths, "--fov", "21", "--json"]) == 0
    called = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    run = subprocess.run([sys.executable, "-m", "opnav.cli", "solve", *paths, "--fov", "21", "--json"],
                         capture_output=True, text=True, check=True)
    alone = [json.loads(line) for line in run.stdout.splitlines()]

    def without_times(record: dict) -> dict:
        return {key: value for key, value in record.items() if not key.endswith("_ms")}

    assert [without_times(r) for r in alone] == [without_times(r) for r in called]
    assert len(alone) == 3 and all(r["matched"] >= 10 for r in alone)
