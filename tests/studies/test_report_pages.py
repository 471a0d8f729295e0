"""Run reports of S1 and S3 (measurement and image mode): the plots each study's story needs (by figure id),
tables instead of raw dicts, the provenance block, and the arrays behind the plots."""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import numpy as np
import pytest

from opnav.cli import main
from opnav.errors import InputError
from opnav.records import KIND_SIZE
from opnav.studies.runner import RunOptions, run_study
from opnav.studies.settings import load_run_file

REPO = Path(__file__).resolve().parents[2]
S1 = REPO / "samples" / "s1_jul_both_0.1.toml"
S3 = REPO / "samples" / "s3_geo.toml"
DEMO = REPO / "opnav" / "data" / "demo_run.toml"

#: Small versions of the acceptance runs: (run file, extra arguments, filters, image mode).
RUNS = {
    "s1": (S1, ["--set", "duration_days=0.5", "--set", "step_s=600"], ("ekf", "ukf"), False),
    "s3": (S3, ["--set", "duration_hours=1", "--filters", "ekf"], ("ekf",), False),
    "demo": (DEMO, ["--set", "duration_days=0.25"], ("ekf",), True),
}
#: Figures of each filter, and of each image-mode study's sensors.
FILTER_FIGURES = ("errors", "residuals", "nis", "nees")
SAMPLE_FIGURES = {"s1": ("sample_frame",), "s3": ("sample_frame_star_sensor", "sample_frame_earth_sensor")}


def _run(out: Path, run_file: Path, extra: list[str]) -> Path:
    assert main(["run", str(run_file), "--out", str(out), "--no-progress", *extra]) == 0
    return out


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    root = tmp_path_factory.mktemp("reports")
    return {name: _run(root / name, run_file, extra) for name, (run_file, extra, _, _) in RUNS.items()}


def _check_page(out: Path, study: str, filters, images: bool, run_file: Path) -> str:
    page = (out / "report.html").read_text()
    md = (out / "report.md").read_text()
    expected = [f"{f}_{kind}" for f in filters for kind in FILTER_FIGURES]
    if images:
        expected += list(SAMPLE_FIGURES[study])
    for figure in expected:
        assert f"<figure id='fig-{figure}'>" in page, figure
        assert (out / "figures" / f"{figure}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", figure
    # no raw Python dict or list text anywhere a reader looks
    for text in (page, md):
        for raw in ("{'", "`{", "': ", "['"):
            assert raw not in text, raw
    assert "<section id='provenance'>" in page and "## Provenance" in md
    assert hashlib.sha256(run_file.read_bytes()).hexdigest() in page
    assert "opnav version" in page and "git revision" in page and "date (UTC)" in page
    # the NEES columns say they are over the window and the whole arc; the arc is in calendar UTC
    assert "share of epochs with NEES in its 95 % band: window / whole arc" in page
    assert "NEES mean: window / whole arc" in page
    assert re.search(r"from \d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC to \d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC", page)
    return page


@pytest.mark.parametrize("name", sorted(RUNS))
def test_report_has_its_study_figures_tables_and_provenance(reports, name):
    run_file, _, filters, images = RUNS[name]
    study = "s3" if run_file == S3 else "s1"
    page = _check_page(reports[name], study, filters, images, run_file)
    citation = {"s1": "Ma Pengbin, Baoyin Hexi, Mu Junshan", "s3": "Wang Changhong, Wang Cunlian, Li Baohua"}[study]
    assert "<h3>Paper beside opnav</h3>" in page and citation in page


def test_s3_image_report_shows_both_sensors(tmp_path, monkeypatch):
    """The page of an S3 image run. Its Earth sensor's limb calibration from 50 noisy frames instead of
    200 (most of the run's time; a standard error of ~0.006 km, inside what the run accepts): the
    calibration itself is tested in test_s3_images."""
    from functools import partial

    from opnav.studies import s3_images

    monkeypatch.setattr(s3_images, "calibrate_limb_altitude", partial(s3_images.calibrate_limb_altitude,
                                                                        noisy_frames=50))
    out = _run(tmp_path / "s3img", S3, ["--mode", "images", "--set", "duration_hours=0.02", "--filters", "ekf"])
    _check_page(out, "s3", ("ekf",), True, S3)


def test_track_arrays_hold_rtn_errors_and_innovation_sigmas(reports):
    for name in ("s1", "s3"):
        data = np.load(reports[name] / "filters" / "ekf.npz")
        # the RTN axes are a rotation: lengths and the covariance's trace survive it
        for block in (slice(0, 3), slice(3, 6)):
            np.testing.assert_allclose(np.linalg.norm(data["error_rtn"][:, block], axis=1),
                                       np.linalg.norm(data["error"][:, block], axis=1), rtol=1e-9)
            np.testing.assert_allclose(np.sum(data["sigma_rtn"][:, block] ** 2, axis=1),
                                       np.sum(data["sigma"][:, block] ** 2, axis=1), rtol=1e-9)
        # each innovation sigma is the square root of its covariance's diagonal: for any positive definite
        # S, r^T S^-1 r >= r_i^2 / S_ii (Cauchy-Schwarz), with equality for one-value records
        used = data["accepted"] & np.isfinite(data["nis"])
        ratio = np.nanmax((data["residual"] / data["residual_sigma"]) ** 2, axis=1)[used]
        assert np.all(ratio <= data["nis"][used] * (1 + 1e-9))
        assert np.all(ratio >= 0.0) and np.all(np.isfinite(ratio))
        # each record's kind, read back through its index, has the record's size
        kinds = data["kind_names"][data["record_kind"]]
        assert np.array_equal([KIND_SIZE[k] for k in kinds], data["dof"])
        assert set(data["target_names"][data["record_target"]]) == ({"earth"} if name == "s3" else {"phobos", "deimos"})


def test_icrf_errors_on_request(reports, tmp_path):
    out = reports["s3"]
    _run(out, S3, RUNS["s3"][1] + ["--report-frame", "icrf"])
    assert "Estimate minus truth (ICRF)" in (out / "report.md").read_text()
    _run(out, S3, RUNS["s3"][1])
    assert "Estimate minus truth (RTN)" in (out / "report.md").read_text()
    with pytest.raises(InputError, match="--report-frame must be one of rtn, icrf"):
        run_study(load_run_file(S3, {"duration_hours": "1"}), RunOptions(out=tmp_path / "x", report_frame="lvlh"))


def test_report_removes_figures_its_earlier_version_had(reports):
    out = reports["s3"]
    png = b"\x89PNG\r\n\x1a\n"
    # a figure an older report linked, and one of another page in the same folder
    (out / "figures" / "ekf_consistency.png").write_bytes(png)
    (out / "figures" / "calibration_vectors.png").write_bytes(png)
    md = out / "report.md"
    md.write_text(md.read_text() + "\n![ekf_consistency](figures/ekf_consistency.png)\n")
    _run(out, S3, RUNS["s3"][1])
    assert not (out / "figures" / "ekf_consistency.png").exists()
    assert (out / "figures" / "calibration_vectors.png").exists() and (out / "figures" / "ekf_errors.png").exists()
