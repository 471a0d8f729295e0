"""Attitude from a CK (opnav.ephemeris.ck): CKs written by spiceypy (``ckw03``) from known attitude
histories, indexed by a linear SCLK written here, read back against the histories; a camera an FK
mounts on the CK frame against SPICE's own frame system; every bad kernel one line.

The SCLK (:func:`opnav.ephemeris.ck_writer.write_linear_sclk`) counts TDB seconds from a day before
the CK in ticks of 1/65536 s, so encoding an epoch loses nothing the tests can see.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from opnav.errors import EphemerisError, InputError
from opnav.ephemeris.ck import ck_attitude
from opnav.ephemeris.ck_writer import TICKS_PER_S, write_ck, write_linear_sclk
from opnav.ephemeris.planets import default_kernel_path
from opnav.ephemeris.spice import KernelError, KernelSet

spiceypy = pytest.importorskip("spiceypy")

T0 = 8.0e8  # 2025-05-08, TDB s past J2000
STEP_S = 60.0
NODES = T0 + STEP_S * np.arange(61)  # an hour of pointing records
#: A slow spin (one turn in 10.5 min) about a fixed ICRF axis, from an arbitrary initial attitude.
SPIN_RAD_S = 0.01
SPIN_AXIS = np.array([0.3, 0.4, np.sqrt(0.75)])
R_ICRF_BODY0 = Rotation.from_euler("zyx", [1.0, 0.2, 0.3])
#: The navigation camera's mounting in the FK: TKFRAME angles (deg) about axes 1, 2, 3.
CAMERA_ANGLES_DEG = (10.0, 20.0, 30.0)

FK = f"""KPL/FK

Probe -77: its body frame is CK structure -77000 (clock -77); a navigation camera fixed on it, and a
star tracker fixed on the camera.

\\begindata
FRAME_PROBE_SC           = -77000
FRAME_-77000_NAME        = 'PROBE_SC'
FRAME_-77000_CLASS       = 3
FRAME_-77000_CLASS_ID    = -77000
FRAME_-77000_CENTER      = -77
CK_-77000_SCLK           = -77
CK_-77000_SPK            = -77

FRAME_PROBE_NAVCAM       = -77100
FRAME_-77100_NAME        = 'PROBE_NAVCAM'
FRAME_-77100_CLASS       = 4
FRAME_-77100_CLASS_ID    = -77100
FRAME_-77100_CENTER      = -77
TKFRAME_-77100_RELATIVE  = 'PROBE_SC'
TKFRAME_-77100_SPEC      = 'ANGLES'
TKFRAME_-77100_UNITS     = 'DEGREES'
TKFRAME_-77100_AXES      = ( 1 2 3 )
TKFRAME_-77100_ANGLES    = ( {CAMERA_ANGLES_DEG[0]} {CAMERA_ANGLES_DEG[1]} {CAMERA_ANGLES_DEG[2]} )

FRAME_PROBE_TRACKER      = -77200
FRAME_-77200_NAME        = 'PROBE_TRACKER'
FRAME_-77200_CLASS       = 4
FRAME_-77200_CLASS_ID    = -77200
FRAME_-77200_CENTER      = -77
TKFRAME_-77200_RELATIVE  = 'PROBE_NAVCAM'
TKFRAME_-77200_SPEC      = 'MATRIX'
TKFRAME_-77200_MATRIX    = ( 0 1 0  -1 0 0  0 0 1 )

