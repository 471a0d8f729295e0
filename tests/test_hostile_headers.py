"""FITS headers that lie or are missing (issue 40): a rendered S1 frame with one header edit, through
the commands that read frames (process, solve, centroid, calibrate). Each ends in exit 2 with one
error line naming the file and the keyword, or in the correct answer (the true pointing of the
frame, which the untouched header's WCS gives); never a traceback, a hang or a huge allocation."""

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from astropy.time import Time, TimeDelta

from opnav.cli import main
from opnav.frames import radec_to_unit

ROOT = Path(__file__).resolve().parents[1]
#: A log line of the CLI ("WARNING opnav.image.pipeline: ..."): a note beside the error, not the error.
LOG_LINE = re.compile(r"^(DEBUG|INFO|WARNING) [\w.]+: ")
#: How close the solved pointing must come to the frame's true one: a tenth of the 3.5" pixel.
POINTING_TOLERANCE_ARCSEC = 0.35


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """One S1 frame (1-degree camera, Phobos and Deimos) as ``opnav render`` writes it, with its truth file."""
    out = tmp_path_factory.mktemp("rendered")
    assert main(["render", str(ROOT / "samples" / "s1_render.toml"), "--out", str(out), "--no-progress",
                 "--stop", "2014-07-15T00:00:00"]) == 0
    return sorted(out.glob("*.fits"))[0]


def hostile(rendered: Path, folder: Path, edit) -> Path:
    """A copy of the rendered frame (and its truth file) in ``folder`` with ``edit(header)`` applied."""
    folder.mkdir()
    with fits.open(rendered) as hdul:
        header, data = hdul[0].header.copy(), hdul[0].data.copy()
    edit(header)
    path = folder / rendered.name
    fits.PrimaryHDU(data, header).writeto(path, output_verify="silentfix")
    shutil.copy(rendered.with_suffix(".truth.json"), folder / rendered.with_suffix(".truth.json").name)
    return path


def outcome(capsys, argv) -> tuple[int, str, list[str]]:
    """(exit status, stdout, the stderr lines that are not log notes); never a traceback."""
    status = main(argv)
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    return status, captured.out, [ln for ln in captured.err.splitlines() if ln.strip() and not LOG_LINE.match(ln)]


def one_line(capsys, argv, *needles) -> str:
    status, _, lines = outcome(capsys, argv)
    assert status == 2 and len(lines) == 1, lines
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def shift_dates(header, seconds: float, keys=("DATE-OBS", "DATE-AVG", "MJD-OBS", "MJD-AVG", "TDB_S")) -> None:
    for key in keys:
        if key.startswith("DATE"):
            header[key] = (Time(header[key]) + TimeDelta(seconds, format="sec")).isot
        elif key.startswith("MJD"):
            header[key] += seconds / 86_400.0
        else:
            header[key] += seconds


def drop_wcs(header) -> None:
    for key in ("CTYPE1", "CTYPE2", "CD1_1", "CD1_2", "CD2_1", "CD2_2", "CRVAL1", "CRVAL2", "CRPIX1", "CRPIX2",
                "WCSAXES", "CUNIT1", "CUNIT2", "LONPOLE", "RADESYS"):
        del header[key]


def true_pointing(rendered: Path) -> np.ndarray:
    header = fits.getheader(rendered)
    return radec_to_unit(np.radians(header["CRVAL1"]), np.radians(header["CRVAL2"]))


def solved_pointing_error_arcsec(capsys, path: Path, rendered: Path, *extra) -> tuple[float, list[str]]:
    """The angle between ``opnav solve``'s image centre and the frame's true pointing, and the notes."""
    status = main(["solve", str(path), "--json", *extra])
    captured = capsys.readouterr()
    assert status == 0 and "Traceback" not in captured.err, captured.err
    solution = json.loads(captured.out)
    solution = solution[0] if isinstance(solution, list) else solution
    centre = radec_to_unit(np.radians(solution["ra_deg"]), np.radians(solution["dec_deg"]))
    return float(np.degrees(np.arccos(np.clip(centre @ true_pointing(rendered), -1, 1))) * 3600.0), captured.err


