"""``opnav solve``: lost-in-space plate solve of an image file (FITS, PNG, TIFF, JPEG).

Example::

    opnav solve frame.fits --fov 11.4 --json

prints the ICRF right ascension and declination of the image centre, the roll (position
angle of the image's "up", i.e. decreasing row, measured from north through east), the
horizontal field of view of the solution, the number of matched stars and the times spent.
Exit status 1 when no solution passes verification, 2 on unusable input.

The pattern index is built from the star catalog (``opnav.catalog.load_catalog``) for the
FOV range the search needs and cached under ``$OPNAV_CACHE`` (default ``~/.cache/opnav``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np

from ..catalog import load_catalog
from ..errors import InputError, NoSolutionError
from ..frames import unit_to_radec
from ..image.io import read_image
from ..image.starid import PlateSolution, solve_image
from ..image.starid_index import load_or_build_index, vmag_limit_for_density

NAME = "solve"
HELP = "lost-in-space plate solve of an image (FITS, PNG, TIFF, JPEG): pointing, roll, field of view"

#: Without --fov, the index covers horizontal fields of view in this range, deg.
DEFAULT_FOV_RANGE_DEG = (10.0, 45.0)
#: The smallest index level is this fraction of the smallest FOV searched: a frame then holds
#: patterns of a denser level too, which makes sparse or cluttered fields solvable.
LEVEL_MARGIN = 0.6


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("image", help="image file: FITS, PNG, TIFF (8/16 bit) or JPEG, mono or RGB")
    parser.add_argument("--fov", type=float, default=None, metavar="DEG",
                        help=f"horizontal field of view guess, deg (default: search {DEFAULT_FOV_RANGE_DEG[0]:g}-"
                        f"{DEFAULT_FOV_RANGE_DEG[1]:g} deg)")
    parser.add_argument("--fov-tolerance", type=float, default=0.1,
                        help="relative uncertainty of --fov (default 0.1 = +-10%%)")
    parser.add_argument("--catalog", default=None, help="star catalog file (default: the packaged catalog)")
    parser.add_argument("--cache-dir", default=None, help="pattern-index cache directory (default $OPNAV_CACHE "
                        "or ~/.cache/opnav)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def _roll_deg(center_icrf: np.ndarray, up_icrf: np.ndarray) -> float:
    """Position angle (deg, north through east) of ``up_icrf`` at ``center_icrf``."""
    pole = np.array([0.0, 0.0, 1.0])
    east = np.cross(pole, center_icrf)
    if np.linalg.norm(east) < 1e-12:  # at a celestial pole, north is undefined: use +x as the reference
        east = np.cross(center_icrf, np.array([1.0, 0.0, 0.0]))
    east /= np.linalg.norm(east)
    north = np.cross(center_icrf, east)
    return math.degrees(math.atan2(up_icrf @ east, up_icrf @ north)) % 360.0


def summary(solution: PlateSolution, total_s: float) -> dict:
    """The JSON record printed by the command."""
    camera = solution.camera
    rotation = solution.identification.R_icrf_cam
    center = rotation.apply(camera.unproject(np.array([(camera.width_px - 1) / 2.0, (camera.height_px - 1) / 2.0])))
    ra, dec = unit_to_radec(center)
    return {
        "ra_deg": round(math.degrees(float(ra)), 6),
        "dec_deg": round(math.degrees(float(dec)), 6),
        "roll_deg": round(_roll_deg(center, rotation.apply([0.0, -1.0, 0.0])), 4),
        "fov_deg": round(math.degrees(camera.fov_x_rad), 5),
        "matched": len(solution.identification.pairs),
        "p_false": float(f"{solution.identification.p_false:.3g}"),
        "solve_ms": round(1e3 * solution.solve_s, 2),
        "extract_ms": round(1e3 * solution.extract_s, 2),
        "total_ms": round(1e3 * total_s, 2),
    }


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    if args.fov is not None and not (0.0 < args.fov < 120.0):
        raise InputError(f"--fov must be in (0, 120) deg, got {args.fov}")
    if not (0.0 < args.fov_tolerance <= 0.5):
        raise InputError(f"--fov-tolerance must be in (0, 0.5], got {args.fov_tolerance}")
    image, meta = read_image(args.image)
    if args.fov is not None:
        fov_range = (args.fov * (1.0 - args.fov_tolerance), args.fov * (1.0 + args.fov_tolerance))
    else:
        fov_range = DEFAULT_FOV_RANGE_DEG
    catalog = load_catalog(args.catalog)
    fov_min = LEVEL_MARGIN * fov_range[0] if args.fov is not None else fov_range[0]
    index = load_or_build_index(catalog, cache_dir=args.cache_dir, fov_min_deg=fov_min, fov_max_deg=fov_range[1],
                                vmag_limit=vmag_limit_for_density(catalog.vmag, fov_min))
    try:
        solution = solve_image(image, index=index, fov_deg=args.fov, fov_tolerance=args.fov_tolerance,
                               saturation_adu=meta.saturation_adu, invalid=meta.invalid, lossy=meta.lossy)
    except NoSolutionError as exc:
        print(f"opnav solve: no solution for {args.image}: {exc}", file=sys.stderr)
        return 1
    record = summary(solution, time.perf_counter() - started)
    if args.json:
        print(json.dumps(record))
    else:
        print(f"{args.image}: RA {record['ra_deg']:.4f} deg, Dec {record['dec_deg']:.4f} deg, roll {record['roll_deg']:.2f} deg, "
              f"FOV {record['fov_deg']:.3f} deg, {record['matched']} stars matched (p_false {record['p_false']:.1g}), "
              f"solve {record['solve_ms']:.1f} ms, total {record['total_ms']:.0f} ms")
    return 0
