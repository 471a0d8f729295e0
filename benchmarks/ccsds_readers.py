"""Every OEM and TDM opnav writes, read by two independent CCSDS readers, beside opnav's own numbers.

The readers: ``ccsds-ndm`` (Python, xsdata models; opnav's dependency, in this process) and
``ccsds-ndm-py`` (Rust, PyPI ``ccsds-ndm-py``). The second installs a package also named
``ccsds_ndm``, so it lives in its own virtual environment and runs in a subprocess::

    python3 -m venv /tmp/ndmpy && /tmp/ndmpy/bin/pip install ccsds-ndm-py
    .venv/bin/python benchmarks/ccsds_readers.py --ndmpy /tmp/ndmpy/bin/python

Without ``--ndmpy`` (or when that interpreter cannot import it) its column says so and the rest runs.

The files: the runs ``opnav run`` writes into ``--out`` (reused when their folder holds a finished
summary): the demo (``opnav/data/demo_run.toml``, S1 from pixels: radec and radec_pair records),
S1 (1 day, EKF and UKF, measurement mode), S3 (1 h; starlight records, so no TDM), S2 and S4 (48 h)
(their OEMs, when the study writes them); ``opnav navigate`` of the demo's TDM (``estimates.oem``,
``measurements.tdm``); and the NDM/XML forms of the demo's TDM and EKF OEM (``opnav.ccsds`` writes
XML for a ``.xml`` name).

Printed per file: what opnav reads (records or states), then for each reader whether it parsed the
file, whether its epochs are opnav's (as text), the largest difference from opnav's numbers (OEM:
position km, velocity km/s, covariance relative to its diagonal scale; TDM: angles in arcsec) and
the names it sees (OEM ``OBJECT_NAME``/``INTERPOLATION``; TDM ``PARTICIPANT_1``). A TDM's
directions are also compared with the run's ``measurements.csv`` (the records it was written from).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
ARCSEC_PER_DEG = 3600.0

#: (folder, run file, --set values, --filters) of each run; S2 and S4 take no --filters.
RUNS = {
    "demo": ("opnav/data/demo_run.toml", [], None),
    "s1": ("samples/s1_jul_both_0.1.toml", ["duration_days=1"], "ekf,ukf"),
    "s3": ("samples/s3_geo.toml", ["duration_hours=1"], "ekf"),
    "s2": ("samples/s2_capture.toml", [], None),
    "s4": ("samples/s4_approach.toml", ["duration_hours=48"], None),
}

#: What ccsds-ndm-py reports of a file, as JSON (run by its own interpreter; numbers as Python floats).
NDMPY_SCRIPT = r"""
import json, sys
import ccsds_ndm

def oem(m):
    seg = m.segments[0]
    meta, data = seg.metadata, seg.data
    return {"kind": "OEM", "segments": len(m.segments), "object_name": meta.object_name,
            "object_id": meta.object_id, "interpolation": meta.interpolation,
            "interpolation_degree": meta.interpolation_degree,
            "epochs": [e for s in m.segments for e in s.data.state_vector_epochs],
            "states": [row for s in m.segments for row in s.data.state_vector_numpy.tolist()],
            "cov_epochs": [e for s in m.segments for e in s.data.covariance_matrix_epochs],
            "covariances": [c for s in m.segments for c in s.data.covariance_matrix_numpy.tolist()]}

def tdm(m):
    return {"kind": "TDM", "segments": [
        {"participant_1": s.metadata.participant_1, "participant_2": s.metadata.participant_2,
         "observations": [[o.epoch, o.keyword, o.value] for o in s.data.observations]}
        for s in m.body.segments]}

out = {}
for path in sys.argv[1:]:
    try:
        m = ccsds_ndm.from_file(path)
        out[path] = oem(m) if type(m).__name__ == "Oem" else tdm(m)
    except Exception as exc:
        out[path] = {"error": f"{type(exc).__name__}: {' '.join(str(exc).split())[:200]}"}
