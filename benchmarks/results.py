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
import sys
from pathlib import Path

import numpy as np

from opnav.records import atomic_write_text
from opnav.studies.bound_ratio import mean_nees, rms_over_bound
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


S1_FILTER = "ekf"
#: A bound check of at least this many seeds on a row at the bound is listed as a control.
CONTROL_SEEDS = 20
PASS_NAMES = {"ekf": "EKF", "restarted": "EKF restarted from its answer", "ukf": "UKF"}


def s1_table(sweep: dict) -> list[str]:
    """S1 Tables 2-3 (module notes): per row the seeds' RMS beside the bound with the ratio's interval,
    and the NEES over the window and the arc with their bands."""
    runs = sweep["runs"]
    filters = sorted({name for row in sweep["points"] for run in row["runs"] for name in run})
    ukf_note = ("" if "ukf" in filters else
                " EKF only: in the 10-seed campaign of both filters (`--filters ekf,ukf`) the UKF's RMS equalled "
                "the EKF's to 4 digits in every row.")
    lines = [f"### S1 Tables 2-3: RMS over the last 15 days, {runs} seeds a point", "",
             "Each row has its own seeds (no common random numbers across rows)." + ukf_note, "",
             "RMS over seeds: the root mean square over the seeds of each seed's position RMS over the window "
             "(the mean over seeds in brackets: it is smaller, by Jensen's inequality). PCRB: the posterior "
             "Cramér-Rao bound along the truth, the square root of the mean over the same window of the trace of "
             "its 3x3 position block: the least RMS any estimator can have on average. Ratio: RMS over seeds / PCRB, "
             "with its 95 % interval (BCa bootstrap over the seeds, `opnav.studies.bound_ratio`): 1 inside means the "
             "filter reaches the bound. NEES (6 states): the runs' mean over the window and over the whole arc, each "
             "with the 95 % band of a mean over that many independent runs (chi-square(6 N) / N).", "",
             "| month | targets | noise | seeds | EKF position RMS over seeds (km) [mean; min, max] | PCRB (km) | "
             "RMS / PCRB [95 %] | against the bound | NEES window [band] | NEES arc [band] | "
             + ("UKF RMS over seeds (km), / PCRB [95 %], NEES window | " if "ukf" in filters else "")
             + "paper (km) | paper vs seeds | EKF velocity RMS (m/s) | paper (m/s) |",
             "|---|---|---|---|---|---|---|---|---|---|" + ("---|" if "ukf" in filters else "") + "---|---|---|---|"]
    if "unfinished" in sweep:
        lines[0] += f" ({sweep['unfinished']}: {len(sweep['points'])} of 24 points)"
    for row in sweep["points"]:
        figures = s1_row(row)
        if figures is None:
            continue
        point, paper = row["point"], row["paper"]
        figure = paper.get("position_rms_km")
        ratio, window, arc = figures["ratio"], figures["nees_window"], figures["nees_arc"]
        rms = figures["rms_km"]
        lines.append(
            f"| {point.get('month', 'jul')} | {point.get('targets', 'both')} | {point.get('noise_arcsec', '0.1')}\" | "
            f"{ratio.seeds if ratio else rms.size} | "
            f"{np.sqrt(np.mean(rms**2)):.1f} [{rms.mean():.1f}; {rms.min():.1f}, {rms.max():.1f}] | "
            f"{f'{ratio.bound_km:.1f}' if ratio else '-'} | "
            f"{f'{ratio.ratio:.2f} [{ratio.low:.2f}, {ratio.high:.2f}]' if ratio else '-'} | "
            f"{ratio.verdict if ratio else '-'} | {_nees_cell(window)} | {_nees_cell(arc)} | "
            + (f"{_ukf_cell(row)} | " if "ukf" in filters else "")
            + f"{figure} | {_versus_seeds(rms, figure) if figure is not None else '-'} | "
            f"{_spread(_stats(figures['velocity_m_s']), 3)} | {paper.get('velocity_rms_m_s', '-')} |")
    return lines + [""] + s1_against_the_bound(sweep)


def _ukf_cell(row: dict) -> str:
    figures = s1_row(row, "ukf")
    if figures is None:
        return "-"
    ratio = figures["ratio"]
    rms = figures["rms_km"]
    shown = f"{ratio.ratio:.2f} [{ratio.low:.2f}, {ratio.high:.2f}]" if ratio else "-"
    return f"{np.sqrt(np.mean(rms**2)):.1f}, {shown}, {figures['nees_window'].mean:.2f}"


def _row_name(point: dict) -> str:
    return f"{point.get('month')} {point.get('targets')} {point.get('noise_arcsec')}\""