@pytest.mark.parametrize("name, edit, needles", [
    ("no_wcs", drop_wcs, ("no celestial TAN WCS", "CTYPE1")),
    ("tdb_text", lambda h: h.__setitem__("TDB_S", "abc"), ("TDB_S = 'abc' is not a number",)),
    ("gain_text", lambda h: h.__setitem__("GAIN", "abc"), ("GAIN = 'abc' is not a number",)),
    ("date_1900", lambda h: (h.__delitem__("TDB_S"), h.__setitem__("DATE-AVG", "1900-01-01T00:00:00"),
                             h.__setitem__("DATE-OBS", "1899-12-31T23:59:59.5")),
     ("DATE-AVG gives 1900-01-01", "from 1957-10-04")),
    ("tdb_1900", lambda h: h.__setitem__("TDB_S", -3.155e9), ("TDB_S gives 1900-01-09", "from 1957-10-04")),
    # one date keyword a day off while the others are right: the header contradicts itself
    ("date_avg_one_day_off", lambda h: shift_dates(h, 86_400.0, keys=("DATE-AVG",)),
     ("TDB_S and DATE-AVG disagree by 86400 s",)),
    ("mjd_one_day_off", lambda h: shift_dates(h, -86_400.0, keys=("MJD-OBS",)), ("MJD-OBS + EXPTIME/2", "disagree")),
    ("crval2_not_a_dec", lambda h: h.__setitem__("CRVAL2", 95.0), ("CRVAL2 = 95.0 is not a declination",)),
    ("cd_one_degree_a_pixel", lambda h: (h.__setitem__("CD1_1", 1.0), h.__setitem__("CD2_2", 1.0)),
     ("deg field of view; expected (0, 120) deg",)),
    ("observer_faster_than_light", lambda h: h.__setitem__("OBS_VX", 4e5), ("OBS_VX/VY/VZ give", "km/s")),
])
def test_process_refuses_a_lying_header_in_one_line_naming_file_and_keyword(rendered, tmp_path, capsys, name, edit,
                                                                            needles):
    path = hostile(rendered, tmp_path / name, edit)
    line = one_line(capsys, ["process", str(path.parent), "--out", str(tmp_path / "m.csv"), "--no-progress"],
                    str(path), *needles)
    assert "every one of the 1 frames" in line


@pytest.mark.parametrize("name, edit", [
    # the whole header a day late, consistently: the stars agree, the moons are not where it predicts them
    ("all_dates_one_day_off", lambda h: shift_dates(h, 86_400.0)),
    # the WCS (the a-priori attitude) 5 degrees off the stars: tracking finds no star pair and no moon near it
    ("wcs_5_degrees_off", lambda h: h.__setitem__("CRVAL1", h["CRVAL1"] + 5.0)),
])
def test_process_of_a_consistent_but_wrong_header_ends_in_no_record_not_a_crash(rendered, tmp_path, capsys, name,
                                                                               edit):
    path = hostile(rendered, tmp_path / name, edit)
    status, _, lines = outcome(capsys, ["process", str(path.parent), "--out", str(tmp_path / "m.csv"),
                                        "--no-progress"])
    assert status == 2 and len(lines) == 1 and "no records" in lines[0] and "1 without the target" in lines[0]
    reasons = json.loads((tmp_path / "m.json").read_text())["frame_flags"]
    assert {"no_phobos", "no_deimos"} <= set(next(iter(reasons.values())))


@pytest.mark.parametrize("name, edit, extra", [
    ("wcs_5_degrees_off", lambda h: h.__setitem__("CRVAL1", h["CRVAL1"] + 5.0), ()),
    ("no_wcs", drop_wcs, ("--fov", "1.0")),
    ("all_dates_one_day_off", lambda h: shift_dates(h, 86_400.0), ()),
    ("gain_text", lambda h: h.__setitem__("GAIN", "abc"), ()),
])
def test_solve_finds_the_true_pointing_whatever_the_wcs_or_date_says(rendered, tmp_path, capsys, name, edit, extra):
    path = hostile(rendered, tmp_path / name, edit)
    error, _ = solved_pointing_error_arcsec(capsys, path, rendered, *extra)
    assert error < POINTING_TOLERANCE_ARCSEC