print(json.dumps(out))
"""


# ---- making the files


def make_runs(out: Path, names: list[str]) -> dict[str, Path]:
    """Each run's folder, run now unless it holds a summary already; a failed run is named and skipped."""
    folders = {}
    for name in names:
        runfile, settings, filters = RUNS[name]
        folder = out / name
        if not (folder / "summary.json").is_file():
            command = [sys.executable, "-m", "opnav.cli", "run", str(ROOT / runfile), "--out", str(folder),
                       "--no-progress"]
            for value in settings:
                command += ["--set", value]
            if filters:
                command += ["--filters", filters]
            done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
            if done.returncode != 0:
                last = (done.stderr.strip().splitlines() or ["?"])[-1]
                print(f"{name}: opnav run exited with {done.returncode} ({last}); its files so far are read")
        folders[name] = folder
    return folders


def navigate_demo(demo: Path, out: Path) -> Path | None:
    """``opnav navigate`` of the demo run's TDM (its sidecar beside it) into ``out``."""
    if not (demo / "measurements.tdm").is_file():
        return None
    command = [sys.executable, "-m", "opnav.cli", "navigate", str(demo / "measurements.tdm"), "--scenario",
               str(ROOT / "opnav/data/demo.toml"), "--out", str(out), "--no-progress"]
    subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    return out if (out / "estimates.oem").is_file() else None


def xml_forms(demo: Path, out: Path) -> list[Path]:
    """The demo's TDM (with its records and sidecar) and EKF OEM written again as NDM/XML."""
    from opnav.ccsds import read_oem, read_tdm, write_oem, write_tdm

    made = []
    out.mkdir(parents=True, exist_ok=True)
    if (demo / "measurements.tdm").is_file():
        write_tdm(out / "measurements.xml", read_tdm(demo / "measurements.tdm"), participant="demo")
        made.append(out / "measurements.xml")
    if (demo / "filters" / "ekf.oem").is_file():
        oem = read_oem(demo / "filters" / "ekf.oem")
        write_oem(out / "ekf.xml", oem.t_tdb_s, oem.states, oem.covariances, object_name=oem.object_name,
                  object_id=oem.object_id, center=oem.center)
        made.append(out / "ekf.xml")
    return made


# ---- reading them


def ccsds_ndm_view(path: Path) -> dict:
    """What ``ccsds-ndm`` reports of ``path``, in the layout of :data:`NDMPY_SCRIPT`."""
    from ccsds_ndm.ndm_io import NdmIo

    from opnav.ccsds.oem import _COV_KEYS  # the 21 lower-triangle entries of an OEM covariance block

    try:
        message = NdmIo().from_path(path)
    except Exception as exc:  # noqa: BLE001 - any failure is the reader's answer
        return {"error": f"{type(exc).__name__}: {' '.join(str(exc).split())[:200]}"}
    segments = message.body.segment
    if type(message).__name__ == "Oem":
        meta = segments[0].metadata
        vectors = [v for s in segments for v in s.data.state_vector]
        blocks = [b for s in segments for b in (s.data.covariance_matrix or [])]
        covariances = []
        for block in blocks:
            cov = np.empty((6, 6))
            for i, j, name in _COV_KEYS:
                cov[i, j] = cov[j, i] = getattr(block, name).value
            covariances.append(cov.tolist())
        return {"kind": "OEM", "segments": len(segments), "object_name": meta.object_name,
                "object_id": meta.object_id, "interpolation": meta.interpolation,
                "interpolation_degree": meta.interpolation_degree,
                "epochs": [v.epoch for v in vectors],
                "states": [[getattr(v, k).value for k in ("x", "y", "z", "x_dot", "y_dot", "z_dot")] for v in vectors],
                "cov_epochs": [b.epoch for b in blocks], "covariances": covariances}
    out = []
    for segment in segments:
        observations = []
        for obs in segment.data.observation:
            for key in ("angle_1", "angle_2"):
                item = getattr(obs, key)
                if item is not None:
                    observations.append([obs.epoch, key.upper(), item.value])
        out.append({"participant_1": segment.metadata.participant_1,
                    "participant_2": segment.metadata.participant_2, "observations": observations})
    return {"kind": "TDM", "segments": out}


