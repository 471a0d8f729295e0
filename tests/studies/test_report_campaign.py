"""The campaign page: the error ensemble with the sample and the filter 3-sigma, the Monte Carlo NEES
against its band, the RMS histogram, tables instead of dicts, provenance."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from opnav.consistency import chi2_mean_bounds
from opnav.studies.campaign import run_campaign
from opnav.studies.report_campaign import load_ensemble, run_arrays_file

ROOT = Path(__file__).resolve().parents[2]
S1 = str(ROOT / "samples" / "s1_jul_both_0.1.toml")
RAW = ("{'", "`{", "': ", "['")


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    out = tmp_path_factory.mktemp("campaign")
    # full runs (each through the runner, with its filters/<name>.npz); a one-day arc every 10 minutes
    record = run_campaign(S1, runs=3, out=out, overrides={"duration_days": "1", "step_s": "600"}, filters=("ekf",),
                          quick=False, command=("opnav", "montecarlo", S1, "--runs", "3"))
    return out, record


def test_campaign_page_has_its_figures_tables_and_provenance(campaign):
    out, record = campaign
    html = (out / "campaign.html").read_text()
    md = (out / "campaign.md").read_text()
    ids = set(re.findall(r"<figure id='fig-([a-z0-9_]+)'", html))
    assert ids == {"campaign_ekf_errors", "campaign_ekf_nees", "campaign_rms_histogram"}
    for figure in ids:
        assert (out / "figures" / f"{figure}.png").read_bytes().startswith(b"\x89PNG")
    for text in (html, md):
        for raw in RAW:
            assert raw not in text, f"raw dict/list text {raw!r} in the campaign page"
    provenance = html[html.index("<section id='provenance'>"):]
    assert "opnav montecarlo" in provenance and "SHA-256" in provenance
    # the paper's figure beside the campaign's, with the citation and a word on the changed settings
    assert "Optics and Precision Engineering" in html and "duration_days = 1" in html
    test = record["aggregate"]["ekf"]["monte_carlo_nees"]
    assert f"<td>{test['mean']:.2f}</td>" in html


def test_the_ensemble_is_what_the_runs_saved(campaign):
    out, record = campaign
    summaries = [json.loads((Path(r["folder"]) / "summary.json").read_text()) for r in record["runs"]]
    files = [run_arrays_file(Path(r["folder"]), "ekf", s) for r, s in zip(record["runs"], summaries)]
    assert all(f.parent.name == "filters" for f in files)
    test = record["aggregate"]["ekf"]["monte_carlo_nees"]
    ensemble = load_ensemble(files, test["window_start_tdb_s"])
    assert ensemble.runs == 3 and ensemble.error.shape == (3, ensemble.t_tdb_s.size, 6)
    # the NEES the page averages over the window is the one the campaign's Monte Carlo test judged
    window = ensemble.t_tdb_s >= ensemble.window_start_tdb_s
    assert np.count_nonzero(window) == test["epochs"]
    np.testing.assert_allclose(ensemble.nees[:, window].mean(), test["mean"], rtol=1e-12)
    assert tuple(test["band"]) == pytest.approx(chi2_mean_bounds(6, 3, 0.95))
    # the RMS the histogram bins is the window RMS of the plotted errors
    rms = np.sqrt(np.mean(np.sum(ensemble.error[:, window, :3] ** 2, axis=2), axis=1))
    np.testing.assert_allclose(rms, [r["filters"]["ekf"]["position_rms_km"] for r in record["runs"]], rtol=1e-9)


def test_load_ensemble_keeps_the_epochs_every_run_has(tmp_path):
    from opnav.filters.estimates import save_npz

    t = 1000.0 * np.arange(6)
    rng = np.random.default_rng(5)
    save_npz(tmp_path / "a.npz", t_tdb_s=t, nees=rng.random(6), error=rng.random((6, 6)), sigma=rng.random((6, 6)))
    save_npz(tmp_path / "b.npz", t_tdb_s=t[1:] + 0.2, nees=rng.random(5))  # a run that kept only its NEES
    ensemble = load_ensemble([tmp_path / "a.npz", tmp_path / "b.npz"], window_start_tdb_s=2000.0)
    np.testing.assert_array_equal(ensemble.t_tdb_s, t[1:])
    assert ensemble.nees.shape == (2, 5) and ensemble.error is None and ensemble.sigma is None
    save_npz(tmp_path / "c.npz", t_tdb_s=t + 1e5, nees=rng.random(6))
    with pytest.raises(ValueError, match="share no epoch"):
        load_ensemble([tmp_path / "a.npz", tmp_path / "c.npz"], window_start_tdb_s=0.0)
