"""Propagation speed: S1 30-day arc with STM (one call, and as a filter calls it), batch cost, geopotential rate.

Run: ``.venv/bin/python benchmarks/propagate.py [--fraction 0.05]``. Prints wall times; the
1-minute-step figure is measured on ``--fraction`` of the 43 200 calls and extrapolated
(say so when quoting it).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from opnav.constants import EARTH_GM_JGM3_KM3_S2, EARTH_RADIUS_JGM3_KM
from opnav.dynamics import S3_GEOPOTENTIAL, Geopotential, cruise_model, geo_model, propagate
from opnav.epochs import parse_epoch

T_S1 = parse_epoch("2013-12-12T12:00:00", "tt")
X_S1 = np.array([24306991.2893, 132523850.2219, 58427884.5328, -32.455391, 3.658828, 3.362343])
T_MAY = parse_epoch("2014-05-01T00:00:00", "tt")
ARC_S = 30 * 86_400.0


def _timed(function, repeat: int = 1) -> float:
    best = np.inf
    for _ in range(repeat):
        start = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - start)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--fraction", type=float, default=0.05,
                        help="fraction of the 43 200 one-minute calls to time (default 0.05)")
    args = parser.parse_args()

    model = cruise_model()
    x_may = propagate(model, T_S1, X_S1, T_MAY).states[-1]
    propagate(model, T_MAY, x_may, T_MAY + ARC_S)  # warm the ephemeris cache for the arc

    one_call = _timed(lambda: propagate(model, T_MAY, x_may, T_MAY + ARC_S, stm=True), repeat=3)
    print(f"S1 30-day arc, cruise model, STM, one call:        {one_call:8.3f} s")

    calls = max(1, int(round(args.fraction * 43_200)))
    x = x_may
    start = time.perf_counter()
    for i in range(calls):
        t0 = T_MAY + 60.0 * i
        x = propagate(model, t0, x, t0 + 60.0, stm=True).states[-1]
    elapsed = time.perf_counter() - start
    print(f"S1 1-minute calls with STM: {calls} calls in {elapsed:.2f} s = {1e3 * elapsed / calls:.2f} ms/call; "
          f"43 200 calls (30 days) extrapolated: {elapsed / calls * 43_200:.0f} s")

    for label, span in (("30-day arc", ARC_S), ("1-minute step", 60.0)):
        single = _timed(lambda: propagate(model, T_MAY, x_may, T_MAY + span, stm=True), repeat=3)
        batch = np.tile(x_may, (13, 1)) + np.linspace(0, 1, 13)[:, None] * [1e3, -1e3, 5e2, 1e-3, -1e-3, 5e-4]
        thirteen = _timed(lambda: propagate(model, T_MAY, batch, T_MAY + span, stm=True), repeat=3)
        print(f"13 states vs 1, {label:14s} with STM: {thirteen:.4f} s vs {single:.4f} s = {thirteen / single:.2f}x")

    geo = geo_model()
    t_s3 = parse_epoch("2001-01-01T00:00:00", "utc")
    x_geo = np.array([-6936.0, -41590.0, 0.0, 3.033, -0.506, 0.0])
    day = _timed(lambda: propagate(geo, t_s3, x_geo, t_s3 + 86_400.0, stm=True))
    print(f"S3 one day, geo model, STM, one call:              {day:8.3f} s")
    steps = 360
    start = time.perf_counter()
    x = x_geo
    for i in range(steps):
        t0 = t_s3 + 10.0 * i
        x = propagate(geo, t0, x, t0 + 10.0, stm=True).states[-1]
    elapsed = time.perf_counter() - start
    print(f"S3 10-second calls with STM: {1e3 * elapsed / steps:.2f} ms/call; 8640 calls (1 day) extrapolated: "
          f"{elapsed / steps * 8640:.0f} s")

    term = Geopotential(EARTH_GM_JGM3_KM3_S2, EARTH_RADIUS_JGM3_KM, **S3_GEOPOTENTIAL)
    rng = np.random.default_rng(0)
    for k in (1, 1000):
        r = rng.normal(size=(k, 3)) * 20_000.0
        v = np.zeros_like(r)
        n_calls = 2000 if k == 1 else 50
        acc = _timed(lambda: [term.acceleration(t_s3, r, v) for _ in range(n_calls)])
        par = _timed(lambda: [term.partials(t_s3, r, v) for _ in range(n_calls)])
        print(f"geopotential, batch of {k:4d}: acceleration {n_calls * k / acc:12,.0f} states/s, "
              f"partials {n_calls * k / par:12,.0f} states/s")


if __name__ == "__main__":
    main()
