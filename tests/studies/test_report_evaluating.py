"""S2 and S4 reports: their figures by id, tables instead of dicts, provenance, and the OEMs of every
estimated trajectory (read back by opnav.ccsds.read_oem and equal to the saved estimates)."""

import hashlib
import json
import re
from pathlib import Path

import numpy as np
import pytest

import opnav
from opnav.ccsds import read_oem
from opnav.studies.runner import RunOptions, run_study
from opnav.studies.settings import load_run_file

ROOT = Path(__file__).resolve().parents[2]
#: What a report must not show: Python dicts and lists printed raw.
RAW = ("{'", "`{", "': ", "['")


def _run(tmp_path_factory, sample: str, overrides: dict, name: str):
    out = tmp_path_factory.mktemp(name)
    run = load_run_file(ROOT / "samples" / sample, overrides)
    lines: list[str] = []
    summary = run_study(run, RunOptions(out=out, log=lines.append))
    return run, out, summary, lines


@pytest.fixture(scope="module")
def s2(tmp_path_factory):
    # half a day before the SOI and 12 h after it keep the switching run to seconds; the observability
    # tables are the study's own (hourly grid over its arcs)
    return _run(tmp_path_factory, "s2_capture.toml",
                {"arc_days": "0.5", "stop_before_periapsis_h": "36", "observability": "true"}, "s2")


@pytest.fixture(scope="module")
def s4(tmp_path_factory):
    return _run(tmp_path_factory, "s4_approach.toml", {"duration_hours": "6"}, "s4")


def _figure_ids(html: str) -> set[str]:
    return set(re.findall(r"<figure id='fig-([a-z0-9_]+)'", html))


def _check_page(out: Path, figures: tuple[str, ...], sample: str) -> str:
    html = (out / "report.html").read_text()
    md = (out / "report.md").read_text()
    assert _figure_ids(html) == set(figures)
    for figure in figures:
        png = (out / "figures" / f"{figure}.png").read_bytes()
        assert png.startswith(b"\x89PNG") and len(png) > 10_000
    for text in (html, md):
        for raw in RAW:
            assert raw not in text, f"raw dict/list text {raw!r} in the report"
    # what made the page: the run file with the SHA-256 of its bytes, opnav's version, the date
    provenance = html[html.index("<section id='provenance'>"):]
    run_file = ROOT / "samples" / sample
    assert str(run_file) in provenance and hashlib.sha256(run_file.read_bytes()).hexdigest() in provenance
    assert opnav.__version__ in provenance
    return html


def test_s2_report_has_its_figures_tables_and_provenance(s2):
    from opnav.studies.report_s2 import FIGURES, OBSERVABILITY_FIGURES

    run, out, summary, _ = s2
    html = _check_page(out, FIGURES + OBSERVABILITY_FIGURES, "s2_capture.toml")
    # the paper's Table 3 and Tables 1-2 figures stand beside opnav's, as table cells
    for printed in ("5.031", "14.552", "0.024417", "1.2599e+14"):
        assert f"<td>{printed}</td>" in html
    assert "S2 Table 3" in html and "Aero Weaponry" in html
    # the terminal table is still there
    assert summary["filters"]["ekf-switching"]["MPD (model 1)"]["nees_mean"] > 0


def test_s2_oems_are_the_switching_estimates(s2):
    run, out, summary, _ = s2
    with np.load(out / "evaluation.npz") as saved:
        t, state, sigma, inside = (saved[k] for k in ("switching_t_tdb_s", "switching_state", "switching_sigma",
                                                      "switching_inside_soi"))
    assert set(summary["estimates"]) == {"ekf-switching-model1", "ekf-switching-model2"}
    for name, center, keep in (("ekf-switching-model1", "SUN", ~inside), ("ekf-switching-model2", "MARS", inside)):
        oem = read_oem(out / "filters" / f"{name}.oem")
        assert oem.center == center and oem.ref_frame == "ICRF" and oem.object_name == run.spacecraft
        np.testing.assert_allclose(oem.t_tdb_s, t[keep], rtol=0, atol=1e-3)
        # positions of 1e8 km (heliocentric) and 1e5 km (Mars) written with enough digits for a metre
        np.testing.assert_allclose(oem.states[:, :3], state[keep, :3], rtol=0, atol=1e-3)
        np.testing.assert_allclose(oem.states[:, 3:], state[keep, 3:], rtol=0, atol=1e-9)
        np.testing.assert_allclose(np.sqrt(np.diagonal(oem.covariances, axis1=1, axis2=2)), sigma[keep], rtol=1e-6)
    # the switch hands the estimate over at the SOI crossing: phase 1 ends at it, phase 2 starts after it
    soi = summary["facts"]["soi_crossing_tdb_s"]
    assert t[~inside][-1] <= soi < t[inside][0]


def test_s4_report_shows_the_divergence_and_writes_three_oems(s4):
    from opnav.studies.report_s4 import FIGURES

    run, out, summary, _ = s4
    html = _check_page(out, FIGURES, "s4_approach.toml")
    assert "Journal of Deep Space Exploration" in html
    with np.load(out / "evaluation.npz") as saved:
        arrays = {k: saved[k] for k in saved.files}
    for name in ("exact", "registered", "unregistered"):
        oem = read_oem(out / "filters" / f"{name}.oem")
        assert oem.center == "SUN" and oem.object_name == run.spacecraft
        np.testing.assert_allclose(oem.t_tdb_s, arrays["t_tdb_s"], rtol=0, atol=1e-3)
        np.testing.assert_allclose(oem.states[:, :3], arrays[f"{name}_state"][:, :3], rtol=0, atol=1e-3)
        np.testing.assert_allclose(np.sqrt(np.diagonal(oem.covariances, axis1=1, axis2=2)), arrays[f"{name}_sigma"],
                                   rtol=1e-6)
        # the plotted error is the estimate minus a truth that does not depend on the case
        truth = arrays[f"{name}_state"] - arrays[f"{name}_error"]
        np.testing.assert_allclose(truth, arrays["exact_state"] - arrays["exact_error"], rtol=0, atol=1e-6)
    # what the figures show: holding the latest angle sample leaves the fused error beyond its own
    # 3-sigma at the end, while each record at its own time tag stays inside
    ratio = {name: np.max(np.abs(arrays[f"{name}_error"][-1, :3]) / arrays[f"{name}_sigma"][-1, :3])
             for name in ("exact", "unregistered")}
    assert ratio["unregistered"] > 3.0 > ratio["exact"]
    assert json.loads((out / "summary.json").read_text())["estimates"]["registered"]["center"] == "sun"


def test_a_rerun_reuses_the_stage_and_redoes_it_when_a_file_changed(s4):
    # after the other S4 test: it reads the files this one rewrites
    run, out, summary, _ = s4
    lines: list[str] = []
    again = run_study(run, RunOptions(out=out, log=lines.append))
    assert "evaluate (reused)" in again["stages_wall_s"]
    assert again["filters"] == summary["filters"]
    oem = out / "filters" / "unregistered.oem"
    oem.write_text(oem.read_text().replace("SUN", "MARS", 1))
    lines.clear()
    third = run_study(run, RunOptions(out=out, log=lines.append))
    assert "evaluate" in third["stages_wall_s"] and any("checksums" in line for line in lines)
    assert read_oem(oem).center == "SUN"