def s1_against_the_bound(sweep: dict) -> list[str]:
    """The text under the S1 table: which rows miss the bound or the NEES band, and what
    ``benchmarks/s1_bound_check.py`` found on their seeds (``sweep["checks"]``, by point folder name)."""
    rows = [(row, s1_row(row)) for row in sweep["points"]]
    rows = [(row, figures) for row, figures in rows if figures is not None and figures["ratio"] is not None]
    if not rows:
        return []
    checks = sweep.get("checks", [])
    off = [(row, figures) for row, figures in rows if figures["ratio"].verdict != "reaches the bound"]
    lines = [f"**Against the bound.** {len(rows) - len(off)} of {len(rows)} rows reach the bound (1 inside the "
             "ratio's 95 % interval). Were every row at the bound, about one in 14 would still miss 1 (the "
             "bootstrap interval of a mean of 50 one-degree-of-freedom draws covers about 93 %, "
             "`tests/studies/test_bound_ratio.py`): a row outside is a question, answered on its own seeds by "
             "`benchmarks/s1_bound_check.py`, which runs the EKF again over the same records from its own final "
             "estimate propagated back to the arc's start (a batch initialisation). How the rows and checks below "
             "read: docs/studies.md, S1, \"What the 50-seed table shows\"."]
    ukf = [(row, s1_row(row, "ukf")) for row, _ in rows]
    ukf = [(row, figures["ratio"]) for row, figures in ukf if figures is not None and figures["ratio"] is not None]
    if ukf:
        lines[0] += (f" The UKF, on the same records: {sum(r.verdict == 'reaches the bound' for _, r in ukf)} of "
                     f"{len(ukf)} rows reach the bound"
                     + "".join(f"; {_row_name(row['point'])} {r.ratio:.2f} [{r.low:.2f}, {r.high:.2f}], {r.verdict}"
                               for row, r in ukf if r.verdict != "reaches the bound") + ".")
    for row, figures in off:
        ratio = figures["ratio"]
        text = f"- {_row_name(row['point'])}: {ratio.ratio:.2f} [{ratio.low:.2f}, {ratio.high:.2f}], {ratio.verdict}."
        mine = [check for check in checks if _same_point(check["point"], row["point"])]
        if not mine:
            text += " Not checked yet (`benchmarks/s1_bound_check.py`)."
        seeds = set(_run_seeds(row))
        for check in mine:
            ekf, restarted = check["ekf"], check["restarted"]
            fresh = not seeds.intersection(check["seeds"])
            text += (f" Seeds {check['seeds'][0]}-{check['seeds'][-1]} ({'fresh ones, none of the table' if fresh else 'the table'}"
                     f"'s): EKF {ekf['ratio']:.2f} [{ekf['low']:.2f}, {ekf['high']:.2f}], {ekf['verdict']}; restarted "
                     f"{restarted['ratio']:.2f} [{restarted['low']:.2f}, {restarted['high']:.2f}], {restarted['verdict']} "
                     f"(the restart scales the seeds' mean square by {check['restarted_over_ekf_mean_square']:.3f})"
                     + (f"; UKF {check['ukf']['ratio']:.2f} [{check['ukf']['low']:.2f}, {check['ukf']['high']:.2f}] "
                        f"(mean square {check['ukf_over_ekf_mean_square']:.4f} of the EKF's)" if "ukf" in check else "")
                     + ".")
        fresh = [check for check in mine if not seeds.intersection(check["seeds"])]
        if fresh:
            pooled = rms_over_bound(np.concatenate([figures["rms_km"]] + [check["rms_km"]["ekf"] for check in fresh]),
                                    ratio.bound_km)
            text += (f" The table's seeds and the fresh ones together ({pooled.seeds}): EKF {pooled.ratio:.2f} "
                     f"[{pooled.low:.2f}, {pooled.high:.2f}], {pooled.verdict}.")
        lines.append(text)
    controls = [check for check in checks if len(check["seeds"]) >= CONTROL_SEEDS
                and not any(_same_point(check["point"], row["point"]) for row, _ in off)]
    for check in controls:
        text = (f"- Control, a row at the bound ({_row_name(check['point'])}, {len(check['seeds'])} seeds): the restart "
                f"scales the mean square by {check['restarted_over_ekf_mean_square']:.3f} (ratio "
                f"{check['ekf']['ratio']:.2f} -> {check['restarted']['ratio']:.2f}).")
        lines.append(text)
    window = [r for r in (f["nees_window"] for _, f in rows)]
    arc = [r for r in (f["nees_arc"] for _, f in rows)]
    outside = [f"{_row_name(row['point'])} ({part})" for (row, f) in rows
               for part, nees in (("window", f["nees_window"]), ("arc", f["nees_arc"])) if not nees.inside]
    run_window = np.concatenate([_run_values(row, "nees_mean") for row, _ in rows])
    run_arc = np.concatenate([_run_values(row, "nees_mean_arc") for row, _ in rows])
    pooled_window, pooled_arc = mean_nees(run_window), mean_nees(run_arc)
    lines += ["", f"**NEES.** {len(outside)} of {len(window) + len(arc)} figures lie outside their 95 % band"
              + (f" ({', '.join(outside)})" if outside else "") + f"; at 95 % about {0.05 * (len(window) + len(arc)):.1f} "
              f"would by chance. Over all {run_window.size} runs the mean NEES is {pooled_window.mean:.2f} over the "
              f"window and {pooled_arc.mean:.2f} over the arc, against the band of {run_window.size} runs "
              f"[{pooled_window.low:.2f}, {pooled_window.high:.2f}]; the runs' window means vary by "
              f"{run_window.var(ddof=1):.1f} (a consistent filter's: at most 12, the variance of one chi-square(6))."]
    for row, f in rows:
        if not f["nees_window"].inside or not f["nees_arc"].inside:
            values = _run_values(row, "nees_mean")
            top = int(np.argmax(values))
            seed = _run_seeds(row)[top] if len(_run_seeds(row)) == values.size else None
            rest = np.delete(values, top)
            text = (f"- {_row_name(row['point'])}: its largest run's window mean is {values[top]:.1f}"
                    + (f" (seed {seed})" if seed is not None else "") + f" (a chi-square(6) exceeds it with probability "
                    f"{chi2_survival(values[top]):.1e}); without that run the row's window mean is {rest.mean():.2f}, "
                    f"its median {np.median(values):.2f}.")
            for check in checks:
                if seed in check["seeds"] and _same_point(check["point"], row["point"]) and "nees_window_arc" in check:
                    k = check["seeds"].index(seed)
                    text += (" Run again (`benchmarks/s1_bound_check.py`), its window NEES: " + ", ".join(
                        f"{PASS_NAMES[name]} {pairs[k][0]:.2f}" for name, pairs in check["nees_window_arc"].items())
                        + ": the same records give the same NEES whichever filter reads them.")
            lines.append(text)
    return lines