def ndmpy_views(python: str | None, paths: list[Path]) -> dict[str, dict] | str:
    """What ``ccsds-ndm-py`` reports of each file, or why it could not be asked."""
    if python is None:
        return "skipped: no --ndmpy PATH (the python of a venv with ccsds-ndm-py)"
    if not Path(python).is_file():
        return f"skipped: --ndmpy {python} does not exist"
    done = subprocess.run([python, "-c", NDMPY_SCRIPT, *map(str, paths)], capture_output=True, text=True)
    if done.returncode != 0:
        return f"skipped: {python} could not run ccsds-ndm-py ({(done.stderr.strip().splitlines() or ['?'])[-1]})"
    return json.loads(done.stdout)


# ---- comparing


def oem_line(path: Path, view: dict) -> str:
    """How a reader's OEM numbers differ from opnav's."""
    from opnav.ccsds import read_oem
    from opnav.epochs import format_epoch

    if "error" in view:
        return f"FAILED ({view['error']})"
    oem = read_oem(path)
    epochs = [str(e) for e in format_epoch(oem.t_tdb_s, "tdb", precision=6)]
    states = np.array(view["states"])
    same_epochs = view["epochs"] == epochs
    d_pos = np.max(np.abs(states[:, :3] - oem.states[:, :3]))
    d_vel = np.max(np.abs(states[:, 3:] - oem.states[:, 3:]))
    text = (f"{len(view['epochs'])} states, epochs {'=' if same_epochs else '!='} opnav's, "
            f"max |d| {d_pos:.3g} km {d_vel:.3g} km/s")
    if oem.covariances is not None:
        cov = np.array(view["covariances"])
        scale = np.sqrt(np.einsum("nii->ni", oem.covariances))
        relative = np.abs(cov - oem.covariances) / (scale[:, :, None] * scale[:, None, :])
        text += f", covariance {len(cov)} blocks max |d|/scale {np.max(relative):.3g}"
    return (text + f"; OBJECT_NAME {view['object_name']}, OBJECT_ID {view['object_id']}, "
            f"INTERPOLATION {view['interpolation']} {view['interpolation_degree']}")


def tdm_directions(view: dict) -> dict[tuple[str, str], list[tuple[float, float]]]:
    """(TARGET, epoch text) -> [(ra deg, dec deg), ...] of a reader's TDM observations."""
    out: dict = {}
    for segment in view["segments"]:
        pending: dict = {}
        for epoch, key, value in segment["observations"]:
            pending.setdefault(epoch, {}).setdefault(key, []).append(float(value))
        for epoch, angles in pending.items():
            for ra, dec in zip(angles.get("ANGLE_1", []), angles.get("ANGLE_2", [])):
                out.setdefault((segment["participant_2"], epoch), []).append((ra, dec))
    return out


def opnav_directions(records) -> dict[tuple[str, str], list[tuple[float, float]]]:
    """The same map of opnav records (radec and radec_pair), angles in deg."""
    from opnav.epochs import format_epoch
    from opnav.records import pair_targets

    texts = [str(e) for e in format_epoch(np.array([r.t_tdb_s for r in records]), "tdb", precision=6)]
    out: dict = {}
    for rec, epoch in zip(records, texts):
        targets = pair_targets(rec) if rec.kind == "radec_pair" else (rec.target,)
        for k, target in enumerate(targets):
            ra, dec = math.degrees(rec.value[2 * k]) % 360.0, math.degrees(rec.value[2 * k + 1])
            out.setdefault((target.upper(), epoch), []).append((ra, dec))
    return out


def largest_angle_difference(a: dict, b: dict) -> tuple[float, int]:
    """The largest angle difference (arcsec, RA wrapped) over the directions both maps hold, and how
    many directions one holds that the other does not."""
    worst, unmatched = 0.0, 0
    for key in a.keys() | b.keys():
        left, right = a.get(key, []), b.get(key, [])
        unmatched += abs(len(left) - len(right))
        for (ra1, dec1), (ra2, dec2) in zip(left, right):
            d_ra = (ra1 - ra2 + 180.0) % 360.0 - 180.0
            worst = max(worst, abs(d_ra) * ARCSEC_PER_DEG, abs(dec1 - dec2) * ARCSEC_PER_DEG)
    return worst, unmatched


