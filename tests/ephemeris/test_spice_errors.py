"""Bad kernels end in one line naming the kernel and the body, frame or epoch: never CSPICE's
multi-line message. Each error is an ``InputError`` (and an ``EphemerisError``)."""

from __future__ import annotations

import numpy as np
import pytest

from opnav.epochs import parse_epoch
from opnav.errors import EphemerisError, InputError
from opnav.ephemeris.planets import default_kernel_path
from opnav.ephemeris.spice import KernelError, SpiceEphemeris, pool_string
from opnav.ephemeris.spk_writer import write_spk

DE421 = default_kernel_path()


def _one_line(excinfo) -> str:
    message = str(excinfo.value)
    assert "\n" not in message and "=====" not in message and "Toolkit version" not in message
    assert isinstance(excinfo.value, InputError) and isinstance(excinfo.value, EphemerisError)
    return message


def test_a_missing_kernel_is_named(tmp_path):
    with pytest.raises(KernelError) as excinfo:
        SpiceEphemeris([DE421, tmp_path / "mar097.bsp"])
    assert _one_line(excinfo) == f"kernel {tmp_path / 'mar097.bsp'} not found"


def test_a_text_file_named_as_an_spk_is_refused(tmp_path):
    (tmp_path / "probe.bsp").write_text("KPL/PCK\n\\begindata\nBODY499_RADII = ( 1 2 3 )\n")
    with pytest.raises(KernelError) as excinfo:
        SpiceEphemeris([tmp_path / "probe.bsp"])
    message = _one_line(excinfo)
    assert str(tmp_path / "probe.bsp") in message and "text kernel (KPL/PCK)" in message
    assert "must be DAF/SPK" in message


def test_a_file_that_is_no_kernel_at_all_is_refused(tmp_path):
    (tmp_path / "notes.txt").write_text("orbit of the probe, see the spreadsheet\n")
    with pytest.raises(KernelError) as excinfo:
        SpiceEphemeris([DE421, tmp_path / "notes.txt"])
    assert "is not a SPICE kernel" in _one_line(excinfo) and "notes.txt" in str(excinfo.value)


def test_kernels_without_an_spk_are_refused(tmp_path):
    (tmp_path / "mars.tpc").write_text("KPL/PCK\n\\begindata\nBODY499_RADII = ( 1 2 3 )\n")
    with pytest.raises(KernelError) as excinfo:
        SpiceEphemeris([tmp_path / "mars.tpc"])
    assert "mars.tpc hold no SPK" in _one_line(excinfo)


def test_a_body_not_covered_at_an_epoch_names_kernel_body_epoch_and_coverage(tmp_path):
    t = 4.6e8 + 600.0 * np.arange(20)
    states = np.hstack([np.tile([1.5e8, 0.0, 0.0], (20, 1)), np.zeros((20, 3))])
    states[:, 0] += 30.0 * (t - t[0])
    states[:, 3] = 30.0
    write_spk(tmp_path / "probe.bsp", t, states, body=-999, center=10)
    eph = SpiceEphemeris([DE421, tmp_path / "probe.bsp"])
    late = np.array([t[3], t[-1], t[-1] + 3600.0, t[-1] + 7200.0])
    with pytest.raises(KernelError) as excinfo:
        eph.state(-999, late, center="sun")
    message = _one_line(excinfo)
    assert "de421.bsp, probe.bsp do not cover -999 relative to 'sun'" in message
    assert f"({late[2]:.0f} s past J2000)" in message  # the first epoch outside, not the first asked
    assert f"probe.bsp 2014-07-30T13:46:40 TDB ({t[0]:.0f} s past J2000) to" in message
    # a body no loaded SPK holds at all
    with pytest.raises(KernelError) as excinfo:
        eph.state("phobos", t[0])
    assert "'phobos' (NAIF 401): in no SPK" in _one_line(excinfo)
    # past DE421's end (2053)
    with pytest.raises(KernelError) as excinfo:
        eph.state("mars", parse_epoch("2060-01-01T00:00:00", "tdb"))
    assert "2060-01-01T00:00:00 TDB" in _one_line(excinfo) and "de421.bsp 1899-07-29" in str(excinfo.value)


def test_an_unknown_body_lists_the_bodies_the_kernels_hold():
    eph = SpiceEphemeris([DE421])
    with pytest.raises(KernelError) as excinfo:
        eph.state("vulcan", 0.0)
    message = _one_line(excinfo)
    assert "unknown body 'vulcan'" in message and "de421.bsp" in message and "mars, mars_barycenter" in message
    with pytest.raises(KernelError, match=r"body 'eros' \(NAIF 2000433\) is in no SPK of kernels de421.bsp"):
        eph.check_body("eros")