def _run_values(row: dict, key: str, name: str = S1_FILTER) -> np.ndarray:
    return np.array([run[name][key] for run in row["runs"] if name in run])


def _same_point(a: dict, b: dict) -> bool:
    return {k: str(v) for k, v in a.items()} == {k: str(v) for k, v in b.items()}


def _run_seeds(row: dict) -> list[int]:
    return [int(seed) for seed in row.get("seeds", [])]


def chi2_survival(value: float, dof: int = 6) -> float:
    from scipy.stats import chi2

    return float(chi2.sf(value, dof))


def s1_row(row: dict, name: str = S1_FILTER) -> dict | None:
    """One S1 point's figures for filter ``name`` from its runs' figures (None when no run has it):
    ``rms_km`` and ``velocity_m_s`` (per seed), ``ratio`` (:class:`~opnav.studies.bound_ratio.BoundRatio`
    or None without a bound), ``nees_window`` and ``nees_arc`` (:class:`~opnav.studies.bound_ratio.MeanNEES`)."""
    figures = [run[name] for run in row["runs"] if name in run]
    if not figures:
        return None
    rms = np.array([f["position_rms_km"] for f in figures])
    bound = row.get("posterior_crb")
    ratio = rms_over_bound(rms, bound["pcrb_position_km"]) if bound and rms.size >= 3 else None
    return {"rms_km": rms, "velocity_m_s": np.array([f["velocity_rms_m_s"] for f in figures]), "ratio": ratio,
            "nees_window": mean_nees([f["nees_mean"] for f in figures]),
            "nees_arc": mean_nees([f["nees_mean_arc"] for f in figures])}


def _nees_cell(nees) -> str:
    return f"{nees.mean:.2f} [{nees.low:.2f}, {nees.high:.2f}]{'' if nees.inside else ' out'}"


def _stats(values: np.ndarray) -> dict:
    return {"mean": float(values.mean()), "std": float(values.std(ddof=1)) if values.size > 1 else 0.0,
            "min": float(values.min()), "max": float(values.max())}