def tdm_line(view: dict, mine: dict) -> str:
    if "error" in view:
        return f"FAILED ({view['error']})"
    theirs = tdm_directions(view)
    worst, unmatched = largest_angle_difference(theirs, mine)
    observers = sorted({s["participant_1"] for s in view["segments"]})
    return (f"{sum(map(len, theirs.values()))} directions in {len(view['segments'])} segments, "
            f"{unmatched} not opnav's, max |d| {worst:.3g} arcsec; PARTICIPANT_1 {', '.join(observers)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "benchmarks" / "ccsds_readers",
                        help="folder of the runs (reused when finished)")
    parser.add_argument("--ndmpy", default=None, help="python of a virtual environment with ccsds-ndm-py")
    parser.add_argument("--runs", default=",".join(RUNS), help=f"runs to make and read (of {', '.join(RUNS)})")
    args = parser.parse_args()

    from opnav.ccsds import read_tdm
    from opnav.records import read_csv

    folders = make_runs(args.out, [name for name in args.runs.split(",") if name])
    files: list[tuple[str, Path, Path | None]] = []  # (label, file, the CSV it was written from)
    for name, folder in folders.items():
        csv_path = folder / "measurements.csv"
        if (folder / "measurements.tdm").is_file():
            files.append((f"{name} run", folder / "measurements.tdm", csv_path))
        elif csv_path.is_file():
            kinds = sorted({r.kind for r in read_csv(csv_path)})
            print(f"{name} run: no TDM ({', '.join(kinds)} records; measurements.csv is their exchange file)")
        files += [(f"{name} run", oem, None) for oem in sorted((folder / "filters").glob("*.oem"))]
    if "demo" in folders:
        navigated = navigate_demo(folders["demo"], args.out / "navigate_demo")
        if navigated is not None:
            files += [("navigate demo", navigated / "estimates.oem", None),
                      ("navigate demo", navigated / "measurements.tdm", folders["demo"] / "measurements.csv")]
        files += [("demo as XML", path, folders["demo"] / "measurements.csv" if path.suffix == ".xml"
                   and "measurements" in path.name else None) for path in xml_forms(folders["demo"], args.out / "xml")]

    ndmpy = ndmpy_views(args.ndmpy, [path for _, path, _ in files])
    if isinstance(ndmpy, str):
        print(f"ccsds-ndm-py: {ndmpy}")
    for label, path, csv_path in files:
        print(f"\n{label}: {path.relative_to(args.out) if path.is_relative_to(args.out) else path}")
        if path.suffix in (".tdm",) or path.name == "measurements.xml":
            records = read_tdm(path)
            mine = opnav_directions(records)
            pairs = sum(r.kind == "radec_pair" for r in records)
            text = f"  opnav        {len(records)} records ({pairs} radec_pair) with the sidecar"
            if csv_path is not None and csv_path.is_file():
                from opnav.ccsds import tdm_ready

                worst, unmatched = largest_angle_difference(opnav_directions(tdm_ready(read_csv(csv_path))), mine)
                text += f"; against measurements.csv: max |d| {worst:.3g} arcsec, {unmatched} unmatched"
            print(text)
            print(f"  ccsds-ndm    {tdm_line(ccsds_ndm_view(path), mine)}")
            print(f"  ccsds-ndm-py {tdm_line(ndmpy[str(path)], mine) if isinstance(ndmpy, dict) else ndmpy}")
        else:
            print(f"  ccsds-ndm    {oem_line(path, ccsds_ndm_view(path))}")
            print(f"  ccsds-ndm-py {oem_line(path, ndmpy[str(path)]) if isinstance(ndmpy, dict) else ndmpy}")


if __name__ == "__main__":
    main()