def test_a_frame_not_defined_names_the_frame_and_the_kernels(tmp_path):
    eph = SpiceEphemeris([DE421])
    with pytest.raises(KernelError) as excinfo:
        eph.rotation("PROBE_NAVCAM", 0.0)
    assert _one_line(excinfo) == "frame 'PROBE_NAVCAM' is not defined by kernels de421.bsp"
    # a body-fixed frame SPICE knows by name but no loaded PCK orients
    with pytest.raises(KernelError) as excinfo:
        eph.rotation("IAU_MARS", 0.0)
    message = _one_line(excinfo)
    assert "de421.bsp cannot orient frame 'IAU_MARS' near 2000-01-01T12:00:00 TDB" in message
    assert "SPICE(FRAMEDATANOTFOUND)" in message
    with pytest.raises(KernelError) as excinfo:
        eph.radii_km("mars")
    assert _one_line(excinfo) == "kernels de421.bsp give no radii (BODY499_RADII) for 'mars'; PCKs: none loaded"


def test_a_meta_kernel_listing_a_missing_file_names_it(tmp_path):
    (tmp_path / "mission.tm").write_text(
        f"KPL/MK\n\\begindata\nKERNELS_TO_LOAD = ( {pool_string(DE421)},\n'gone.bsp' )\n")
    with pytest.raises(KernelError) as excinfo:
        SpiceEphemeris([tmp_path / "mission.tm"])
    assert _one_line(excinfo) == f"kernel {tmp_path / 'gone.bsp'} not found"
    (tmp_path / "empty.tm").write_text("KPL/MK\n\\begindata\nMISSION_NAME = ( 'x' )\n")
    with pytest.raises(KernelError) as excinfo:
        SpiceEphemeris([tmp_path / "empty.tm"])
    assert "lists no KERNELS_TO_LOAD" in _one_line(excinfo)


def test_a_corrupt_spk_is_one_line(tmp_path):
    data = DE421.read_bytes()[:4096]  # a DAF/SPK ID word over a truncated file
    (tmp_path / "cut.bsp").write_bytes(data)
    with pytest.raises(KernelError) as excinfo:
        SpiceEphemeris([tmp_path / "cut.bsp"])
    message = _one_line(excinfo)
    assert message.startswith(f"kernel {tmp_path / 'cut.bsp'} is cut short: its records run to byte ")
    assert message.endswith(", the file has 4,096")


def test_a_meta_kernel_that_lists_itself_is_refused(tmp_path):
    (tmp_path / "loop.tm").write_text(f"KPL/MK\n\\begindata\nKERNELS_TO_LOAD = ( {pool_string(DE421)},\n'loop.tm' )\n")
    with pytest.raises(KernelError) as excinfo:
        SpiceEphemeris([tmp_path / "loop.tm"])
    assert _one_line(excinfo) == f"meta-kernel {tmp_path / 'loop.tm'} lists itself (through loop.tm)"


def test_a_meta_kernel_string_longer_than_spice_keeps_is_refused_and_pool_string_splits_it(tmp_path):
    # SPICE keeps 80 characters of a string and drops the rest without a word: a long path read as a missing file
    long_folder = tmp_path / ("k" * 90)
    long_folder.mkdir()
    (long_folder / "de421.bsp").symlink_to(DE421)
    (tmp_path / "long.tm").write_text(f"KPL/MK\n\\begindata\nKERNELS_TO_LOAD = ( '{long_folder / 'de421.bsp'}' )\n")
    with pytest.raises(KernelError) as excinfo:
        SpiceEphemeris([tmp_path / "long.tm"])
    message = _one_line(excinfo)
    assert message.startswith(f"meta-kernel {tmp_path / 'long.tm'}, line 3: a string of ")
    assert message.endswith("SPICE keeps 80: split it with '+' continuation ('first part+' 'rest')")
    (tmp_path / "split.tm").write_text(
        f"KPL/MK\n\\begindata\nKERNELS_TO_LOAD = ( {pool_string(long_folder / 'de421.bsp')} )\n\\begintext\n"
        f"'{'t' * 100}' is text, not data\n")
    eph = SpiceEphemeris([tmp_path / "split.tm"])
    assert [p.name for p in eph.kernels.files] == ["de421.bsp"]
    r, _ = eph.state("mars", 0.0, center="sun")
    assert 2.0e8 < np.linalg.norm(r) < 2.5e8  # Mars from the Sun, km: the whole path was read


def test_a_kernel_name_too_long_is_shortened_in_its_line(tmp_path):
    with pytest.raises(KernelError) as excinfo:
        SpiceEphemeris([tmp_path / ("x" * 5000 + ".bsp")])
    message = _one_line(excinfo)
    assert len(message) < 200 and message.startswith(f"kernel {str(tmp_path)[:40]}")
    assert message.endswith("..." + "x" * 36 + ".bsp not found")
