"""The campaign report page (``campaign.md`` / ``campaign.html``): the Monte Carlo ensemble in plots.

:func:`campaign_blocks` turns a campaign record (``campaign.json``, :mod:`opnav.studies.campaign`) and
each filter's :class:`Ensemble` (the runs' per-epoch errors, 1-sigmas and NEES, read by
:func:`load_ensemble`) into the page (:func:`opnav.studies.report_page.write_page` writes it):

- ``campaign_<filter>_errors``: every run's error per ICRF axis over the study window (grey), the
  sample +-3-sigma of the runs (3 x their standard deviation at each epoch, black) and the filter's
  +-3-sigma (3 x the RMS over the runs of its 1-sigma, blue band): a consistent filter's two agree;
- ``campaign_<filter>_nees``: the NEES (6 states) averaged over the runs at each epoch, against the
  95 % band of the mean of that many chi-square(6) values, the study window marked (the campaign's
  Monte Carlo NEES test, :func:`opnav.consistency.ensemble_nees`, judges the window);
- ``campaign_rms_histogram``: the runs' position and velocity RMS over the window, per filter, with
  the paper's figure and the posterior Cramer-Rao bound when the campaign has them.

Tables: the aggregate per filter, the paper's figures beside the campaign's, the Monte Carlo NEES test.
``<filter>`` in an id is the filter's name with ``-`` as ``_``. Studies with their own evaluation
(S2, S4) have no per-epoch arrays: their page is the aggregate table alone.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.ticker import FixedLocator, FormatStrFormatter, MaxNLocator, NullFormatter

from ..consistency import chi2_mean_bounds
from .common import NEES_STATES
from .report_page import Figure, Table, figure_id
from .report_plots import envelope_indices, figure_png, new_figure, utc_axis, utc_dates

#: The papers of the studies a campaign can run (docs/studies.md).
CITATIONS = {
    "s1": "Ma Pengbin, Baoyin Hexi, Mu Junshan: Autonomous navigation of Mars probe based on optical observation "
          "of Martian moon. Optics and Precision Engineering 22(4):863-869, 2014, doi:10.3788/OPE.20142204.0863",
    "s2": "Zhu Jiafang, Wang Xinlong, Li Qunsheng, Che Huan: Autonomous navigation model design and analysis for "
          "Mars probe in capture stage. Aero Weaponry 2017(5):18-24",
    "s3": "Wang Changhong, Wang Cunlian, Li Baohua: A method to realize GEO satellite autonomous navigation. "
          "Navigation Positioning and Timing 2014(2):12-19",
    "s4": "Zhang Heng, Zhang Wei, Chen Xiao: Study on deep space time registration method of integrated navigation "
          "system based on celestial angle and velocity measurements. Journal of Deep Space Exploration "
          "4(4):373-378, 2017, doi:10.15982/j.issn.2095-7777.2017.04.010",
}
#: Coverage of the NEES band.
PROBABILITY = 0.95


@dataclass(frozen=True)
class Ensemble:
    """One filter's runs at the epochs they share.

    Attributes
    ----------
    t_tdb_s : (N,) array
        Epochs, TDB s past J2000.
    nees : (R, N) array
        Each run's NEES (6 states).
    error : (R, N, 6) array or None
        Estimate minus truth ``[r km, v km/s]``, ICRF, about the study's centre (None when a run kept
        only its NEES).
    sigma : (R, N, 6) array or None
        The filter's 1-sigmas, same units.
    window_start_tdb_s : float
        Start of the study window (the RMS and the Monte Carlo NEES test), TDB s past J2000.
    """

    t_tdb_s: np.ndarray
    nees: np.ndarray
    error: np.ndarray | None
    sigma: np.ndarray | None
    window_start_tdb_s: float

    @property
    def runs(self) -> int:
        return int(self.nees.shape[0])


def nice_log_ticks(ax) -> None:
    """Label a log y axis at 1, 2, 5 times the powers of ten inside its limits, as plain numbers (the
    default labels every minor tick as ``2 x 10^0``, which crowd a short axis)."""
    low, high = ax.get_ylim()
    decades = range(int(np.floor(np.log10(low))), int(np.ceil(np.log10(high))) + 1)
    ticks = [m * 10.0**d for d in decades for m in (1, 2, 5) if low <= m * 10.0**d <= high]
    ax.yaxis.set_major_locator(FixedLocator(ticks))
    ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
    ax.yaxis.set_minor_formatter(NullFormatter())


def load_ensemble(files: list[Path], window_start_tdb_s: float) -> Ensemble:
    """The runs' arrays from their ``files`` (the runner's ``filters/<name>.npz`` or a campaign run's
    ``nees/<name>.npz``: ``t_tdb_s``, ``nees`` and, when kept, ``error`` and ``sigma``) at the epochs
    every run has (to the second). Raises ``OSError``/``ValueError``/``KeyError`` for a file that
    cannot be read (the caller says which)."""
    loaded = []
    for path in files:
        with np.load(path) as data:
            loaded.append({key: np.asarray(data[key]) for key in ("t_tdb_s", "nees", "error", "sigma")
                           if key in data.files})
    seconds = [np.round(run["t_tdb_s"]).astype(np.int64) for run in loaded]
    shared = seconds[0]
    for s in seconds[1:]:
        shared = np.intersect1d(shared, s)
    if shared.size == 0:
        raise ValueError("the runs share no epoch")
    picks = [np.searchsorted(s, shared) for s in seconds]
    full = all("error" in run and "sigma" in run for run in loaded)
    return Ensemble(
        t_tdb_s=loaded[0]["t_tdb_s"][picks[0]],
        nees=np.stack([run["nees"][p] for run, p in zip(loaded, picks)]),
        error=np.stack([run["error"][p, :6] for run, p in zip(loaded, picks)]).astype(float) if full else None,
        sigma=np.stack([run["sigma"][p, :6] for run, p in zip(loaded, picks)]).astype(float) if full else None,
        window_start_tdb_s=float(window_start_tdb_s))


#: ``histogram`` of :func:`campaign_blocks` and :func:`write_campaign_page` when the RMS histogram is to be
#: drawn there (a campaign on workers draws it on one: :func:`rms_histogram`).
DRAW_HERE = "draw here"


def campaign_blocks(record: dict, ensembles: dict[str, list], histogram: Figure | None | str = DRAW_HERE) -> list:
    """The campaign page: paragraphs, tables and figures from ``record`` (``campaign.json``) and, per
    filter, its blocks (:func:`filter_blocks`); ``histogram``: :func:`rms_histogram` of ``record`` drawn
    already, or ``DRAW_HERE``."""
    runs = record["runs"]
    seeds = [r["seed"] for r in runs]
    overrides = record.get("overrides") or {}
    blocks: list = [
        f"{len(runs)} runs of {Path(record['run_file']).name} (study {record['study'].upper()}, "
        f"{record['mode']} mode), seeds {seeds[0]} to {seeds[-1]}; settings changed: "
        + (", ".join(f"{k} = {v}" for k, v in overrides.items()) if overrides else "none") + ". "
        "Each run replays alone with `" + " ".join(["opnav run", str(record["run_file"]), "--seed SEED",
                                                    *(f"--set {k}={v}" for k, v in overrides.items()),
                                                    "--out DIR"]) + "`.",
        aggregate_table(record["aggregate"]),
    ]
    paper = paper_table(record)
    if paper is not None:
        blocks.append(paper)
    tests = {name: a["monte_carlo_nees"] for name, a in record["aggregate"].items() if "monte_carlo_nees" in a}
    if tests:
        blocks.append(monte_carlo_table(tests))
    if isinstance(histogram, str):
        histogram = rms_histogram(record)
    if histogram is not None:
        blocks.append(histogram)
    for name, filter_blocks in ensembles.items():
        blocks.append(f"## {name}")
        blocks += filter_blocks
    return blocks


def filter_blocks(name: str, ensemble: Ensemble | str) -> list:
    """One filter's part of the page: its error ensemble and NEES figures, or why it has none."""
    return [block for part in FILTER_PARTS for block in filter_part(name, ensemble, part)]