def _versus_seeds(values: np.ndarray, paper: float) -> str:
    return _versus(_stats(values), paper)


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
    """Every point of the S1 sweep in ``folder`` (``KEY=V,KEY=V`` folders): the point, its runs' figures
    per filter, the paper's row and the bound. A point whose ``campaign.json`` is not written yet
    (an unfinished sweep) gives the runs finished so far (``run_NNN/summary.json``) and the bound its
    campaign computed first (``posterior_bound.json``)."""
    points, unfinished = [], False
    for path in sorted(p for p in folder.glob("*=*") if p.is_dir()):
        point = dict(item.split("=", 1) for item in path.name.split(","))
        campaign = _load(path / "campaign.json")
        if campaign is not None:
            runs = [run["filters"] for run in campaign["runs"]]
            seeds = [run["seed"] for run in campaign["runs"]]
            paper, bound = campaign["paper"], campaign.get("posterior_crb")
        else:
            unfinished = True
            summaries = [s for s in (_load(p) for p in sorted(path.glob("run_*/summary.json"))) if s]
            if not summaries:
                continue
            runs = [s["filters"] for s in summaries]
            seeds = [s["run"].get("seed") for s in summaries]
            paper = summaries[0].get("paper", {})
            bound = (_load(path / "posterior_bound.json") or {}).get("bound")
        points.append({"point": point, "runs": runs, "seeds": seeds, "paper": paper, "posterior_crb": bound})
    if not points:
        return None
    order = {name: k for k, name in enumerate(("may", "jun", "jul", "aug", "phobos", "deimos", "both"))}
    points.sort(key=lambda p: (order.get(p["point"].get("month"), 9), order.get(p["point"].get("targets"), 9),
                               float(p["point"].get("noise_arcsec", 0))))
    record = {"runs": min(len(p["runs"]) for p in points), "points": points,
              "checks": [json.loads(path.read_text())
                         for path in sorted((folder.parent / "s1_bound_check").glob("*=*.json"))]}
    if unfinished:
        record["unfinished"] = "the sweep is not finished: the runs done so far"
    return record


#: Each study's block in the generated section starts with this marker (``{study}`` its folder name).
BLOCK = "<!-- results:{study} -->"
KEPT = "Kept from the README as it was: `{folder}` was not there when this section was generated."


def build(reproduce: Path, kept: dict[str, list[str]] | None = None) -> list[str]:
    """Every table whose campaign exists under ``reproduce``; for one that does not, its block of
    ``kept`` (the README's, :func:`readme_blocks`) with a line saying so, else a line asking for it."""
    lines = ["Generated by `benchmarks/results.py` from the campaigns of `make reproduce` "
             f"(`{reproduce}`); nothing here is typed by hand.", ""]
    sources = (("s1", None, s1_table, "make reproduce-s1"), ("s2", "campaign.json", s2_table, "make reproduce-s2"),
               ("s3", "campaign.json", s3_table, "make reproduce-s3"),
               ("s3_sensors", "campaign.json", lambda c: s3_table(c, "sensors"), "make reproduce-s3"),
               ("s4", "campaign.json", s4_table, "make reproduce-s4"))
    for study, name, table, command in sources:
        record = _s1_points(reproduce / study) if name is None else _load(reproduce / study / name)
        lines.append(BLOCK.format(study=study))
        if record:
            lines += table(record) + [""]
        elif kept and kept.get(study) and not any(line.startswith("Not run yet:") for line in kept[study]):
            note = KEPT.format(folder=reproduce / study)
            lines += [line for line in kept[study] if line != note] + [note, ""]
        else:
            lines += [f"### {study.upper()}", "", f"Not run yet: `{command}`.", ""]
    return lines


def readme_blocks(section: str) -> dict[str, list[str]]:
    """The blocks of a generated section, by study (the lines after each study's marker, up to the next;
    trailing blank lines dropped)."""
    blocks: dict[str, list[str]] = {}
    study = None
    for line in section.splitlines():
        if line.startswith("<!-- results:") and line.endswith(" -->"):
            study = line[len("<!-- results:"):-len(" -->")]
            blocks[study] = []
        elif study is not None:
            blocks[study].append(line)
    for block in blocks.values():
        while block and not block[-1].strip():
            block.pop()
    return blocks


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reproduce", default="out/reproduce", help="folder of the campaigns (default out/reproduce)")
    parser.add_argument("--readme", help="README to update between the results markers")
    args = parser.parse_args()
    reproduce = Path(args.reproduce)
    kept, readme_text = None, None
    if args.readme:
        readme = Path(args.readme)
        if not readme.is_file():
            print(f"--readme {readme}: no such file", file=sys.stderr)
            return 2
        readme_text = readme.read_text()
        if BEGIN not in readme_text or END not in readme_text:
            print(f"{readme}: no {BEGIN} ... {END} section to replace", file=sys.stderr)
            return 2
        kept = readme_blocks(readme_text.split(BEGIN, 1)[1].split(END, 1)[0])
    lines = build(reproduce, kept)
    reproduce.mkdir(parents=True, exist_ok=True)
    atomic_write_text(reproduce / "results.md", "\n".join(lines) + "\n")
    atomic_write_text(reproduce / "results.html", markdown_page("opnav results beside the papers", lines))
    print("\n".join(lines))
    if args.readme:
        head, rest = readme_text.split(BEGIN, 1)
        _, tail = rest.split(END, 1)
        atomic_write_text(readme, head + BEGIN + "\n" + "\n".join(lines) + "\n" + END + tail)
        print(f"updated {readme}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
