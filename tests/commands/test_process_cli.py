"""`opnav process` as the README gives it: the bodies the frames show by default, the file's own count,
and one clear line instead of an empty result (issue 36)."""

import json
import shutil
from pathlib import Path

import pytest

from opnav.cli import main
from opnav.image.directory import frame_targets, known_bodies
from opnav.records import read_csv

ROOT = Path(__file__).resolve().parents[2]
DEMO = ROOT / "opnav" / "data" / "demo.toml"


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """The demo's first three frames (its seed: the frames `opnav demo` renders): Phobos, Deimos and Mars
    in the truth files; both moons measured in the third."""
    folder = tmp_path_factory.mktemp("process") / "frames"
    assert main(["render", str(DEMO), "--out", str(folder), "--stop", "2014-07-15T02:00:30", "--no-progress"]) == 0
    return folder


def one_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if not line.startswith("WARNING")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_without_targets_the_frames_bodies_are_measured_and_the_count_is_the_files(frames, tmp_path, capsys):
    """The README's `opnav process FRAMES --out x.csv`: the moons the truth files name are measured (Mars,
    their primary, only when asked), and the printed count is the file's, the pair counted once."""
    out = tmp_path / "m.csv"
    assert main(["process", str(frames), "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    records = read_csv(out)
    kinds = {kind: sum(r.kind == kind for r in records) for kind in {r.kind for r in records}}
    assert kinds.get("radec_pair", 0) >= 1 and set(kinds) <= {"radec", "radec_pair"}
    assert printed.startswith(f"{len(records)} records (")
    assert all(f"{n} {kind}" in printed for kind, n in kinds.items())
    assert "from 3 of 3 frames" in printed and "targets deimos, phobos" in printed
    assert "mars also, measured only with --targets" in printed
    assert json.loads(out.with_suffix(".json").read_text())["targets"] == ["deimos", "phobos"]


def test_frames_that_name_no_body_need_targets_one_line(frames, tmp_path, capsys):
    bare = tmp_path / "bare"
    bare.mkdir()
    for path in frames.glob("*.fits"):
        shutil.copy(path, bare / path.name)  # no truth files, no OBJECT keyword
    assert main(["process", str(bare), "--out", str(tmp_path / "m.csv"), "--no-progress"]) == 2
    line = one_line(capsys)
    assert "--targets is needed" in line and ", ".join(known_bodies()) in line and str(bare) in line
    assert not (tmp_path / "m.csv").exists()


def test_unknown_targets_are_one_line_before_any_frame(frames, tmp_path, capsys):
    assert main(["process", str(frames), "--out", str(tmp_path / "m.csv"), "--targets", "phobos", "titan",
                 "--no-progress"]) == 2
    line = one_line(capsys)
    assert "--targets: unknown body titan; known: deimos, earth, mars, phobos" in line
    assert not (tmp_path / "m.csv").exists()


def test_no_record_is_an_error_naming_the_skip_reasons(frames, tmp_path, capsys):
    """The Earth is in none of these frames: no record, exit 2 (not exit 0 with an empty file)."""
    out = tmp_path / "m.csv"
    assert main(["process", str(frames), "--out", str(out), "--targets", "earth", "--no-catalog",
                 "--no-progress"]) == 2
    line = one_line(capsys)
    assert "no records" in line and "earth" in line and str(out.with_suffix(".json")) in line


def test_frame_targets_read_truth_files_and_the_object_keyword(frames, tmp_path):
    from astropy.io import fits

    found = frame_targets(frames)
    assert found.named == ("deimos", "mars", "phobos") and found.frames == found.described == 3
    assert found.point == ("deimos", "phobos") and found.resolved == ("mars",)
    assert found.default() == ("deimos", "phobos")
    # a frame without a truth file: its OBJECT keyword; only resolved bodies: those are the default
    path = tmp_path / "earth.fits"
    fits.PrimaryHDU(header=fits.Header([("OBJECT", "Earth")])).writeto(path)
    earth = frame_targets(tmp_path)
    assert earth.named == ("earth",) and earth.default() == ("earth",) and "OBJECT" in earth.source


def test_camera_covariance_white_adds_j_c_jt_where_consider_keeps_j(frames, tmp_path, capsys):
    """`--camera-covariance` (the camera file's [calibration] covariance C in each moon record) and
    `--camera-error consider` (the Jacobian J kept instead) measure the same moons: the white file's
    covariances are the plain file's plus J C J^T of the consider file's J, record by record (a pair's two moons share the one camera error, so its cross-covariance gains J_1 C J_2^T too), and the
    .json says which was done."""
    import numpy as np

    from opnav.camera import CameraCovariance, write_camera_file
    from opnav.records import camera_jacobian
    from opnav.studies.s1 import load_demo

    camera = load_demo()[0].camera
    C = np.diag([4.0, 0.64, 0.64, 1e-8])  # f, cx, cy px^2; k1
    C[0, 1] = C[1, 0] = 0.5  # correlated, as a calibration's are
    calibrated = tmp_path / "calibrated.toml"
    write_camera_file(calibrated, camera, CameraCovariance(("f", "cx", "cy", "k1"), C, {}))
    files = {}
    for name, extra in {"plain": [], "white": ["--camera-covariance"],
                        "consider": ["--camera-covariance", "--camera-error", "consider"]}.items():
        files[name] = tmp_path / f"{name}.csv"
        assert main(["process", str(frames), "--camera", str(calibrated), *extra, "--out", str(files[name]),
                     "--no-progress"]) == 0
    capsys.readouterr()
    plain, white, consider = (read_csv(files[n]) for n in ("plain", "white", "consider"))
    assert [json.loads(files[n].with_suffix(".json").read_text())["camera_error"] for n in files] == [None, "white",
                                                                                                   "consider"]
    assert len(plain) == len(white) == len(consider) >= 3
    for p, w, c in zip(plain, white, consider):
        assert p.target == w.target == c.target and np.array_equal(p.value, c.value)
        assert np.array_equal(p.covariance, c.covariance) and camera_jacobian(p) is None
        names, J = camera_jacobian(c)
        assert names == ("f", "cx", "cy", "k1")
        added = J @ C @ J.T
        assert np.allclose(w.covariance, p.covariance + added, rtol=1e-9, atol=1e-9 * np.max(np.abs(added)))
        assert np.all(np.diag(added) > 0.0)
    assert any(p.size == 4 for p in plain)  # a pair: its cross-covariance gains J_1 C J_2^T (one camera error)