#: The parts of a filter's blocks (:func:`filter_part`): its error ensemble figure, its NEES figure.
FILTER_PARTS = ("errors", "nees")


def filter_part(name: str, ensemble: Ensemble | str, part: str) -> list:
    """Part ``part`` (:data:`FILTER_PARTS`) of :func:`filter_blocks`: ``errors``, the error ensemble
    figure (or why there is none, or why the filter has no figures); ``nees``, the NEES figure (nothing
    when the filter has no figures)."""
    if isinstance(ensemble, str):
        return [f"No ensemble plots for {name}: {ensemble}"] if part == "errors" else []
    if part == "nees":
        return [nees_figure(name, ensemble)]
    if ensemble.error is not None:
        return [error_ensemble_figure(name, ensemble)]
    return [f"Some runs of {name} kept only their NEES, not their per-epoch errors (files of an older "
            "opnav): no error ensemble plot. Delete their summary.json and resume the campaign to redo them."]


def _ensemble_from_files(files: list[str], window_start_tdb_s: float) -> Ensemble | str:
    """The ensemble in the runs' array ``files``, or why it cannot be read."""
    try:
        return load_ensemble([Path(f) for f in files], window_start_tdb_s)
    except READ_ERRORS as exc:
        return f"a run's arrays cannot be read ({exc})"