@pytest.mark.parametrize("name, edit, keyword", [
    ("tdb_text", lambda h: h.__setitem__("TDB_S", "abc"), "TDB_S"),
    ("tdb_1900", lambda h: h.__setitem__("TDB_S", -3.155e9), "TDB_S"),
])
def test_solve_leaves_an_unusable_epoch_out_and_says_so(rendered, tmp_path, capsys, caplog, name, edit, keyword):
    path = hostile(rendered, tmp_path / name, edit)
    status = main(["solve", str(path)])
    captured = capsys.readouterr()
    assert status == 0 and "Traceback" not in captured.err
    notes = [record.getMessage() for record in caplog.records if record.levelname == "WARNING"]
    assert any(keyword in note and str(path) in note and "left out" in note for note in notes), notes
    assert "stars at catalog epoch" in captured.out


def test_centroid_and_calibrate_refuse_in_one_line(rendered, tmp_path, capsys, caplog):
    path = hostile(rendered, tmp_path / "gain", lambda h: h.__setitem__("GAIN", "abc"))
    one_line(capsys, ["centroid", str(path)], str(path), "GAIN")
    # calibrate's plate solve leaves the 1900 epoch out (a warning naming it); without the epoch's aberration
    # the stars miss their gate, and the line says so (opnav.image.calibration_stars, not this module's)
    path = hostile(rendered, tmp_path / "old", lambda h: h.__setitem__("TDB_S", -3.155e9))
    one_line(capsys, ["calibrate", str(path), "--out", str(tmp_path / "cam.toml"), "--no-report"], str(path))
    assert any("TDB_S gives 1900" in record.getMessage() for record in caplog.records)
    assert not (tmp_path / "cam.toml").exists()


def test_a_20000_by_20000_frame_is_refused_before_its_pixels_are_read(tmp_path, capsys):
    """800 MB on disk as a sparse file (a few kB used): refused from NAXISn, nothing allocated."""
    header = fits.PrimaryHDU(np.zeros((3, 3), np.uint16)).header
    header["NAXIS1"], header["NAXIS2"] = 20_000, 20_000
    text = header.tostring().encode()
    folder = tmp_path / "big"
    folder.mkdir()
    path = folder / "big.fits"
    with open(path, "wb") as handle:
        handle.write(text)
        handle.truncate(len(text) + -(-20_000 * 20_000 * 2 // 2880) * 2880)
    for argv in (["centroid", str(path)], ["solve", str(path)],
                 ["process", str(folder), "--targets", "phobos", "--out", str(tmp_path / "m.csv"), "--no-progress"]):
        one_line(capsys, argv, str(path), "20000 x 20000 pixels; at most 178,956,970")


def test_a_wcs_narrower_than_any_index_is_left_out_not_built(rendered, tmp_path, capsys, caplog):
    """A CD matrix that says 0.05 deg across (the 1-degree frame's WCS divided by 20): its pattern index
    held 9 GB a minute into the build. The field of view is left out with a warning; the frame is
    searched without it and still solved (or tracked from the WCS pointing)."""
    def narrow(h):
        for key in ("CD1_1", "CD1_2", "CD2_1", "CD2_2"):
            h[key] = h[key] / 20.0

    path = hostile(rendered, tmp_path / "narrow", narrow)
    status = main(["solve", str(path), "--json"])
    captured = capsys.readouterr()
    assert status in (0, 1) and "Traceback" not in captured.err
    assert any("narrower than the 0.5 deg opnav indexes" in r.getMessage() and str(path) in r.getMessage()
               for r in caplog.records)
    one_line(capsys, ["solve", str(path), "--fov", "0.05"], "--fov", "[0.5, 120) deg")


def test_an_index_of_too_many_lattice_fields_is_refused_before_it_is_built():
    from opnav.catalog import synthetic_catalog
    from opnav.errors import InputError
    from opnav.image.starid_index import MAX_LATTICE_FIELDS, build_index, index_options_for_fov

    catalog = synthetic_catalog(300, rng=np.random.default_rng(3))
    with pytest.raises(InputError, match=f"at most {MAX_LATTICE_FIELDS:,}"):
        build_index(catalog, **index_options_for_fov(catalog, 0.05, 0.1))
