"""The papers' tables from the campaigns under ``out/reproduce`` (``make reproduce``), as Markdown.

Writes ``REPRODUCE/results.md`` and ``results.html`` and, with ``--readme``, replaces the
README's section between ``<!-- results:begin -->`` and ``<!-- results:end -->`` with the same
tables, so the README's results are generated, not typed. A study whose campaign is missing
is listed as not run. Each row gives our seed distribution (mean ± std [min, max]), the
filters' own 1-sigma and NEES beside the paper's figure, and says when the paper's figure
lies outside the seeds' range.

    python benchmarks/results.py --reproduce out/reproduce --readme README.md
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from opnav.records import atomic_write_text
from opnav.studies.report import markdown_page

BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"


def _load(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def _spread(stats: dict, digits: int = 3) -> str:
    return (f"{stats['mean']:.{digits}f} ± {stats['std']:.{digits}f} "
            f"[{stats['min']:.{digits}f}, {stats['max']:.{digits}f}]")


def _versus(stats: dict, paper: float) -> str:
    if paper < stats["min"]:
        return "paper below every seed"
    if paper > stats["max"]:
        return "paper above every seed"
    return "inside the seeds' range"


def s1_table(sweep: dict) -> list[str]:
    runs = sweep["runs"]
    lines = [f"### S1 Tables 2-3: RMS over the last 15 days, {runs} seeds a point", "",
             "PCRB: the posterior Cramér-Rao bound along the truth (1-sigma, RMS over the same window, to compare with the RMS columns), "
             "the best any unbiased filter can do with these measurements.", "",
             "| month | targets | noise | EKF position (km) | UKF position (km) | EKF 1-sigma at the end (km) | PCRB (km) | NEES | "
             "paper (km) | paper vs seeds | EKF velocity (m/s) | paper (m/s) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    if "unfinished" in sweep:
        lines[0] += f" ({sweep['unfinished']}: {len(sweep['points'])} of 24)"
    for row in sweep["points"]:
        point, agg, paper = row["point"], row["aggregate"], row["paper"]
        ekf, ukf = agg.get("ekf"), agg.get("ukf")
        if ekf is None:
            continue
        figure = paper.get("position_rms_km")
        bound = row.get("posterior_crb")
        shown_bound = f"{bound['pcrb_position_km']:.1f}" if bound else "-"
        lines.append(f"| {point.get('month', 'jul')} | {point.get('targets', 'both')} | {point.get('noise_arcsec', '0.1')}\" | "
                     f"{_spread(ekf['position_rms_km'], 1)} | "
                     f"{_spread(ukf['position_rms_km'], 1) if ukf else '-'} | "
                     f"{ekf.get('final_position_sigma_km_mean', float('nan')):.1f} | {shown_bound} | "
                     f"{ekf['nees_mean']['mean']:.2f} | "
                     f"{figure} | {_versus(ekf['position_rms_km'], figure) if figure is not None else '-'} | "
                     f"{_spread(ekf['velocity_rms_m_s'], 3)} | {paper.get('velocity_rms_m_s', '-')} |")
    return lines


def s2_table(campaign: dict) -> list[str]:
    agg = campaign["aggregate"]["ekf-switching"]
    runs = agg["runs"]
    paper = campaign["paper"]
    lines = [f"### S2 Table 3: switching EKF (MPD before the SOI, MPS after), {runs} seeds", "",
             "| phase | position error after convergence, mean (km) | its variance (km^2) | NEES | "
             "1-sigma at end (km) | paper mean / variance | paper vs seeds |", "|---|---|---|---|---|---|---|"]
    for phase, key in (("MPD (model 1)", "MPD"), ("MPS (model 2)", "MPS")):
        mean = agg[f"{phase}.position_error_mean_km"]
        figure = paper["table3"][key]
        lines.append(f"| {phase} | {_spread(mean, 2)} | {agg[f'{phase}.position_error_var_km2']['mean']:.1f} | "
                     f"{agg[f'{phase}.nees_mean']['mean']:.2f} | {agg[f'{phase}.sigma_position_km_at_end']['mean']:.2f} | "
                     f"{figure[0]} / {figure[1]} | {_versus(mean, figure[0])} |")
    summary = _load(Path(campaign["runs"][0]["folder"]) / "summary.json")
    if summary and "observability" in summary:
        lines += ["", "### S2 Tables 1-2: observability per measurement set (deterministic)", "",
                  "| model | set | rank | condition number | CRB position 1-sigma (km) | paper rank | paper condition |",
                  "|---|---|---|---|---|---|---|"]
        for model, sets in summary["observability"].items():
            table = paper["table1_2"][model[-1]]
            for name, rep in sets.items():
                crb = ", ".join(f"{v:.3g}" for v in rep["crb_sigma_position_km"])
                figure = table.get(name, ("-", "-", "-", "-"))
                lines.append(f"| {model[-1]} | {name} | {rep['rank']} | {rep['condition_number']:.3g} | {crb} | "
                             f"{figure[0]} | {figure[3]} |")
        lines += ["", "Condition numbers depend on the scaling of the state; the paper's scaling is not stated."]
    return lines


S3_NOISE = {"paper": "the study's noise: independent white noise on the angle (star sensor, 5\" 3-sigma) and on the "
                      "elevation (UV Earth sensor, 20\")",
            "sensors": "the sensors' noise: the angle also carries the Earth sensor's centre error and the elevation "
                       "shares it (`--set noise_model=sensors`; what an image stage gives): the filters' 1-sigma and RMS about 4x larger"}


def s3_table(campaign: dict, noise: str = "paper") -> list[str]:
    paper = campaign["paper"]["table4"]
    runs = len(campaign["runs"])
    lines = [f"### S3 Table 4 ({noise} noise): position RMS over the last 12 h, {runs} seeds", "",
             f"Measurement noise: {S3_NOISE[noise]}.", "",
             "| filter | position RMS (km) | velocity RMS (m/s) | NEES | filter 1-sigma at end (km) | "
             "paper position range (km) | paper velocity range (m/s) |", "|---|---|---|---|---|---|---|"]
    for name, agg in campaign["aggregate"].items():
        figure = paper.get(name, {})
        lines.append(f"| {name} | {_spread(agg['position_rms_km'])} | {_spread(agg['velocity_rms_m_s'], 4)} | "
                     f"{agg['nees_mean']['mean']:.2f} | {agg.get('final_position_sigma_km_mean', float('nan')):.3f} | "
                     f"{tuple(figure.get('position_km', ()))} | {tuple(figure.get('velocity_m_s', ()))} |")
    return lines


def s4_table(campaign: dict) -> list[str]:
    runs = len(campaign["runs"])
    lines = [f"### S4: federated filter, angle data leading the velocity clock, {runs} seeds", "",
             "| filter | final position error (km) | its 1-sigma (km) | final velocity error (m/s) | "
             "worst axis error / sigma |", "|---|---|---|---|---|"]
    for name, agg in campaign["aggregate"].items():
        lines.append(f"| {name} | {_spread(agg['final_position_error_km'], 1)} | "
                     f"{agg['final_position_sigma_km']['mean']:.1f} | {_spread(agg['final_velocity_error_m_s'], 3)} | "
                     f"{_spread(agg['max_axis_error_in_sigma'], 2)} |")
    lines += ["", f"Paper: {campaign['paper'].get('claim', campaign['paper'])}."]
    return lines


def _s1_points(folder: Path) -> dict | None:
    """The sweep record, or the points finished so far (``KEY=V,KEY=V`` folders) of an unfinished sweep."""
    record = _load(folder / "sweep.json")
    if record is not None:
        return record
    points = []
    for path in sorted(folder.glob("*=*/campaign.json")):
        campaign = json.loads(path.read_text())
        point = dict(item.split("=", 1) for item in path.parent.name.split(","))
        points.append({"point": point, "aggregate": campaign["aggregate"], "paper": campaign["paper"],
                       "posterior_crb": campaign.get("posterior_crb"), "runs": len(campaign["runs"])})
    if not points:
        return None
    return {"runs": min(p["runs"] for p in points), "points": points,
            "unfinished": "the sweep is not finished: the points done so far"}


def build(reproduce: Path) -> list[str]:
    """Every table whose campaign exists under ``reproduce``; a line for each one that does not."""
    lines = ["Generated by `benchmarks/results.py` from the campaigns of `make reproduce` "
             f"(`{reproduce}`); nothing here is typed by hand.", ""]
    sources = (("s1", None, s1_table, "make reproduce-s1"), ("s2", "campaign.json", s2_table, "make reproduce-s2"),
               ("s3", "campaign.json", s3_table, "make reproduce-s3"),
               ("s3_sensors", "campaign.json", lambda c: s3_table(c, "sensors"), "make reproduce-s3"),
               ("s4", "campaign.json", s4_table, "make reproduce-s4"))
    for study, name, table, command in sources:
        record = _s1_points(reproduce / study) if name is None else _load(reproduce / study / name)
        lines += (table(record) if record else [f"### {study.upper()}", "", f"Not run yet: `{command}`."]) + [""]
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reproduce", default="out/reproduce", help="folder of the campaigns (default out/reproduce)")
    parser.add_argument("--readme", help="README to update between the results markers")
    args = parser.parse_args()
    reproduce = Path(args.reproduce)
    lines = build(reproduce)
    reproduce.mkdir(parents=True, exist_ok=True)
    atomic_write_text(reproduce / "results.md", "\n".join(lines) + "\n")
    atomic_write_text(reproduce / "results.html", markdown_page("opnav results beside the papers", lines))
    print("\n".join(lines))
    if args.readme:
        readme = Path(args.readme)
        text = readme.read_text()
        if BEGIN not in text or END not in text:
            raise SystemExit(f"{readme}: no {BEGIN} ... {END} section to replace")
        head, rest = text.split(BEGIN, 1)
        _, tail = rest.split(END, 1)
        atomic_write_text(readme, head + BEGIN + "\n" + "\n".join(lines) + "\n" + END + tail)
        print(f"updated {readme}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
