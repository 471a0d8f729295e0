"""``opnav propagate``: propagate a state with a force model and print it at given dates.

Example::

    opnav propagate --epoch 2013-12-12T12:00:00 --scale tt \\
        --state 24306991.2893 132523850.2219 58427884.5328 -32.455391 3.658828 3.362343 \\
        --frame icrf --center sun --model cruise --at 2014-05-01 2014-06-01 --relative-to mars --json

Input and output vectors are in ``--frame`` (ICRF or the J2000 ecliptic), km and km/s;
output dates are written in ``--scale``.
"""

from __future__ import annotations

import argparse
import json

from ..errors import InputError

NAME = "propagate"
HELP = "propagate a state (km, km/s) with a force model and print it at given dates"
_FRAMES = ("icrf", "ecliptic")
TWO_BODY = "two-body"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..dynamics import MODELS

    parser.add_argument("--epoch", required=True, help="epoch of --state, ISO date in --scale")
    parser.add_argument("--scale", default="utc", help="time scale of all dates: utc, tt, tdb, tai (default utc)")
    parser.add_argument("--state", required=True, nargs=6, metavar=("X", "Y", "Z", "VX", "VY", "VZ"),
                        help="position (km) and velocity (km/s) relative to --center")
    parser.add_argument("--frame", default="icrf", help="frame of --state and of the output: icrf or ecliptic "
                        "(J2000 ecliptic); default icrf")
    parser.add_argument("--center", default="sun", help="origin of --state (any ephemeris body; default sun)")
    parser.add_argument("--model", default="cruise",
                        help=f"force model: {', '.join([*MODELS, TWO_BODY])} (two-body uses --center's GM)")
    parser.add_argument("--at", required=True, nargs="+", metavar="DATE", help="output dates in --scale")
    parser.add_argument("--relative-to", default=None, help="origin of the output (default: --center)")
    parser.add_argument("--json", action="store_true", help="print a JSON list instead of a table")


def _parse_state(values: list[str]):
    """The six numbers of ``--state`` as an array (km, km/s)."""
    import numpy as np

    try:
        state = np.array([float(v) for v in values])
    except ValueError:
        raise InputError(f"--state needs six numbers (km, km/s), got {' '.join(values)!r}") from None
    if not np.all(np.isfinite(state)):
        raise InputError(f"--state contains NaN or infinity: {' '.join(values)}")
    return state


def _parse_dates(texts: list[str], scale: str, option: str):
    """Dates of ``option`` in time scale ``scale`` as TDB s past J2000 (an array)."""
    import numpy as np

    from ..epochs import parse_epoch

    try:
        return np.atleast_1d(parse_epoch(texts, scale))
    except InputError as exc:
        # astropy's parse failure lists every format it tried, one per line; the first line says it.
        raise InputError(f"{option}: {str(exc).splitlines()[0].rstrip(':')}") from None


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..dynamics import get_model, states_at, two_body_model
    from ..ephemeris import Ephemeris
    from ..epochs import format_epoch
    from ..frames import ecliptic_to_icrf, icrf_to_ecliptic

    frame = args.frame.strip().lower()
    if frame not in _FRAMES:
        raise InputError(f"unknown --frame {args.frame!r}; expected icrf or ecliptic")
    center = Ephemeris.check_body(args.center)
    relative_to = Ephemeris.check_body(args.relative_to) if args.relative_to else center
    model_name = args.model.strip().lower()
    model = two_body_model(center) if model_name == TWO_BODY else get_model(model_name)
    state = _parse_state(args.state)
    t0 = float(_parse_dates([args.epoch], args.scale, "--epoch")[0])
    epochs = _parse_dates(list(args.at), args.scale, "--at")

    if frame == "ecliptic":
        state = np.r_[ecliptic_to_icrf(state[:3]), ecliptic_to_icrf(state[3:])]
    out = states_at(model, t0, state, epochs, center=center, output_center=relative_to)
    if frame == "ecliptic":
        out = np.concatenate([icrf_to_ecliptic(out[:, :3]), icrf_to_ecliptic(out[:, 3:])], axis=1)

    dates = format_epoch(epochs, args.scale)
    rows = [{"epoch": date, "r_km": [float(c) for c in x[:3]], "v_km_s": [float(c) for c in x[3:]],
             "range_km": float(np.linalg.norm(x[:3]))} for date, x in zip(dates, out)]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    print(f"model {model.name}, {frame.upper()} relative to {relative_to}, dates in {args.scale.upper()}")
    print(f"{'epoch':<24} {'x_km':>16} {'y_km':>16} {'z_km':>16} {'vx_km_s':>11} {'vy_km_s':>11} "
          f"{'vz_km_s':>11} {'range_km':>16}")
    for row in rows:
        r, v = row["r_km"], row["v_km_s"]
        print(f"{row['epoch']:<24} {r[0]:16.3f} {r[1]:16.3f} {r[2]:16.3f} {v[0]:11.6f} {v[1]:11.6f} "
              f"{v[2]:11.6f} {row['range_km']:16.3f}")
    return 0
