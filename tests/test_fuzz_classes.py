"""Property tests of the classes of issue 40 that ``benchmarks/fuzz.py`` explores at scale:
inconsistent FITS headers, extreme ``--set`` values, special files and the environment.

Each input ends in a valid result or in one opnav error line naming the file, key or option;
never a traceback, a hang or a silent default.
"""

from __future__ import annotations

import dataclasses
import math
import os
import signal
import tomllib
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from opnav.camera import Camera
from opnav.catalog import load_catalog
from opnav.cli import main
from opnav.errors import FrameError, InputError, OpnavError
from opnav.filters.options import load_navigation
from opnav.image.header import (EPOCH_SPAN_TDB_S, camera_from_header, detector_keywords, header_epoch, header_observer,
                                wcs_attitude, wcs_hint)
from opnav.image.io import read_image
from opnav.records import read_csv
from opnav.render.frames_io import frame_header
from opnav.render.truth import FrameTruth
from opnav.sim.scene import load_scene
from opnav.studies import STUDIES
from opnav.studies.settings import load_run_file

pytestmark = pytest.mark.filterwarnings("ignore::erfa.ErfaWarning")

ROOT = Path(__file__).resolve().parents[1]
FUZZ = settings(deadline=None, derandomize=True, max_examples=300,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
RUN_FILES = tuple(ROOT / "samples" / name for name in ("s1_jul_both_0.1.toml", "s2_capture.toml", "s3_geo.toml",
                                                        "s4_approach.toml"))


@contextmanager
def no_hang(seconds: int = 20):
    """Fail (instead of waiting for ever) when the block runs past ``seconds``: a reader that opens a FIFO."""
    def alarm(signum, frame):  # noqa: ARG001 - signal handler signature
        raise TimeoutError(f"ran past {seconds} s")

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


# ---------------------------------------------------------------------------------------------
# Inconsistent or lying headers
# ---------------------------------------------------------------------------------------------

TRUTH = FrameTruth(t_tdb_s=4.586e8, exposure_s=2.0, camera_id="nac",
                   R_icrf_cam=Rotation.from_euler("zyx", [40.0, -25.0, 110.0], degrees=True),
                   r_observer_ssb_km=np.array([1e8, 2e7, -3e6]), v_observer_ssb_km_s=np.array([20.0, -8.0, 4.0]),
                   omega_cam_rad_s=np.zeros(3), stars=None, targets=())
CAMERA = Camera.from_fov(1.0, 64, 48)
BASE = frame_header(CAMERA, TRUTH)
KEYS = ("TDB_S", "DATE-OBS", "DATE-AVG", "MJD-OBS", "MJD-AVG", "EXPTIME", "TIMESYS", "CTYPE1", "CTYPE2", "CRVAL1",
        "CRVAL2", "CRPIX1", "CRPIX2", "CD1_1", "CD1_2", "CD2_1", "CD2_2", "CDELT1", "CDELT2", "CROTA2", "GAIN",
        "RDNOISE", "BIASLVL", "OBS_X", "OBS_Y", "OBS_Z", "OBS_VX", "OBS_VY", "OBS_VZ")
VALUES = st.one_of(
    st.sampled_from(["abc", "", "nan", "1900-01-01T00:00:00", "2200-01-01T00:00:00", "2014-07-16T00:00:00",
                     "RA---TAN", "DEC--TAN", "RA---SIN", "GPS", "TDB", None]),
    st.floats(allow_nan=False, allow_infinity=False),  # FITS cards hold finite numbers only
    st.integers(-2**62, 2**62), st.booleans(),
)


def lying_header(edits) -> fits.Header:
    header = BASE.copy()
    for key, value in edits:
        if value is None:
            header.remove(key, ignore_missing=True)
        else:
            header[key] = value
    return header


def check_header(header, path: str = "f.fits") -> None:
    """Every header reader gives a usable value or one FrameError line naming the file."""
    readers = (lambda: header_epoch(header, path), lambda: wcs_attitude(header, path),
               lambda: camera_from_header(header, (48, 64), path), lambda: detector_keywords(header, path),
               lambda: header_observer(header, TRUTH.t_tdb_s, path), lambda: wcs_hint(header, (48, 64), path))
    for read in readers:
        try:
            value = read()
        except FrameError as exc:
            assert "\n" not in str(exc) and str(exc).startswith(path), str(exc)
            continue
        if isinstance(value, float):  # the epoch
            assert EPOCH_SPAN_TDB_S[0] <= value <= EPOCH_SPAN_TDB_S[1]
        elif isinstance(value, Camera):
            assert math.isfinite(value.focal_length_px) and 0.0 < math.degrees(value.fov_x_rad) < 120.0
            assert value.gain_e_per_adu > 0.0 and value.exposure_s > 0.0 and math.isfinite(value.bias_adu)
        elif isinstance(value, tuple) and isinstance(value[0], Rotation):
            matrix = value[0].as_matrix()
            assert np.allclose(matrix @ matrix.T, np.eye(3)) and math.isfinite(value[1]) and value[1] > 0.0
        elif isinstance(value, dict):  # detector keywords
            assert all(math.isfinite(v) for v in value.values()) and value["gain_e_per_adu"] > 0.0
        elif value is not None and hasattr(value, "v_ssb_km_s"):
            assert np.all(np.isfinite(value.r_ssb_km)) and np.linalg.norm(value.v_ssb_km_s) < 3000.0


@FUZZ
@given(edits=st.lists(st.tuples(st.sampled_from(KEYS), VALUES), min_size=1, max_size=4))
@example(edits=[("DATE-AVG", "2014-07-16T00:00:00")])  # a day off the others
@example(edits=[(key, None) for key in KEYS[7:20]])  # no WCS at all
@example(edits=[("TDB_S", -3.155e9)])  # 1900
@example(edits=[("CD1_1", 1.0), ("CD2_2", 1.0)])  # 1 deg a pixel
def test_lying_headers_give_valid_values_or_one_frame_error_line(edits):
    check_header(lying_header(edits))


def test_the_untouched_header_is_read_as_written():
    t = header_epoch(BASE, "f.fits")
    assert abs(t - TRUTH.t_tdb_s) < 1e-6
    R, f_px, _ = wcs_attitude(BASE, "f.fits")
    assert np.degrees((R.inv() * TRUTH.R_icrf_cam).magnitude()) * 3600.0 < 1e-6
    assert abs(f_px - CAMERA.focal_length_px) < 1e-6 * CAMERA.focal_length_px


# ---------------------------------------------------------------------------------------------
# Extreme values on every numeric setting of every study
# ---------------------------------------------------------------------------------------------

def _numeric_settings() -> list[tuple[Path, str]]:
    pairs = []
    for path in RUN_FILES:
        study = STUDIES[tomllib.loads(path.read_text())["scenario"]["study"]]
        defaults = study.Settings()
        pairs += [(path, field.name) for field in dataclasses.fields(study.Settings)
                  if isinstance(getattr(defaults, field.name), (int, float))
                  and not isinstance(getattr(defaults, field.name), bool)]
    return pairs


NUMERIC_SETTINGS = _numeric_settings()
EXTREMES = st.one_of(st.sampled_from(["1e300", "-1e300", "1e-300", "-1e-300", "5e-324", "1e308", "-1", "0", "nan",
                                      "inf", "-inf", "1e999"]),
                     st.floats(allow_nan=True, allow_infinity=True).map(repr))


@FUZZ
@given(pair=st.sampled_from(NUMERIC_SETTINGS), value=EXTREMES)
def test_extreme_settings_are_refused_in_one_line_or_stay_finite(pair, value):
    path, key = pair
    try:
        run = load_run_file(path, {key: value})
    except InputError as exc:
        assert "\n" not in str(exc) and key in str(exc), str(exc)
        return
    number = getattr(run.settings, key)
    assert math.isfinite(number), f"{key} = {value} accepted as {number!r}"
    # a square (a variance, an area) neither overflows nor vanishes: the bound the loader checks
    assert number == 0.0 or 0.0 < number * number < math.inf


@pytest.mark.parametrize("value", ["1e300", "1e-300", "nan", "inf", "-inf"])
def test_every_numeric_setting_of_every_study_refuses_the_unusable_extremes(value):
    accepted = []
    for path, key in NUMERIC_SETTINGS:
        try:
            load_run_file(path, {key: value})
        except InputError:
            continue
        accepted.append(f"{path.name}: {key}")
    assert not accepted, f"{value} accepted by {accepted}"


# ---------------------------------------------------------------------------------------------
# Special files as every file argument
# ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def specials(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("special")
    made = {}
    for suffix in (".fits", ".toml", ".csv", ".npz"):
        fifo = folder / f"fifo{suffix}"
        os.mkfifo(fifo)
        made[f"fifo{suffix}"] = fifo
        made[f"folder{suffix}"] = folder / f"folder{suffix}"
        made[f"folder{suffix}"].mkdir()
        for name, target in (("zero", Path("/dev/zero")), ("fifo", fifo), ("dangling", folder / "none" / "x")):
            link = folder / f"link_{name}{suffix}"
            link.symlink_to(target)
            made[f"link_{name}{suffix}"] = link
    return made


READERS = {".fits": (read_image,), ".csv": (read_csv,), ".npz": (load_catalog,),
           ".toml": (load_scene, load_navigation, lambda p: load_run_file(p, None))}


@pytest.mark.parametrize("kind", ["fifo", "folder", "link_zero", "link_fifo", "link_dangling"])
@pytest.mark.parametrize("suffix", sorted(READERS))
def test_every_reader_refuses_a_special_file_in_one_line(specials, kind, suffix):
    path = specials[f"{kind}{suffix}"]
    for read in READERS[suffix]:
        with no_hang(), pytest.raises(OpnavError) as caught:
            read(path)
        # the file or, for a symlink, the file it names
        assert "\n" not in str(caught.value) and (path.name in str(caught.value) or str(path.resolve()) in
                                                  str(caught.value)), str(caught.value)


@pytest.mark.parametrize("kind", ["fifo", "folder", "link_zero"])
def test_the_commands_refuse_a_special_file_as_any_file_argument(specials, tmp_path, capsys, kind):
    frame = tmp_path / "frame.fits"
    fits.PrimaryHDU(np.random.default_rng(1).normal(100.0, 5.0, (32, 32)).astype(np.float32)).writeto(frame)
    argvs = [
        ["centroid", str(specials[f"{kind}.fits"])],
        ["solve", str(frame), "--fov", "10", "--catalog", str(specials[f"{kind}.npz"])],
        ["navigate", str(specials[f"{kind}.csv"]), "--scenario", str(ROOT / "samples" / "s3_render.toml"),
         "--out", str(tmp_path / "nav")],
        ["run", str(specials[f"{kind}.toml"]), "--out", str(tmp_path / "run")],
        ["centroid", str(frame), "--camera", str(specials[f"{kind}.toml"])],
    ]
    for argv in argvs:
        with no_hang():
            status = main(argv)
        err = capsys.readouterr().err.strip()
        assert status == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, (argv, err)
        named = Path(argv[1] if argv[0] in ("centroid", "navigate", "run") and "--camera" not in argv else argv[-1])
        assert named.name in err or str(named.resolve()) in err, (argv, err)  # a symlink: it or its target


# ---------------------------------------------------------------------------------------------
# Environment: a reader that went away
# ---------------------------------------------------------------------------------------------

class ClosedPipe:
    """A stdout whose reader went away (``opnav centroid ... | head -0``)."""

    def __init__(self) -> None:
        self.fd = os.open(os.devnull, os.O_WRONLY)

    def write(self, text: str) -> int:
        raise BrokenPipeError(32, "Broken pipe")

    def flush(self) -> None:
        raise BrokenPipeError(32, "Broken pipe")

    def fileno(self) -> int:
        return self.fd


def test_a_closed_stdout_ends_quietly_with_141(tmp_path, monkeypatch, capsys):
    frame = tmp_path / "frame.fits"
    image = np.random.default_rng(2).normal(100.0, 5.0, (32, 32))
    image[16, 16] += 3000.0
    fits.PrimaryHDU(image.astype(np.float32)).writeto(frame)
    pipe = ClosedPipe()
    try:
        monkeypatch.setattr("sys.stdout", pipe)
        status = main(["centroid", str(frame), "--json"])
    finally:
        monkeypatch.undo()
        os.close(pipe.fd)
    assert status == 141 and capsys.readouterr().err == ""