def filter_blocks_from_files(name: str, files: list[str], window_start_tdb_s: float) -> list:
    """:func:`filter_blocks` of the ensemble in the runs' array ``files``."""
    return filter_blocks(name, _ensemble_from_files(files, window_start_tdb_s))


def filter_part_from_files(name: str, files: list[str], window_start_tdb_s: float, part: str) -> list:
    """:func:`filter_part` of the ensemble in the runs' array ``files`` (a campaign worker's task: the page's
    figures are drawn where the runs were, a figure a task)."""
    return filter_part(name, _ensemble_from_files(files, window_start_tdb_s), part)


def _cell(stats: dict | None, digits: int) -> str:
    if not isinstance(stats, dict):
        return "-"
    low, high = f"{stats['min']:.{digits}f}", f"{stats['max']:.{digits}f}"
    return f"{stats['mean']:.{digits}f} ± {stats['std']:.{digits}f} [{low}, {high}]"


def aggregate_table(aggregate: dict) -> Table:
    """Per filter: the RMS figures over the runs (S1, S3), or one row per figure (S2, S4)."""
    if aggregate and all("position_rms_km" in a for a in aggregate.values()):
        rows = tuple((name, _cell(a["position_rms_km"], 3), _cell(a["velocity_rms_m_s"], 4),
                      f"{a['nees_mean']['mean']:.2f}", f"{a.get('final_position_sigma_km_mean', float('nan')):.3f}",
                      f"{a['runs_with_flags']}/{a['runs']}") for name, a in aggregate.items())
        return Table("Aggregate over the runs (study window)",
                     ("filter", "position RMS (km): mean ± std [min, max]", "velocity RMS (m/s): mean ± std [min, max]",
                      "NEES mean of the run means", "final position 1-sigma, mean (km)", "runs with consistency flags"),
                     rows)
    rows = []
    for name, a in aggregate.items():
        for key, value in a.items():
            if isinstance(value, dict) and {"mean", "std", "min", "max"} <= set(value) and key != "wall_s":
                rows.append((name, key.replace("_", " "), f"{value['mean']:.6g} ± {value['std']:.3g}",
                             f"{value['min']:.6g} to {value['max']:.6g}"))
    return Table("Aggregate over the runs", ("filter", "figure", "mean ± std", "min to max"), tuple(rows))


