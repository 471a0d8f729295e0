"""The S1 run as a user runs it: ``opnav run samples/s1_jul_both_0.1.toml --filters ekf,ukf``, every stage timed.

The command runs in its own process into a fresh folder (``--mode measurements``: simulate,
both filters, measurement CSV/JSON/TDM, estimate npz/OEM/JSON, report). Printed: each stage of
``summary.json`` ``stages_wall_s`` (setup = interpreter start, imports and the run file; the
runner's stages after it), their sum, the command's wall time measured from outside (process
start to exit) and what the stages leave out (when every stage is timed: the interpreter's exit),
the time not spent in a filter stage, the load average around the run (the machine may be
shared), and each filter's cost per record: its stage (the filter with its figures) and the
filter loop alone (the filter's ``wall_s``).

Usage::

    .venv/bin/python benchmarks/run_s1.py                  # the 30-day sample, 86,400 records
    .venv/bin/python benchmarks/run_s1.py --days 5 --keep out/bench_s1
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def load() -> str:
    """The 1-, 5- and 15-minute load averages, as ``uptime`` prints them."""
    return ", ".join(f"{value:.2f}" for value in os.getloadavg())


def run(out: Path, args: argparse.Namespace) -> tuple[float, dict]:
    """``opnav run`` in a new process into ``out``: its wall time (s) and its summary."""
    command = [sys.executable, "-m", "opnav.cli", "run", str(args.runfile), "--mode", "measurements",
               "--filters", args.filters, "--out", str(out), "--no-progress"]
    if args.days is not None:
        command += ["--set", f"duration_days={args.days:g}"]
    tic = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, cwd=ROOT)
    wall = time.perf_counter() - tic
    return wall, json.loads((out / "summary.json").read_text())


def report(wall: float, summary: dict) -> list[str]:
    """The lines printed for one run."""
    walls = summary["stages_wall_s"]
    total = sum(walls.values())
    width = max(len(name) for name in walls)
    lines = [f"  {name:<{width}} {value:7.2f} s" for name, value in walls.items()]
    lines += [f"  {'sum of stages':<{width}} {total:7.2f} s",
              f"  {'command wall':<{width}} {wall:7.2f} s (stages cover {100 * total / wall:.1f} %; "
              f"{wall - total:.2f} s outside them)"]
    records = summary["measurements"]["records"]
    outside = wall - sum(value for name, value in walls.items() if name.startswith("filter "))
    lines.append(f"  {'not filtering':<{width}} {outside:7.2f} s (the command wall less the filter stages)")
    for name, figures in summary["filters"].items():
        stage = walls.get(f"filter {name}", float("nan"))
        lines.append(f"  {name}: {1e6 * stage / records:.1f} us/record for its stage, {1e6 * figures['wall_s'] / records:.1f} "
                     f"us/record for the filter loop ({records} records)")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runfile", default=ROOT / "samples" / "s1_jul_both_0.1.toml")
    parser.add_argument("--filters", default="ekf,ukf")
    parser.add_argument("--days", type=float, default=None, help="arc length (default: the run file's, 30 days)")
    parser.add_argument("--keep", type=Path, default=None,
                        help="write into this folder instead of a temporary one (the stages a finished run left "
                             "there are reused, and named so)")
    args = parser.parse_args(argv)
    arc = "the run file's arc" if args.days is None else f"{args.days:g}-day arc"
    print(f"opnav run {Path(args.runfile).name} --mode measurements --filters {args.filters} ({arc}); "
          f"{os.cpu_count()} cores, load average {load()}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        out = args.keep if args.keep is not None else Path(tmp) / "s1"
        wall, summary = run(out, args)
    print("\n".join(report(wall, summary)))
    print(f"load average after: {load()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