FRAME_PROBE_ECLIPTIC_CAM = -77300
FRAME_-77300_NAME        = 'PROBE_ECLIPTIC_CAM'
FRAME_-77300_CLASS       = 4
FRAME_-77300_CLASS_ID    = -77300
FRAME_-77300_CENTER      = -77
TKFRAME_-77300_RELATIVE  = 'ECLIPJ2000'
TKFRAME_-77300_SPEC      = 'ANGLES'
TKFRAME_-77300_UNITS     = 'DEGREES'
TKFRAME_-77300_AXES      = ( 3 1 3 )
TKFRAME_-77300_ANGLES    = ( 5 -7 11 )
\\begintext
"""


def spin(t) -> Rotation:
    """``R_icrf_body`` of the uniform spin at TDB epochs ``t``."""
    return Rotation.from_rotvec(np.outer(SPIN_RAD_S * (np.atleast_1d(t) - T0), SPIN_AXIS)) * R_ICRF_BODY0


@pytest.fixture(scope="module")
def kernels(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ck")
    sclk = write_linear_sclk(folder / "probe.tsc", clock_id=-77, start_tdb_s=T0 - 86_400.0)
    (folder / "probe.tf").write_text(FK)
    ck = write_ck(folder / "probe.bc", NODES, spin(NODES), ck_id=-77000, sclk=sclk)
    return {"folder": folder, "sclk": sclk, "fk": folder / "probe.tf", "ck": ck,
            "set": KernelSet([ck, sclk, folder / "probe.tf"])}


def _angle(a: Rotation, b: Rotation) -> np.ndarray:
    return (a * b.inv()).magnitude()


def test_the_linear_sclk_counts_tdb_seconds(kernels):
    with KernelSet([kernels["sclk"]]).loaded():
        ticks = np.array([spiceypy.sce2c(-77, float(t)) for t in NODES[[0, 7, -1]]])
    np.testing.assert_allclose(ticks, (NODES[[0, 7, -1]] - (T0 - 86_400.0)) * TICKS_PER_S, rtol=0, atol=1e-6)


def test_a_uniform_spin_reads_back_at_and_between_nodes(kernels):
    # type 3 turns at a constant rate about one axis between records: exact for a uniform spin
    between = np.sort(np.random.default_rng(38).uniform(NODES[0], NODES[-1], 500))
    for t in (NODES, between):
        for frame in (-77000, "-77000", "PROBE_SC", "probe_sc"):
            attitude = ck_attitude(kernels["set"], frame, t)
            assert len(attitude) == t.size
            assert _angle(attitude, spin(t)).max() < 1e-12
    one = ck_attitude(kernels["set"], "PROBE_SC", float(between[3]))
    assert one.single and _angle(one, spin(between[3])[0]) < 1e-12


def test_between_nodes_the_error_is_the_interpolation_remainder(tmp_path, kernels):
    # A coning body: a spin w about an axis a tilted by theta from ICRF z, precessing about z at p.
    # Its angular velocity turns at |dw/dt| = p w sin(theta); type 3's constant-rate turn between
    # records h apart misses the attitude at mid-interval by h^2 / 8 |dw/dt| (leading order; the next
    # order is (w h)^2 smaller), and meets it at the records.
    precession, rate, theta, h = 2e-3, 0.02, 0.5, 5.0
    axis = np.array([np.sin(theta), 0.0, np.cos(theta)])

    def coning(t):
        dt = np.atleast_1d(t) - T0
        return (Rotation.from_rotvec(np.outer(precession * dt, [0.0, 0.0, 1.0]))
                * Rotation.from_rotvec(np.outer(rate * dt, axis)) * R_ICRF_BODY0)

    nodes = T0 + h * np.arange(121)
    ck = write_ck(tmp_path / "coning.bc", nodes, coning(nodes), ck_id=-77002, sclk=kernels["sclk"])
    kernel_set = KernelSet([ck, kernels["sclk"]])
    assert _angle(ck_attitude(kernel_set, -77002, nodes), coning(nodes)).max() < 1e-12
    mid = nodes[:-1] + h / 2
    miss = _angle(ck_attitude(kernel_set, -77002, mid), coning(mid))
    remainder = h**2 / 8 * precession * rate * np.sin(theta)  # 6.0e-5 rad
    np.testing.assert_allclose(miss, remainder, rtol=2 * (rate * h) ** 2)


def test_a_camera_the_fk_mounts_on_the_ck_frame(kernels):
    t = np.sort(np.random.default_rng(7).uniform(NODES[0], NODES[-1], 50))
    body = ck_attitude(kernels["set"], "PROBE_SC", t)
    # TKFRAME ANGLES (a1, a2, a3) about axes (1, 2, 3) (NAIF's frames.req): the matrix turning camera vectors
    # into body vectors is [a1]_1 [a2]_2 [a3]_3, where [a]_i turns the axes (not the vector) by a about
    # axis i, i.e. scipy's rotation by -a
    a1, a2, a3 = np.radians(CAMERA_ANGLES_DEG)
    R_body_cam = Rotation.from_euler("x", -a1) * Rotation.from_euler("y", -a2) * Rotation.from_euler("z", -a3)
    camera = ck_attitude(kernels["set"], "PROBE_NAVCAM", t)
    assert _angle(camera, body * R_body_cam).max() < 1e-14
    np.testing.assert_allclose(ck_attitude(kernels["set"], -77100, t).as_matrix(), camera.as_matrix(), atol=1e-15)
    # against SPICE's frame system, which walks the same chain itself (reading the CK at zero tolerance)
    for frame in ("PROBE_NAVCAM", "PROBE_TRACKER", "PROBE_ECLIPTIC_CAM"):
        with kernels["set"].loaded():
            R_frame_icrf = np.array([spiceypy.pxform("J2000", frame, float(x)) for x in t])
        assert _angle(ck_attitude(kernels["set"], frame, t), Rotation.from_matrix(R_frame_icrf).inv()).max() < 1e-14
    # the camera's boresight in ICRF: body +z turned through the mounting
    np.testing.assert_allclose(camera.apply([0.0, 0.0, 1.0]), body.apply(R_body_cam.apply([0.0, 0.0, 1.0])),
                               atol=1e-14)


def test_a_tolerance_reaches_the_nearest_record_past_the_coverage(kernels):
    late = NODES[-1] + 5.0
    nearest = ck_attitude(kernels["set"], "PROBE_NAVCAM", late, tolerance_s=10.0)
    assert _angle(nearest, ck_attitude(kernels["set"], "PROBE_NAVCAM", NODES[-1])) < 1e-15
    with pytest.raises(KernelError, match="have no pointing"):
        ck_attitude(kernels["set"], "PROBE_NAVCAM", late, tolerance_s=4.0)


def _one_line(excinfo) -> str:
    message = str(excinfo.value)
    assert "\n" not in message and "=====" not in message and "Toolkit version" not in message
    assert isinstance(excinfo.value, InputError) and isinstance(excinfo.value, EphemerisError)
    return message


def test_no_pointing_at_an_epoch_names_kernels_frame_epoch_and_coverage(kernels):
    t = np.array([NODES[3], NODES[-1], NODES[-1] + 60.0, NODES[-1] + 120.0])
    with pytest.raises(KernelError) as excinfo:
        ck_attitude(kernels["set"], "PROBE_NAVCAM", t)
    message = _one_line(excinfo)
    assert message.startswith("kernels probe.bc, probe.tsc, probe.tf have no pointing for frame 'PROBE_NAVCAM' "
                              "(CK id -77000) at 2025-05-08T19:14:20 TDB (800003660 s past J2000) (tolerance 0 s)")
    assert message.endswith("coverage: probe.bc 2025-05-08T18:13:20 TDB (800000000 s past J2000) to "
                            "2025-05-08T19:13:20 TDB (800003600 s past J2000)")


def test_a_frame_no_kernel_defines(kernels):
    with pytest.raises(KernelError) as excinfo:
        ck_attitude(kernels["set"], "PROBE_HAZCAM", T0)
    assert _one_line(excinfo) == ("frame 'PROBE_HAZCAM' is not defined by kernels probe.bc, probe.tsc, probe.tf: "
                                  "give a frame an FK defines, a frame id, or a CK id")


def test_a_ck_id_no_ck_holds(kernels):
    with pytest.raises(KernelError) as excinfo:
        ck_attitude(kernels["set"], -82000, T0)
    assert _one_line(excinfo) == "CK id -82000 is in no CK of kernels probe.bc, probe.tsc, probe.tf; the CKs hold " \
                                 "CK ids -77000"


def test_kernels_without_a_ck(kernels):
    with pytest.raises(KernelError) as excinfo:
        ck_attitude(KernelSet([default_kernel_path(), kernels["sclk"], kernels["fk"]]), "PROBE_NAVCAM", T0)
    assert _one_line(excinfo) == ("kernels de421.bsp, probe.tsc, probe.tf hold no CK (a binary DAF/CK file): "
                                  "no attitude for frame 'PROBE_NAVCAM' (CK id -77000)")


def test_no_sclk_loaded(kernels):
    with pytest.raises(KernelError) as excinfo:
        ck_attitude(KernelSet([kernels["ck"], kernels["fk"]]), "PROBE_SC", T0)
    assert _one_line(excinfo) == ("kernels probe.bc, probe.tf hold no SCLK for spacecraft clock -77 (needed by frame "
                                  "'PROBE_SC' (CK id -77000)): load the spacecraft's SCLK kernel (.tsc)")


def test_a_tt_clock_without_a_leapseconds_kernel(tmp_path, kernels):
    # SCLK01_TIME_SYSTEM 2: the clock's parallel time is TT, which SPICE reaches from TDB through the LSK
    tt = tmp_path / "probe_tt.tsc"
    tt.write_text(kernels["sclk"].read_text().replace("SCLK01_TIME_SYSTEM_77        = ( 1 )",
                                                      "SCLK01_TIME_SYSTEM_77        = ( 2 )"))
    assert tt.read_text() != kernels["sclk"].read_text()
    with pytest.raises(KernelError) as excinfo:
        ck_attitude(KernelSet([kernels["ck"], tt]), -77000, T0)
    assert _one_line(excinfo) == ("spacecraft clock -77 of kernels probe.bc, probe_tt.tsc keeps TT, not TDB (needed by "
                                  "CK id -77000): load a leapseconds kernel (.tls) for TDB to TT")


def test_an_epoch_before_the_clock_starts(kernels):
    with pytest.raises(KernelError) as excinfo:
        ck_attitude(kernels["set"], -77000, np.array([T0, T0 - 2 * 86_400.0]))
    message = _one_line(excinfo)
    assert message.startswith("spacecraft clock -77 of kernels probe.bc, probe.tsc, probe.tf cannot encode "
                              "2025-05-06T18:13:20 TDB (799827200 s past J2000) (for CK id -77000): SPICE(")


def test_a_ck_that_is_not_a_ck(tmp_path, kernels):
    from opnav.ephemeris.spk_writer import write_spk

    t = T0 + 600.0 * np.arange(10)
    states = np.hstack([np.tile([1.5e8, 0.0, 0.0], (10, 1)), np.tile([0.0, 30.0, 0.0], (10, 1))])
    write_spk(tmp_path / "probe.bc", t, states, body=-77, center=10)  # an SPK named as a CK
    with pytest.raises(KernelError) as excinfo:
        KernelSet([tmp_path / "probe.bc", kernels["sclk"]])
    assert "is a DAF/SPK file (DAF/SPK), but a .bc file must be DAF/CK" in _one_line(excinfo)
    (tmp_path / "text.bc").write_text("KPL/FK\n\\begindata\nFRAME_X = -1\n")
    with pytest.raises(KernelError) as excinfo:
        KernelSet([tmp_path / "text.bc"])
    assert "is a text kernel (KPL/FK), but a .bc file must be DAF/CK" in _one_line(excinfo)


@pytest.mark.parametrize("t, tolerance, expected", [
    (np.nan, 0.0, "epoch t is NaN or infinite"),
    (np.zeros((2, 2)), 0.0, "epochs t must be a scalar or a non-empty 1-D array, got shape (2, 2)"),
    (np.array([]), 0.0, "epochs t must be a scalar or a non-empty 1-D array, got shape (0,)"),
    (T0, -1.0, "tolerance_s must be >= 0 s, got -1.0"),
])
def test_bad_epochs_and_tolerances(kernels, t, tolerance, expected):
    with pytest.raises(KernelError) as excinfo:
        ck_attitude(kernels["set"], "PROBE_SC", t, tolerance_s=tolerance)
    assert _one_line(excinfo) == expected


def test_the_writer_refuses_what_it_cannot_write(tmp_path, kernels):
    with pytest.raises(InputError, match="ck_id must be an integer <= -1000"):
        write_ck(tmp_path / "x.bc", NODES, spin(NODES), ck_id=-77, sclk=kernels["sclk"])
    with pytest.raises(InputError, match="increasing"):
        write_ck(tmp_path / "x.bc", NODES[::-1], spin(NODES), ck_id=-77000, sclk=kernels["sclk"])
    with pytest.raises(InputError, match="attitudes has 60 rotations for 61 epochs"):
        write_ck(tmp_path / "x.bc", NODES, spin(NODES[1:]), ck_id=-77000, sclk=kernels["sclk"])
    with pytest.raises(InputError, match="clock_id must be a negative integer"):
        write_linear_sclk(tmp_path / "x.tsc", clock_id=77, start_tdb_s=T0)