def paper_table(record: dict) -> Table | None:
    """The study's published figures beside the campaign's, with the citation (None without any)."""
    paper = record.get("paper") or {}
    if not paper:
        return None
    study = record["study"]
    note = f"Paper: {CITATIONS.get(study, study.upper())}." + (f" {paper['note']}." if paper.get("note") else "")
    if record.get("overrides"):
        note += (" This campaign changed settings (" + ", ".join(f"{k} = {v}" for k, v in record["overrides"].items())
                 + "): the paper's figures are for the study's own set-up.")
    aggregate = record["aggregate"]
    if "position_rms_km" in paper:
        rows = []
        for name, a in aggregate.items():
            if "position_rms_km" not in a:
                continue
            rows.append((name, f"{paper['position_rms_km']:g}", _cell(a["position_rms_km"], 3),
                         f"{paper.get('velocity_rms_m_s', float('nan')):g}", _cell(a["velocity_rms_m_s"], 4)))
        return Table("Paper beside the campaign", ("filter", "paper position RMS (km)",
                                                    "campaign position RMS (km): mean ± std [min, max]",
                                                    "paper velocity RMS (m/s)",
                                                    "campaign velocity RMS (m/s): mean ± std [min, max]"),
                     tuple(rows), note=note)
    if "table4" in paper:
        rows = []
        for name, ranges in paper["table4"].items():
            ours = aggregate.get(name, {}).get("position_rms_km")
            rows.append((name, f"{ranges['position_km'][0]:g} to {ranges['position_km'][1]:g}",
                         f"{ranges['velocity_m_s'][0]:g} to {ranges['velocity_m_s'][1]:g}",
                         _cell(ours, 3) if ours else "not run"))
        return Table("Paper beside the campaign",
                     ("filter", "paper: converged position error per axis (km)",
                      "paper: converged velocity error per axis (m/s)", "campaign position RMS (km): mean ± std"),
                     tuple(rows), note=note)
    if "claim" in paper:
        return Table("Paper", ("finding",), ((str(paper["claim"]),),), note=note)
    return Table("Paper", ("quantity", "value"), tuple((str(k).replace("_", " "), str(v)) for k, v in paper.items()
                                                      if not isinstance(v, (dict, list))), note=note)


def monte_carlo_table(tests: dict) -> Table:
    """The Monte Carlo NEES test per filter (:func:`opnav.consistency.ensemble_nees`)."""
    rows = []
    for name, test in tests.items():
        if not test.get("available"):
            rows.append((name, "-", "-", "-", "-", "-", f"not available: {test.get('reason', 'no reason recorded')}"))
            continue
        low, high = test["band"]
        verdict = ("inside" if low <= test["mean"] <= high else "above: covariance too small" if test["mean"] > high
                   else "below: covariance too large")
        rows.append((name, str(test["runs"]), str(test["epochs"]), f"{test['mean']:.2f}",
                     f"{low:.2f} to {high:.2f}", f"{test['share_inside']:.2f}", f"mean over the window {verdict}"))
    return Table(f"Monte Carlo NEES test over the study window ({NEES_STATES} states)",
                 ("filter", "runs", "epochs", "NEES averaged over runs and epochs",
                  f"{100 * PROBABILITY:g} % band of the run mean at one epoch", "share of epochs inside the band",
                  "reading"), tuple(rows),
                 note="At each epoch the NEES of the runs is averaged and compared with the band of the mean of that "
                      f"many chi-square({NEES_STATES}) values (Bar-Shalom, Li and Kirubarajan 2001, Sec. 5.4.2): a "
                      f"consistent filter has about {100 * PROBABILITY:g} % of the epochs inside.")


