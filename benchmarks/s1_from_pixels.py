"""S1 from pixels against S1 from measurements at the noise the image stage achieved.

Reads the image-mode runs already made (``--pixels``: one folder per run, e.g. made with
``opnav run samples/s1_jul_both_0.1.toml --mode images --set month=jul --seed 1 --out
out/pixels/jul_s1``; folders named ``<month>_s<seed>``) and, for each, runs the same month and
seed in measurement mode with each moon's RA/Dec noise set to what the image stage achieved
on it in that run (``noise_arcsec_phobos`` / ``noise_arcsec_deimos``: the median 1-sigma the
stage reported, whose chi-square against the frames' truth is printed beside it); that
measurement-mode run again with only the records of a moon at the epochs where the image stage
measured it ("where imaged": the same noise, the camera's availability: a moon behind Mars, on
its disk or in its halo gives no record, while the papers' set-up measures both moons every
minute); and ``--twin-draws`` measurement-level twins of the image run itself (:mod:`twins`:
its records and covariances, values drawn from them; the mean over the draws). Prints per run and per month
(mean and spread over seeds): the image stage's noise, each filter's position RMS over the
last 15 days from pixels, from measurements, where imaged and from the twins and the ratios,
the share of frames in which the stage measured each moon, and the NEES
(mean, and the share of epochs inside the 95 % chi-square(6) band), plus the wall time of the
image-mode simulation stage. Per month and filter it also prints the Monte Carlo consistency
test (:func:`opnav.consistency.ensemble_nees`): the NEES averaged over the month's runs at each
epoch they share, against the 95 % band of the mean of that many chi-square(6) values, and the
share of the last 15 days' epochs inside it. One run's NEES is not a test on its own: its epochs share one estimation error, so a run
whose error happens to lie 3 sigma out along the weak axis is out of the band at every epoch.
So last, per run and for each of its twins, the error along that axis (the line of sight from
Mars) in units of the filter's own sigma along it, averaged over the last 15 days, and per month
and over all runs their RMS with a chi-square test: this is the consistency test that many runs
of one month can make and the ensemble NEES of five runs cannot.

Usage::

    .venv/bin/python benchmarks/s1_from_pixels.py --pixels out/pixels
"""

from __future__ import annotations

import argparse
import json
import logging
import re
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from opnav.ccsds import read_oem
from opnav.consistency import ensemble_nees
from opnav.records import atomic_write_text, file_sha256
from opnav.studies.common import NEES_STATES
from opnav.studies.runner import RunOptions, filter_stage, load_simulation, run_study
from opnav.studies.settings import load_run_file
from twins import measured_where_imaged, twin_means

