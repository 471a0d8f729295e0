"""Hostile inputs of the reliability issue: each ends in one line naming the file, key or option
and what is accepted, or in the correct answer (never a traceback, a hang or a silent default)."""

from pathlib import Path

import numpy as np
import pytest

from opnav.cli import main
from opnav.ephemeris import default_ephemeris
from opnav.errors import EphemerisError, InputError
from opnav.records import read_csv
from opnav.sim.scene import load_scene

ROOT = Path(__file__).resolve().parents[1]
RENDER = (ROOT / "samples" / "s1_render.toml").read_text()


def scenario(tmp_path, old: str, new: str) -> Path:
    assert old in RENDER
    path = tmp_path / "case.toml"
    path.write_text(RENDER.replace(old, new, 1))
    return path


def one_line_error(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    return err


@pytest.mark.parametrize("old, new, message", [
    ("step_s = 300.0", 'step_s = "five"', r"\[epochs\] step_s must be float .*'five'"),
    ("sigma_px = 1.0", 'sigma_px = "big"', r"\[psf\] sigma_px must be float .*'big'"),
    ("position_km = [24306991.2893", 'position_km = ["a", 132523850.2219', r"\[observer\] position_km must be an array of 3 finite numbers .*'a'"),
    ("vmag_limit = 11.0", 'vmag_limit = "faint"', r"\[catalog\] vmag_limit must be float .*'faint'"),
    ("windowed = false", "windowed = 2", r"\[render\] windowed must be true or false, got 2"),
    ("focal_length_mm = 762.7", "focal_length_mm = 1e12", r'field of view; at least 10" is accepted'),
    ('start = "2014-07-15T00:00:00"', 'start = "2014-13-45T99:00:00"', "expected ISO 8601"),
    ("step_s = 300.0", "step_s = 0.0", "step_s must be positive"),
    ('stop = "2014-07-15T00:10:00"\nstep_s = 300.0', 'stop = "2014-07-16T00:00:00"\nstep_s = 0.001',
     "give 86,400,000 epochs; at most 10,000,000"),
    # checked on load, not when first used (issue 40)
    ('dynamics = "cruise"', 'dynamics = "crusie"',
     r"\[observer\] dynamics must be one of cruise, capture1, capture2, geo, approach, got 'crusie' "
     r"\(did you mean 'cruise'\?\)"),
    ('center = "sun"', 'center = "vulcan"', r"\[observer\] center must be one of .*sun.*, got 'vulcan'"),
    ('center = "sun"', 'center = "earth"', r"\[observer\] center must be 'sun', the centre of dynamics 'cruise', "
                                           r"got 'earth'"),
    ('position_km = [24306991.2893, 132523850.2219, 58427884.5328]\nvelocity_km_s = [-32.455391, 3.658828, 3.362343]',
     'body = "marz"', r"\[observer\] body must be one of .*mars.*, got 'marz' \(did you mean 'mars'\?\)"),
    ('target = "phobos"', 'target = "phobus"', r"\[pointing\] target must be one of .*phobos.*, got 'phobus'"),
    ("vmag_limit = 11.0", 'vmag_limit = 11.0\npath = "no-such-catalog.npz"',
     r"\[catalog\] path must be an existing catalog file \(a relative path is taken from the scene file's folder\), "
     r"got 'no-such-catalog.npz'"),
    ("windowed = false", "windowed = true\nwindow_half_px = -4",
     r"\[render\] window_half_px must be a positive integer, got -4"),
    ("seed = 41", "seed = -1", r"\[scenario\] seed must be a non-negative integer, got -1"),
    ('scale = "utc"\nstart = "2014-07-15T00:00:00"\nstop = "2014-07-15T00:10:00"',
     'scale = "tt"\nstart = "2014-07-15T00:00:00"\nstop = 2014-07-15T00:10:00Z',
     r"\[epochs\] stop '2014-07-15T00:10:00Z' is a UTC date"),
    # TOML values only, as in every file: text is not a number, boolean or array
    ("width_px = 1024", 'width_px = "1024"', r"\[camera\] width_px must be int .*\(written without quotes\), got '1024'"),
    ('names = ["phobos", "deimos", "mars"]', 'names = "phobos, deimos"',
     r"\[targets\] names must be an array of strings \(written as a TOML array"),
])
def test_bad_scenario_values_name_the_key(tmp_path, old, new, message):
    path = scenario(tmp_path, old, new)
    with pytest.raises(InputError, match=message) as info:
        load_scene(path)
    assert str(path) in str(info.value)


def test_toml_text_booleans_are_refused_not_read_as_true(tmp_path):
    for text in ('"false"', '"true"'):
        with pytest.raises(InputError, match=r"\[render\] windowed must be true or false \(written without quotes\)"):
            load_scene(scenario(tmp_path, "windowed = false", f"windowed = {text}"))


def test_render_refuses_a_negative_seed_in_one_line_before_any_work(tmp_path, capsys):
    path = scenario(tmp_path, "seed = 41", "seed = -3")
    err = one_line_error(capsys, ["render", str(path), "--out", str(tmp_path / "out"), "--no-progress"])
    assert "[scenario] seed must be a non-negative integer, got -3" in err and str(path) in err
    assert not (tmp_path / "out").exists()


def test_render_start_stop_are_utc_unless_scale_says_otherwise(tmp_path, capsys):
    from opnav.cli import build_parser

    help_text = " ".join(build_parser(load=("render",))._subparsers._group_actions[0].choices["render"]
                         .format_help().split())
    assert "in the scenario's [epochs] scale)" not in help_text and "default: utc" in help_text
    sample = str(ROOT / "samples" / "s1_render.toml")
    err = one_line_error(capsys, ["render", sample, "--scale", "tt", "--out", str(tmp_path / "a")])
    assert "--scale is the scale of --start/--stop" in err
    err = one_line_error(capsys, ["render", sample, "--start", "2014-07-15T00:00:00Z", "--scale", "TT",
                                  "--out", str(tmp_path / "b")])
    assert err.endswith("--start '2014-07-15T00:00:00Z' is a UTC date (Z or an offset) but its scale is 'tt'; "
                        "drop the Z or set the scale to utc")
    err = one_line_error(capsys, ["render", sample, "--stop", "2014-07-15T25:00:00", "--out", str(tmp_path / "c")])
    assert "--stop: cannot parse epoch" in err


def test_an_empty_opnav_cache_is_unset_as_an_empty_opnav_catalog_is(monkeypatch, tmp_path):
    from opnav.image.starid_index import default_cache_dir

    monkeypatch.setenv("OPNAV_CACHE", "")
    assert default_cache_dir() == Path.home() / ".cache" / "opnav"
    monkeypatch.setenv("OPNAV_CACHE", str(tmp_path / "cache"))
    assert default_cache_dir() == tmp_path / "cache"


def test_radec_errors_docstring_names_the_keys_it_returns():
    import inspect
    import re

    from opnav.sim.checks import radec_errors

    documented = set(re.findall(r"``(\w+)``", inspect.getdoc(radec_errors).split("Returns, per target:")[1]))
    returned = set(re.findall(r'"(\w+)": ', inspect.getsource(radec_errors)))
    assert returned <= documented, f"returned but not documented: {returned - documented}"
    assert "mean_abs_arcsec" not in documented


def test_render_refuses_zero_step_and_frame_floods(tmp_path, capsys):
    sample = str(ROOT / "samples" / "s1_render.toml")
    err = one_line_error(capsys, ["render", sample, "--step", "0", "--out", str(tmp_path / "a")])
    assert "--step must be a positive number" in err
    # 20 frames a second over a UTC day (a few us short of a TDB day): refused before any propagation
    err = one_line_error(capsys, ["render", sample, "--stop", "2014-07-16T00:00:00", "--step", "0.05",
                                  "--out", str(tmp_path / "b"), "--no-progress"])
    assert "1,728,000 frames requested; at most 1,000,000" in err
    assert not (tmp_path / "b").exists()


def test_centroid_window_is_bounded(tmp_path, capsys):
    from astropy.io import fits

    frame = tmp_path / "frame.fits"
    noise = np.random.default_rng(2).normal(100.0, 5.0, (64, 64))
    fits.PrimaryHDU(noise.astype(np.uint16)).writeto(frame)
    err = one_line_error(capsys, ["centroid", str(frame), "--window", "2001"])
    assert "odd integer from 3 to 51" in err


def test_observability_arc_is_not_clamped(capsys):
    err = one_line_error(capsys, ["observability", "--model", "1", "--arc-days", "100000"])
    assert "arc_days must be in (0, 5]" in err


def test_measurement_csv_with_nan_time_or_binary_bytes(tmp_path):
    header = ("t_tdb_s,kind,unit,sensor,target,star_id,star_x,star_y,star_z,frame_id,flags,value,covariance\n")
    row = "{t},radec,rad,cam,phobos,0,nan,nan,nan,,0,0.1 0.2,1e-10 0 0 1e-10\n"
    nan_time = tmp_path / "nan.csv"
    nan_time.write_text(header + row.format(t=100.0) + row.format(t="nan"))
    with pytest.raises(InputError, match=r"nan.csv:3: .*time must be finite"):
        read_csv(nan_time)
    binary = tmp_path / "binary.csv"
    binary.write_bytes(header.encode() + np.random.default_rng(1).bytes(2000))
    with pytest.raises(InputError, match="not a text CSV file"):
        read_csv(binary)


def test_out_is_checked_before_any_work(tmp_path, capsys):
    folder = tmp_path / "folder"
    folder.mkdir()
    err = one_line_error(capsys, ["process", str(tmp_path / "no-frames"), "--out", str(folder)])
    assert "is a folder; give a file name" in err
    afile = tmp_path / "file.txt"
    afile.write_text("x")
    err = one_line_error(capsys, ["run", str(ROOT / "samples" / "s3_geo.toml"), "--out", str(afile / "sub")])
    assert "is a file, not a folder" in err


def test_ephemeris_range_is_given_as_dates():
    with pytest.raises(EphemerisError, match=r"1873-03-31T04:53:20 TDB .* covers|1899-07-29T00:00:00 TDB"):
        default_ephemeris().state("mars", -4.0e9)


def test_an_unwritable_index_cache_is_one_line_before_the_build(tmp_path, monkeypatch, capsys):
    """OPNAV_CACHE (or --cache-dir) under a regular file: refused naming the variable before the index is
    built (the build took seconds to minutes, then its save failed naming only the path)."""
    from astropy.io import fits

    from opnav.catalog import synthetic_catalog

    stars = synthetic_catalog(300, rng=np.random.default_rng(3), vmag_range=(2.0, 7.0),
                              centre_icrf=np.array([1.0, 0.0, 0.0]), radius_rad=np.radians(20.0))
    catalog = tmp_path / "catalog.npz"
    np.savez(catalog, format_version=np.array(1), **{n: getattr(stars, n) for n in stars.__dataclass_fields__})
    image = np.random.default_rng(4).normal(100.0, 5.0, (128, 128))
    for k in range(8):
        image[15 + 13 * k, 20 + 11 * k] += 4000.0
    frame = tmp_path / "frame.fits"
    fits.PrimaryHDU(image.astype(np.float32)).writeto(frame)
    afile = tmp_path / "afile"
    afile.write_text("x")
    monkeypatch.setenv("OPNAV_CACHE", str(afile / "cache"))
    err = one_line_error(capsys, ["solve", str(frame), "--fov", "10", "--catalog", str(catalog)])
    assert err.startswith(f"opnav solve: error: OPNAV_CACHE {afile / 'cache'} cannot be written (Not a directory)")
    err = one_line_error(capsys, ["solve", str(frame), "--fov", "10", "--catalog", str(catalog),
                                  "--cache-dir", str(afile / "c2")])
    assert "--cache-dir" in err and "cannot be written" in err
    assert not any(tmp_path.glob("**/starid-*"))