def rms_histogram(record: dict) -> Figure | None:
    """Histograms of the runs' position and velocity RMS per filter (None when the runs have no RMS)."""
    names = [n for n, a in record["aggregate"].items() if "position_rms_km" in a]
    if not names:
        return None
    fig, axes = new_figure(1, 2, height_in=3.8)
    paper = record.get("paper") or {}
    bound = record.get("posterior_crb") or {}
    colors = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple")
    for col, (key, scale_key, unit, paper_key, bound_key) in enumerate((
            ("position_rms_km", "position", "km", "position_rms_km", "pcrb_position_km"),
            ("velocity_rms_m_s", "velocity", "m/s", "velocity_rms_m_s", "pcrb_velocity_m_s"))):
        ax = axes[0, col]
        values = {n: np.array([r["filters"][n][key] for r in record["runs"] if n in r["filters"]]) for n in names}
        everything = np.concatenate(list(values.values()))
        edges = np.histogram_bin_edges(everything, bins=min(30, max(5, everything.size // 2)))
        # bars side by side: two filters with the same RMS would hide each other as outlines
        ax.hist([values[n] for n in names], bins=edges, color=list(colors[:len(names)]),
                label=[f"{n} ({values[n].size} runs)" for n in names])
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        if isinstance(paper.get(paper_key), (int, float)):
            ax.axvline(paper[paper_key], color="k", ls="--", lw=1.2, label=f"paper: {paper[paper_key]:g} {unit}")
        if isinstance(bound.get(bound_key), (int, float)):
            ax.axvline(bound[bound_key], color="0.4", ls=":", lw=1.4,
                       label=f"posterior CRB: {bound[bound_key]:.3g} {unit}")
        ax.set_xlabel(f"{scale_key} RMS over the study window ({unit})")
        ax.set_ylabel("runs")
        ax.legend(fontsize=8)
    return Figure("campaign_rms_histogram", "The runs' position and velocity RMS over the study window, per filter, "
                  "with the paper's figure and the posterior Cramér-Rao bound (RMS of its 1-sigma) where the campaign "
                  "has them: the spread is what one run's RMS can be expected to scatter by.", figure_png(fig))


def error_ensemble_figure(name: str, ensemble: Ensemble) -> Figure:
    """Every run's error per axis over the study window with the sample and the filter's +-3-sigma."""
    window = ensemble.t_tdb_s >= ensemble.window_start_tdb_s
    t = ensemble.t_tdb_s[window]
    error, sigma = ensemble.error[:, window], ensemble.sigma[:, window]
    fig, axes = new_figure(2, 3, height_in=6.4, sharex=True)
    ddof = 1 if ensemble.runs > 1 else 0
    for row, (scale, what, unit, offset) in enumerate(((1.0, "position", "km", 0), (1e3, "velocity", "m/s", 3))):
        for col, axis in enumerate("xyz"):
            ax = axes[row, col]
            x = utc_axis(ax, t, label=row == 1)
            err = scale * error[:, :, offset + col]
            sample = 3.0 * err.std(axis=0, ddof=ddof)
            filt = 3.0 * scale * np.sqrt(np.mean(sigma[:, :, offset + col] ** 2, axis=0))
            keep = envelope_indices(filt)
            ax.fill_between(x[keep], -filt[keep], filt[keep], color="tab:blue", alpha=0.2, lw=0,
                            label="filter ±3-sigma (RMS over runs)")
            # one set of indices for every run: the epochs where the ensemble reaches its extremes
            keep = np.union1d(envelope_indices(err.max(axis=0)), envelope_indices(err.min(axis=0)))
            for k, run in enumerate(err):
                ax.plot(x[keep], run[keep], color="0.45", lw=0.5, alpha=0.7, label="runs" if k == 0 else None)
            keep = envelope_indices(sample)
            ax.plot(x[keep], sample[keep], color="k", lw=1.3, label=f"sample ±3-sigma ({ensemble.runs} runs)")
            ax.plot(x[keep], -sample[keep], color="k", lw=1.3)
            ax.set_title(f"{what} {axis} ({unit})", fontsize=10)
    fig.legend(*axes[0, 0].get_legend_handles_labels(), loc="outside lower center", ncol=3, fontsize=9)
    fig.suptitle(f"{name}: estimate minus truth of every run (ICRF) over the study window", fontsize=11)
    return Figure(f"campaign_{figure_id(name)}_errors",
                  f"{name}: every run's error per ICRF axis over the study window (grey), the runs' sample ±3-sigma "
                  "(black) and the filter's own ±3-sigma (blue band, RMS over the runs): for a consistent filter the "
                  "black lines run along the band's edges; inside it the filter is pessimistic, outside it "
                  "overconfident.", figure_png(fig))


def nees_figure(name: str, ensemble: Ensemble) -> Figure:
    """The NEES averaged over the runs at each epoch against its band, the study window marked."""
    low, high = chi2_mean_bounds(NEES_STATES, ensemble.runs, PROBABILITY)
    mean = ensemble.nees.mean(axis=0)
    fig, axes = new_figure(1, 1, height_in=3.6)
    ax = axes[0, 0]
    x = utc_axis(ax, ensemble.t_tdb_s)
    ax.axhspan(low, high, color="tab:green", alpha=0.2,
               label=f"{100 * PROBABILITY:g} % band of the mean of {ensemble.runs} chi-square({NEES_STATES})")
    keep = envelope_indices(mean)
    ax.semilogy(x[keep], np.maximum(mean[keep], 1e-3), color="tab:purple", lw=0.9, label="NEES averaged over the runs")
    ax.axvline(utc_dates(np.array([ensemble.window_start_tdb_s]))[0], color="k", ls="--", lw=1.0,
               label="study window starts")
    ax.set_ylim(0.5 * min(low, float(np.min(mean))), 3.0 * max(high, float(np.max(mean))))
    nice_log_ticks(ax)
    ax.set_ylabel(f"mean NEES ({NEES_STATES} states)")
    ax.legend(fontsize=8, loc="upper right", ncol=3)
    window = ensemble.t_tdb_s >= ensemble.window_start_tdb_s
    inside = float(np.mean((mean[window] >= low) & (mean[window] <= high))) if np.any(window) else float("nan")
    return Figure(f"campaign_{figure_id(name)}_nees",
                  f"{name}: NEES averaged over the {ensemble.runs} runs at each epoch against the "
                  f"{100 * PROBABILITY:g} % band of that mean ({100 * inside:.0f} % of the window's epochs inside; about "
                  f"{100 * PROBABILITY:g} % for a consistent filter); above the band the filter is overconfident.",
                  figure_png(fig))


#: Exceptions a damaged or missing run file raises on reading.
READ_ERRORS = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile)


def run_arrays_file(folder: Path, name: str, summary: dict) -> Path:
    """The file of one campaign run's per-epoch arrays for filter ``name``: ``nees/<name>.npz`` for a run
    that kept only its figures (a quick or lockstep run, marked so in its summary), else the runner's
    ``filters/<name>.npz``."""
    kept_only_figures = bool(summary.get("quick") or summary.get("lockstep"))
    return Path(folder) / ("nees" if kept_only_figures else "filters") / f"{name}.npz"


def figure_calls(aggregate: dict, folders: list[str], summaries: list[dict]) -> list[tuple[str, list[str], float]]:
    """The arguments of :func:`filter_blocks_from_files` for each filter of ``aggregate`` (a campaign's,
    with its Monte Carlo NEES tests) whose runs' arrays the page plots: (name, the runs' array files,
    the window start). A campaign draws them on its workers as soon as the runs are done."""
    calls = []
    for name, a in aggregate.items():
        test = a.get("monte_carlo_nees")
        if test is None or not test.get("available"):
            continue
        files = [str(run_arrays_file(Path(folder), name, s)) for folder, s in zip(folders, summaries)
                 if name in s.get("filters", {})]
        calls.append((name, files, test["window_start_tdb_s"]))
    return calls


def write_campaign_page(out: Path, record: dict, folders: list[str], summaries: list[dict],
                        command: tuple[str, ...] | None = None, drawn: dict[str, list] | None = None,
                        histogram: Figure | None | str = DRAW_HERE) -> None:
    """``out/campaign.md``, ``out/campaign.html`` and their figures for campaign ``record`` whose runs are
    in ``folders`` with ``summaries``; ``command`` (argv; None from Python) goes into the provenance.
    ``drawn``: per filter, its blocks from :func:`filter_blocks_from_files` for :func:`figure_calls`
    (a campaign draws them on its workers); a filter missing there is drawn here. ``histogram``: the
    :func:`rms_histogram` of ``record`` drawn on a worker, or ``DRAW_HERE``."""
    from .report_page import provenance, write_page

    drawn = drawn or {}
    ensembles: dict = {}
    for name, a in record["aggregate"].items():
        test = a.get("monte_carlo_nees")
        if test is not None and not test.get("available"):
            ensembles[name] = filter_blocks(name, test.get("reason", "the runs' per-epoch arrays are not available"))
        elif test is not None:
            ensembles[name] = None  # the page keeps the filters' order
    for name, files, start in figure_calls(record["aggregate"], folders, summaries):
        ensembles[name] = drawn[name] if name in drawn else filter_blocks_from_files(name, files, start)
    seeds = [r["seed"] for r in record["runs"]]
    run_file = Path(record["run_file"])
    write_page(Path(out), f"Campaign: {run_file.name}, {len(seeds)} runs (seeds {seeds[0]}..{seeds[-1]})",
               campaign_blocks(record, ensembles, histogram), provenance(command, run_file if run_file.is_file() else None),
               name="campaign")