ROOT = Path(__file__).resolve().parent.parent
RUN_FILE = ROOT / "samples" / "s1_jul_both_0.1.toml"
MOONS = ("phobos", "deimos")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pixels", default="out/pixels", help="folder of the image-mode runs (<month>_s<seed>)")
    parser.add_argument("--filters", default="ekf,ukf")
    parser.add_argument("--twin-draws", type=int, default=5, help="measurement-level twins a run (0: none)")
    parser.add_argument("--no-twin-range", action="store_true",
                        help="skip the twins' range errors (each reads a 30-day OEM with covariances: 1-2 min)")
    args = parser.parse_args(argv)
    logging.getLogger("opnav").setLevel(logging.ERROR)
    filters = tuple(args.filters.split(","))
    rows = []
    for folder in sorted(Path(args.pixels).iterdir()):
        match = re.fullmatch(r"(may|jun|jul|aug)_s(\d+)", folder.name)
        if not match or not (folder / "summary.json").exists():
            continue
        month, seed = match.group(1), int(match.group(2))
        image = json.loads((folder / "summary.json").read_text())
        errors = image["facts"]["measurement_errors"]
        noise = {moon: float(np.mean(errors[moon]["median_sigma_arcsec"])) for moon in MOONS}
        overrides = {"month": month, "seed": str(seed), **{f"noise_arcsec_{m}": f"{noise[m]:.4f}" for m in MOONS}}
        run = load_run_file(RUN_FILE, overrides)
        measured_out = Path(args.pixels) / f"measurements_{folder.name}"
        measured = run_study(run, RunOptions(out=measured_out, filters=filters, progress=False))
        twins = matched = None
        image_run = load_run_file(RUN_FILE, {key: str(value) for key, value in image["run"]["settings"].items()}
                                  | {"seed": str(seed)})
        saved = load_simulation(image_run, folder, mode="images")
        if saved is None:
            print(f"{folder}: its simulation does not match {RUN_FILE.name} at this version; no twins, "
                  "no measurement-mode run on its frames")
        else:
            measured_sim, measured_key, _ = load_simulation(run, measured_out, mode="measurements")
            matched_sim, share = measured_where_imaged(measured_sim, saved[0])
            matched = {"share": share} | {
                name: filter_stage(name, matched_sim, f"{measured_key}:where-imaged:{saved[1]}",
                                   Path(args.pixels) / f"matched_{folder.name}", False, lambda message: None)
                for name in filters}
            if args.twin_draws:
                twins = twin_means(saved[0], saved[1], seed, args.twin_draws, filters,
                                   Path(args.pixels) / f"twins_{folder.name}")
        rows.append((month, seed, noise, errors, image, measured, matched, twins, folder))
    if not rows:
        print(f"no image-mode runs (<month>_s<seed>/summary.json) in {args.pixels}")
        return 1
    print(f"(twins: {args.twin_draws} a run, their mean; 'where imaged': the measurement-mode run with only the "
          "records of a moon at the epochs the image stage measured it)\n")
    print("| month | seed | image noise Phobos / Deimos (\", median 1-sigma; chi2/2) | frames imaged Phobos / Deimos | "
          "filter | RMS from pixels (km) | RMS from measurements (km) | ratio | "
          "RMS from measurements where imaged (km) | ratio | RMS from twins (km) | ratio | NEES mean (in 95 % band) from pixels | simulate stage (min) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    ratios: dict = {}
    nan = {"position_rms_km": float("nan")}
    for month, seed, noise, errors, image, measured, matched, twins, folder in rows:
        window_start = image["window_start_tdb_s"]
        moons = " / ".join(f"{noise[m]:.4f} ({errors[m]['chi2_mean'] / 2:.2f})" for m in MOONS)
        imaged = " / ".join(f"{matched['share'][m]:.0%}" for m in MOONS) if matched else "-"
        for name in filters:
            pix, mea = image["filters"][name], measured["filters"][name]
            where = (matched or {}).get(name, nan)["position_rms_km"]
            twin = (twins or {}).get(name, nan)["position_rms_km"]
            sigmas = [own_sigma_km(base / "filters" / f"{name}.npz", window_start)
                      for base in (folder, Path(args.pixels) / f"measurements_{folder.name}",
                                   Path(args.pixels) / f"matched_{folder.name}")]
            ratios.setdefault((month, name), []).append((pix["position_rms_km"], mea["position_rms_km"], where, twin,
                                                         pix["nees_fraction_in_95"], *sigmas))
            print(f"| {month} | {seed} | {moons} | {imaged} | {name} | {pix['position_rms_km']:.3f} | "
                  f"{mea['position_rms_km']:.3f} | {pix['position_rms_km'] / mea['position_rms_km']:.2f} | "
                  f"{where:.3f} | {pix['position_rms_km'] / where:.2f} | {twin:.3f} | "
                  f"{pix['position_rms_km'] / twin:.2f} | {pix['nees_mean']:.2f} ({pix['nees_fraction_in_95']:.1%}) | "
                  f"{image['stages_wall_s'].get('simulate', float('nan')) / 60:.1f} |")
    print("\n| month | filter | seeds | RMS from pixels mean +- sd (km) | RMS from measurements mean +- sd (km) | "
          "ratio of means | RMS from measurements where imaged mean +- sd (km) | ratio of means | "
          "RMS from twins mean +- sd (km) | ratio of means | NEES in 95 % band (mean share) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    sigma_lines = []

    def spread(column):
        return f"{column.mean():.3f} +- {column.std(ddof=1) if len(column) > 1 else 0.0:.3f}"

    for (month, name), values in ratios.items():
        values = np.array(values)
        print(f"| {month} | {name} | {len(values)} | {spread(values[:, 0])} | {spread(values[:, 1])} | "
              f"{values[:, 0].mean() / values[:, 1].mean():.2f} | {spread(values[:, 2])} | "
              f"{values[:, 0].mean() / values[:, 2].mean():.2f} | {spread(values[:, 3])} | "
              f"{values[:, 0].mean() / values[:, 3].mean():.2f} | {values[:, 4].mean():.1%} |")
        sigma_lines.append(f"| {month} | {name} | {len(values)} | {spread(values[:, 5])} | {spread(values[:, 6])} | "
                           f"{values[:, 5].mean() / values[:, 6].mean():.2f} | {spread(values[:, 7])} | "
                           f"{values[:, 5].mean() / values[:, 7].mean():.2f} |")
    # A run's RMS over the window is close to one draw of a quantity with one or two degrees of
    # freedom (twins.py), so five seeds give a ratio of means good to ~30 %; the filters' own
    # sigma depends on the draws only through the linearisation: its ratio is the information
    # the image stage's records carry
    # against the measurement-level ones, and the range-error test below says whether the errors
    # from pixels match that sigma.
    print("\n| month | filter | seeds | own 1-sigma from pixels (km) | from measurements (km) | ratio | "
          "from measurements where imaged (km) | ratio |")
    print("|---|---|---|---|---|---|---|---|")
    print("\n".join(sigma_lines))
    print("\n| month | filter | runs | epochs shared (last 15 days) | mean over runs of NEES: its mean | "
          "95 % band of that mean | share of epochs inside |")
    print("|---|---|---|---|---|---|---|")
    for month in dict.fromkeys(row[0] for row in rows):
        folders = [row[-1] for row in rows if row[0] == month]
        window_start = json.loads((folders[0] / "summary.json").read_text())["window_start_tdb_s"]
        for name in filters:
            saved = [np.load(folder / "filters" / f"{name}.npz") for folder in folders]
            test = ensemble_nees([(run["t_tdb_s"], run["nees"]) for run in saved], NEES_STATES, window_start, 0.95)
            low, high = test.band
            print(f"| {month} | {name} | {test.runs} | {test.epochs} | {test.mean:.2f} | "
                  f"[{low:.2f}, {high:.2f}] | {test.share_inside:.1%} |")
    print("\n| month | seed | filter | range error from pixels (filter sigma) | its twins' range errors |")
    print("|---|---|---|---|---|")
    pixel_z: dict = {}
    twin_z: dict = {}
    for month, seed, *_, folder in rows:
        window_start = json.loads((folder / "summary.json").read_text())["window_start_tdb_s"]
        for name in filters:
            z = range_error_sigmas(folder / "filters" / f"{name}.oem", folder / "truth.npz", window_start)
            pixel_z.setdefault(name, {}).setdefault(month, []).append(z)
            twin_oems = [] if args.no_twin_range else sorted(
                (Path(args.pixels) / f"twins_{folder.name}").glob(f"twin*/filters/{name}.oem"))
            twins_z = [range_error_sigmas(oem, folder / "truth.npz", window_start) for oem in twin_oems]
            twin_z.setdefault(name, []).extend(twins_z)
            print(f"| {month} | {seed} | {name} | {z:+.2f} | {' '.join(f'{v:+.2f}' for v in twins_z)} |")
    print("\n| runs | count | RMS (sigma) | mean (sigma) | chi-square | p |")
    print("|---|---|---|---|---|---|")
    for name in filters:
        for month, values in pixel_z[name].items():
            print(consistency_line(f"{name} {month} from pixels", values))
        print(consistency_line(f"{name} all from pixels", [v for values in pixel_z[name].values() for v in values]))
        if twin_z[name]:
            print(consistency_line(f"{name} all twins", twin_z[name]))
    return 0


def own_sigma_km(filter_npz: Path, window_start_tdb_s: float) -> float:
    """A filter run's own position 1-sigma over the judged window: the root of the mean trace of
    its position covariance (km) over the epochs from ``window_start_tdb_s`` (TDB s past J2000),
    what its position RMS there is for a consistent filter in expectation.

    ``filter_npz``: a run's ``filters/<name>.npz`` (``t_tdb_s``; ``sigma`` (N, 6): km, km/s)."""
    saved = np.load(filter_npz)
    judged = saved["t_tdb_s"] >= window_start_tdb_s
    return float(np.sqrt(np.mean(np.sum(saved["sigma"][judged, :3] ** 2, axis=1))))


def range_error_sigmas(estimates_oem: Path, truth_npz: Path, window_start_tdb_s: float) -> float:
    """:func:`range_error_of_oem`, kept beside the OEM (``<name>.oem.range_z.json``) under the SHA-256 of
    the OEM and truth files: parsing a 30-day OEM with covariances takes minutes, and a rerun of this
    benchmark over the same runs reads every one again."""
    cache = estimates_oem.with_name(estimates_oem.name + ".range_z.json")
    identity = {"oem": file_sha256(estimates_oem), "truth": file_sha256(truth_npz), "window_start_tdb_s": window_start_tdb_s}
    try:
        saved = json.loads(cache.read_text())
        if saved["identity"] == identity:
            return float(saved["z"])
    except (OSError, ValueError, KeyError, TypeError):
        pass
    z = range_error_of_oem(estimates_oem, truth_npz, window_start_tdb_s)
    atomic_write_text(cache, json.dumps({"identity": identity, "z": z}))
    return z


def range_error_of_oem(estimates_oem: Path, truth_npz: Path, window_start_tdb_s: float) -> float:
    """A run's position error along the line of sight from the origin (S1: Mars' centre) to the
    true probe, in units of the filter's own 1-sigma along it, averaged over the judged window
    (epochs from ``window_start_tdb_s``, TDB s past J2000).

    ``estimates_oem``: the run's ``filters/<name>.oem`` (ICRF km, with covariances);
    ``truth_npz``: its ``truth.npz`` (``epochs`` TDB s, ``truth`` (N, 6) km, km/s, same origin).
    Over the last 15 days an S1 error lies along this line (across it under 0.1 km), so one
    number per run says how far out it sits; for a consistent filter it is at most a unit
    normal draw (an average over correlated epochs of unit normals).
    """
    estimates = read_oem(estimates_oem)
    truth = np.load(truth_npz)
    t_truth = np.round(truth["epochs"]).astype(np.int64)
    t_estimate = np.round(estimates.t_tdb_s).astype(np.int64)
    judged = t_estimate >= window_start_tdb_s
    index = np.searchsorted(t_truth, t_estimate[judged])
    if np.any(index >= t_truth.size) or np.any(t_truth[np.minimum(index, t_truth.size - 1)] != t_estimate[judged]):
        raise ValueError(f"{estimates_oem}: epochs not in {truth_npz}")
    position = truth["truth"][index, :3]
    line_of_sight = position / np.linalg.norm(position, axis=1, keepdims=True)
    along = np.einsum("ni,ni->n", line_of_sight, estimates.states[judged, :3] - position)
    sigma = np.sqrt(np.einsum("ni,nij,nj->n", line_of_sight, estimates.covariances[judged, :3, :3], line_of_sight))
    return float(np.mean(along / sigma))


def consistency_line(label: str, values: list[float]) -> str:
    """RMS of per-run range errors in sigma and the chi-square test of ``sum z**2`` on ``len`` dof
    (conservative: each value's variance is at most 1 for a consistent filter)."""
    z = np.asarray(values)
    statistic = float(np.sum(z**2))
    return (f"| {label} | {z.size} | {np.sqrt(np.mean(z**2)):.2f} | {z.mean():+.2f} | {statistic:.1f} | "
            f"{chi2.sf(statistic, z.size):.3f} |")


if __name__ == "__main__":
    raise SystemExit(main())
