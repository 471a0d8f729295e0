"""The mission's navigation camera oriented by a CK (``attitude = "ck"``): a CK of the spacecraft's body
frame written from the pointing law, read through the FK's camera frame mounted on it, gives the pointing
law's attitudes to the CK's interpolation accuracy, and at the CK's own records the very frames and
records of the pointing law; a target off the detector is not imaged (listed); bad keys refused in one line."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from opnav.cli import main
from opnav.epochs import parse_epoch
from opnav.errors import InputError
from opnav.ephemeris.ck_writer import write_ck, write_linear_sclk
from opnav.sim.sensors import Sky, loop_sources
from opnav.studies import mission
from opnav.studies.mission_images import ck_pointing, pointing
from opnav.studies.settings import load_run_file

#: The camera's mounting on the spacecraft body in the FK: TKFRAME angles (deg) about axes 1, 2, 3.
MOUNTING_DEG = (90.0, 15.0, -40.0)
#: The CK's records every 60 s.
CK_STEP_S = 60.0

FK = f"""KPL/FK

Probe -77: body frame PROBE_SC is CK structure -77000 (clock -77); the navigation camera PROBE_NAVCAM is fixed
on it, its axes opnav's camera axes (+z boresight, +x along columns, +y along rows).

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
TKFRAME_-77100_ANGLES    = ( {MOUNTING_DEG[0]} {MOUNTING_DEG[1]} {MOUNTING_DEG[2]} )
\\begintext
"""

SAMPLE = Path(__file__).resolve().parents[2] / "samples" / "cislunar.toml"
#: Three record epochs of the sample, the Moon only (the Earth fills the frame before 02:42).
START, STOP = "2027-02-28T03:00:00", "2027-02-28T06:00:00"
#: The CK turns the camera this far off the pointing law at the last record epoch: the Moon off a 20-deg field.
OFF_RAD = np.radians(30.0)


def _mounting() -> Rotation:
    """``R_sc_cam`` of the FK's angles, independently of opnav's reader: NAIF's frames.req makes
    [a1]_1 [a2]_2 [a3]_3 turn camera vectors into the body's, [a]_i turning the axes by a about axis i
    (scipy's rotation by -a); tests/ephemeris/test_ck.py holds this against SPICE's pxform."""
    a1, a2, a3 = np.radians(MOUNTING_DEG)
    return Rotation.from_euler("x", -a1) * Rotation.from_euler("y", -a2) * Rotation.from_euler("z", -a3)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """The sample cut to the Moon at three epochs (pointing law), its SCLK and FK among the kernels, and
    the pointing law's camera attitudes at CK records every minute (``law_at``)."""
    folder = tmp_path_factory.mktemp("mission_ck")
    base = load_run_file(SAMPLE).settings
    sclk = write_linear_sclk(folder / "probe.tsc", clock_id=-77, start_tdb_s=float(parse_epoch(START, "tdb")) - 86_400.0)
    (folder / "probe.tf").write_text(FK)
    # the CK runs read the same kernels plus the CK, so both take the bodies from one source
    law = replace(base, start=START, stop=STOP, targets=("moon",), camera_exposure_s=base.camera_exposure_s[0],
                  noise_arcsec=3.0, kernels=(str(sclk), str(folder / "probe.tf")))
    _, epochs = mission.record_epochs(law)
    eph = mission.truth_ephemeris(law)
    _, sources, _ = loop_sources(Sky(kernels=law.kernels), catalog=False)

    def law_at(t):
        """The pointing law's camera attitudes (camera -> ICRF) at TDB epochs ``t``, from the truth there."""
        states = mission.truth_states(law, t)
        r_c, v_c = eph.state(law.center, t, center="ssb")
        return pointing("moon", t, states[:, :3] + r_c, states[:, 3:] + v_c, sources)[0]

    def with_ck(name, nodes, R_icrf_cam):
        """``law`` with ``attitude = "ck"``: the body frame's CK written from the camera attitudes given."""
        ck = write_ck(folder / f"{name}.bc", nodes, R_icrf_cam * _mounting().inv(), ck_id=-77000, sclk=sclk)
        return replace(law, kernels=(*law.kernels, str(ck)), attitude="ck", ck_frame="PROBE_NAVCAM")

    return {"folder": folder, "law": law, "epochs": epochs, "law_at": law_at, "with_ck": with_ck}


def test_between_its_records_the_ck_gives_the_pointing_law_to_its_interpolation_remainder(setup):
    # CK records every minute, the record epochs half-way between two (where the constant-rate turn between
    # records misses most): h^2 / 8 |dw/dt| to leading order (tests/ephemeris/test_ck.py), with h^2 dw/dt
    # read off the law's own records around the epoch: the turn of the step after the interval against
    # the step before it is 2 h^2 dw/dt at mid-interval (to O(h^3))
    epochs = setup["epochs"]
    nodes = np.arange(epochs[0] - 90.0, epochs[-1] + 91.0, CK_STEP_S)
    law_nodes = setup["law_at"](nodes)
    settings = setup["with_ck"]("midway", nodes, law_nodes)
    miss = (ck_pointing(settings, epochs) * setup["law_at"](epochs).inv()).magnitude()
    k = np.searchsorted(nodes, epochs)  # the epoch lies between records k - 1 and k
    step_after, step_before = law_nodes[k + 1] * law_nodes[k].inv(), law_nodes[k - 1] * law_nodes[k - 2].inv()
    remainder = (step_after * step_before.inv()).magnitude() / 2.0 / 8.0
    np.testing.assert_allclose(miss, remainder, rtol=1e-3)  # measured within 5e-5 of it


def test_at_its_records_the_ck_gives_the_pointing_law_s_frames_and_records(setup, tmp_path):
    """CK records every minute on the record epochs: the camera's attitudes are the law's to rounding, so
    the frames rendered and the records measured are the law's, bit for bit; at the last epoch the CK
    turns the camera 30 deg away, and the Moon is not imaged there, with the reason listed."""
    epochs = setup["epochs"]
    nodes = np.arange(epochs[0] - 2 * CK_STEP_S, epochs[-1] + 2.5 * CK_STEP_S, CK_STEP_S)
    assert np.isin(epochs, nodes).all()
    R_nodes = setup["law_at"](nodes)
    turned = nodes >= epochs[-1] - CK_STEP_S  # the last record epoch and its neighbours: no interpolation across
    R_nodes = Rotation.concatenate([R * Rotation.from_rotvec([OFF_RAD, 0.0, 0.0]) if off else R
                                    for R, off in zip(R_nodes, turned)])
    settings = setup["with_ck"]("on_records", nodes, R_nodes)
    at_records = ck_pointing(settings, epochs)
    law_records = setup["law_at"](epochs)
    assert ((at_records * law_records.inv()).magnitude()[:-1] < 1e-14).all()
    assert abs((at_records * law_records.inv()).magnitude()[-1] - OFF_RAD) < 1e-12

    law = mission.simulate_images(setup["law"], 11, tmp_path / "law")
    ck = mission.simulate_images(settings, 11, tmp_path / "ck")
    assert len(law.records) == 3 and len(ck.records) == 2
    for a, b in zip(law.records, ck.records):
        assert a.t_tdb_s == b.t_tdb_s and a.target == b.target == "moon"
        np.testing.assert_array_equal(a.value, b.value)
        np.testing.assert_array_equal(a.covariance, b.covariance)
    images = ck.facts["images"]
    assert images["attitude"] == "ck" and law.facts["images"]["attitude"] == "pointing"
    assert images["wrong_body"] == 0 and images["gross_errors"] == 0 and images["not_imaged"] == 1
    (reason,) = images["not_imaged_first"].values()
    assert reason.startswith("off the navigation camera's detector at the CK's attitude (PROBE_NAVCAM")


def test_the_run_file_keys(setup, tmp_path):
    """``attitude``/``ck_frame`` from a run file (``--set``), in measurement mode as well (it ignores them)."""
    ck = write_ck(tmp_path / "probe.bc", setup["epochs"][[0, -1]] + [-60.0, 60.0],
                  setup["law_at"](setup["epochs"][[0, -1]]), ck_id=-77000, sclk=setup["law"].kernels[0])
    kernels = ",".join([*setup["law"].kernels, str(ck)])
    run = load_run_file(SAMPLE, {"attitude": "CK", "ck_frame": "PROBE_NAVCAM", "kernels": kernels, "start": START,
                                 "stop": STOP})
    assert run.settings.attitude == "ck" and run.settings.ck_frame == "PROBE_NAVCAM"
    out = tmp_path / "measurements"
    assert main(["run", str(SAMPLE), "--mode", "measurements", "--out", str(out), "--filters", "ekf", "--no-progress",
                 *[f"--set={k}={v}" for k, v in (("attitude", "ck"), ("ck_frame", "PROBE_NAVCAM"), ("kernels", kernels),
                                                 ("start", START), ("stop", STOP))]]) == 0
    assert json.loads((out / "summary.json").read_text())["mode"] == "measurements"


def test_bad_attitude_keys_are_one_line(setup):
    law = setup["law"]
    cases = [
        (dict(attitude="ck"), "attitude = 'ck' needs ck_frame (the CK, its SCLK and the FK among kernels"),
        (dict(ck_frame="PROBE_NAVCAM"), "ck_frame is read only with attitude = 'ck' (attitude is 'pointing')"),
        (dict(attitude="ck", ck_frame="PROBE_NAVCAM", ck_tolerance_s=-1.0), "ck_tolerance_s must be >= 0 s, got -1.0"),
        (dict(attitude="sun"), "attitude must be one of pointing, ck, got 'sun'"),
        (dict(attitude="ck", ck_frame="PROBE_NAVCAM"),
         "ck_frame: kernels de421.bsp, probe.tsc, probe.tf hold no CK (a binary DAF/CK file): no attitude for "
         "frame 'PROBE_NAVCAM' (CK id -77000)"),
    ]
    for changes, message in cases:
        with pytest.raises(InputError) as excinfo:
            replace(law, **changes)
        assert "\n" not in str(excinfo.value) and str(excinfo.value).startswith(message), str(excinfo.value)
    # a CK that stops before the last record epoch: the epoch and the CK's coverage named when the file is read
    epochs = setup["epochs"]
    ck = write_ck(setup["folder"] / "short.bc", epochs[:2], setup["law_at"](epochs[:2]), ck_id=-77000,
                  sclk=law.kernels[0])
    with pytest.raises(InputError) as excinfo:
        replace(law, kernels=(*law.kernels, str(ck)), attitude="ck", ck_frame="PROBE_NAVCAM")
    message = str(excinfo.value)
    assert message.startswith("ck_frame: kernels de421.bsp, probe.tsc, probe.tf, short.bc have no pointing for frame "
                              "'PROBE_NAVCAM' (CK id -77000) at 2027-02-28T06:00:00 TDB") and "coverage: short.bc" in message
