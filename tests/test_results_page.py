"""benchmarks/results.py (the README's results section): an S1 row's ratio to the bound from its runs'
figures, and a study whose campaign folder is absent keeping its README block, once."""

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def results():
    spec = importlib.util.spec_from_file_location("results_page", ROOT / "benchmarks" / "results.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _figures(rms_km: float) -> dict:
    return {"position_rms_km": rms_km, "velocity_rms_m_s": 0.01, "nees_mean": 6.0, "nees_mean_arc": 6.0}


def _point(folder: Path, rms_km: list[float], bound_km: float, ukf_km: list[float] | None = None) -> None:
    folder.mkdir(parents=True)
    runs = [{"seed": 100 + i, "folder": str(folder / f"run_{i:03d}"),
             "filters": {"ekf": _figures(r), **({"ukf": _figures(ukf_km[i])} if ukf_km else {})}}
            for i, r in enumerate(rms_km)]
    record = {"runs": runs, "paper": {"position_rms_km": 8.737, "velocity_rms_m_s": 0.003},
              "posterior_crb": {"pcrb_position_km": bound_km, "pcrb_velocity_m_s": 0.01}}
    (folder / "campaign.json").write_text(json.dumps(record))


def test_an_s1_row_holds_the_rms_over_seeds_against_the_bound(results, tmp_path):
    rms = [30.0, 40.0, 50.0, 60.0]
    _point(tmp_path / "s1" / "month=jul,targets=both,noise_arcsec=0.1", rms, 40.0)
    sweep = results._s1_points(tmp_path / "s1")
    figures = results.s1_row(sweep["points"][0])
    assert figures["ratio"].ratio == pytest.approx(np.sqrt(np.mean(np.square(rms))) / 40.0)
    row = [line for line in results.s1_table(sweep) if line.startswith("| jul")][0]
    assert f"{figures['ratio'].ratio:.2f} [{figures['ratio'].low:.2f}, {figures['ratio'].high:.2f}]" in row
    assert figures["ratio"].verdict in row
    assert "UKF RMS" not in "\n".join(results.s1_table(sweep))  # no UKF column without UKF runs


def test_a_row_with_the_ukf_shows_its_ratio_beside_the_ekfs(results, tmp_path):
    _point(tmp_path / "s1" / "month=may,targets=phobos,noise_arcsec=1", [30.0, 40.0, 50.0], 40.0, [60.0, 80.0, 100.0])
    table = results.s1_table(results._s1_points(tmp_path / "s1"))
    header = [line for line in table if line.startswith("| month")][0]
    row = [line for line in table if line.startswith("| may")][0]
    assert header.count("|") == row.count("|")
    ukf = results.s1_row(results._s1_points(tmp_path / "s1")["points"][0], "ukf")["ratio"]
    assert ukf.ratio == pytest.approx(2.0 * np.sqrt(np.mean(np.square([30.0, 40.0, 50.0]))) / 40.0)
    assert f"{ukf.ratio:.2f} [{ukf.low:.2f}, {ukf.high:.2f}]" in row


def test_a_missing_campaign_keeps_its_readme_block_once(results, tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text("intro\n" + results.BEGIN + "\n<!-- results:s2 -->\n### S2 Table 3\n\n| a |\n\n"
                      + results.END + "\ntail\n")
    reproduce = tmp_path / "reproduce"
    for _ in range(2):
        text = readme.read_text()
        kept = results.readme_blocks(text.split(results.BEGIN, 1)[1].split(results.END, 1)[0])
        lines = results.build(reproduce, kept)
        readme.write_text(text.split(results.BEGIN)[0] + results.BEGIN + "\n" + "\n".join(lines) + "\n"
                          + results.END + text.split(results.END)[1])
    text = readme.read_text()
    assert "### S2 Table 3" in text and "| a |" in text
    assert text.count("Kept from the README as it was") == 1  # s2's; the others' "not run" lines are not kept
    assert "Not run yet: `make reproduce-s1`." in text and text.endswith("tail\n")
