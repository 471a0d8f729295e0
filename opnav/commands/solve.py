"""``opnav solve``: lost-in-space plate solve of an image file (FITS, PNG, TIFF, JPEG).

Example::

    opnav solve frame.fits --fov 11.4 --json

prints the ICRF right ascension and declination of the image centre, the roll (position
angle of the image's "up", i.e. decreasing row, measured from north through east), the
horizontal field of view of the solution, the number of matched stars, the field-of-view
ranges searched and the times spent.
Exit status 1 when no solution passes verification, 2 on unusable input.

Which pointing: ``"pointing": "geometric"`` is the attitude against the catalog's astrometric
directions (no stellar aberration). With the observer's velocity (``--velocity``, or the
``OBS_VX/VY/VZ`` keywords of an opnav FITS header) the answer is the *apparent* pointing, the one
a camera moving at that velocity sees and a rendered frame's WCS holds (they differ by up to
``|v| / c``: 20" at 30 km/s).

Which stars: the catalog holds its stars at its own epoch (Hipparcos 1991.25). With the frame's
date (``--epoch``, or the ``TDB_S`` / ``DATE-AVG`` / ``DATE-OBS`` keywords of a FITS header) the
stars are moved to it (proper motion; parallax too with the header's ``OBS_X/Y/Z``) before the
match is verified: a fast star is 2 px from its catalog place after 30 years in a 3.5"/px camera.
Without a date the catalog epoch is used, and the output says which (``"star_epoch"``).

The pattern index is built from the star catalog (``opnav.catalog.load_catalog``) for the
FOV range the search needs and cached under ``$OPNAV_CACHE`` (default ``~/.cache/opnav``).
With ``--fov`` it covers that FOV +- the tolerance (a field narrower than ``NARROW_FOV_DEG``
gets a lattice-field index: 30-50 s to build the first time, progress on stderr). Without
``--fov`` the default range (``DEFAULT_FOV_RANGE_DEG``) is searched, then every narrow index
already in the cache for this catalog (built by an earlier ``--fov`` run); the ranges searched
are printed.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from ..catalog import load_catalog
from ..epochs import format_epoch, parse_epoch
from ..errors import CatalogError, InputError, NoSolutionError
from ..frames import unit_to_radec
from ..image.io import BAYER_PATTERNS, read_image
from ..image.starid import PlateSolution, solve_stars, solve_with_deeper_extraction
from ..image.starid_index import (
    FORMAT_VERSION,
    PatternIndex,
    catalog_digest,
    default_cache_dir,
    load_or_build_index,
    stderr_progress,
    vmag_limit_for_density,
)

NAME = "solve"
HELP = "lost-in-space plate solve of an image (FITS, PNG, TIFF, JPEG): pointing, roll, field of view"

#: Without --fov, the index covers horizontal fields of view in this range, deg.
DEFAULT_FOV_RANGE_DEG = (10.0, 45.0)
#: The smallest index level is this fraction of the smallest FOV searched: a frame then holds
#: patterns of a denser level too, which makes sparse or cluttered fields solvable.
LEVEL_MARGIN = 0.6
#: Below this horizontal FOV, deg, the index is built from lattice fields (``selection="fields"``).
NARROW_FOV_DEG = 4.0
#: Smallest level of a narrow index as a fraction of the smallest FOV searched.
NARROW_LEVEL_MARGIN = 0.75
#: Brightest stars of each lattice field that form patterns in a narrow index.
NARROW_STARS_PER_FIELD = 8
#: Lattice-field diameter of a narrow index as a fraction of each level's FOV. A field as wide
#: as the level's frame holds the frame's brightest stars even when they sit near its edges
#: (0.7 left 19 of the 60 ``make demo`` frames with no 4 of their stars in one field).
NARROW_PATTERN_SIZE_FRACTION = 1.0
#: Sparse level of a ``--fov`` index of a wider field (:class:`opnav.image.starid_index.IndexOptions`):
#: local brightness maxima about this fraction of the largest FOV apart form patterns as large as
#: the frame. 0.18 (1.2 deg for a 6.1 deg field) held a pattern of 2 in 3 of the 6.1 x 4.6 deg
#: frames of 5-9 stars that the levels miss, for 45 % more patterns; 0.16 (1.07 deg) also holds
#: the frames whose fainter stars have a brighter neighbour just beyond the frame's edge (2 of
#: 100 JPEG q70 frames of ``benchmarks/starid_real.py``'s 6.1-degree camera), for 56 % more again
#: (10.7 million patterns for that camera).
SPARSE_SPACING_FRACTION = 0.16


def index_options_for_fov(catalog, fov_deg: float, fov_tolerance: float) -> dict:
    """Keywords of :func:`load_or_build_index` for a horizontal FOV guess ``fov_deg`` +- ``fov_tolerance``.

    Fields narrower than ``NARROW_FOV_DEG`` get a ``"fields"`` index (patterns from the brightest
    stars of lattice fields, bounded in size however deep the catalog; see
    :mod:`opnav.image.starid_index`) with levels from ``NARROW_LEVEL_MARGIN`` of the smallest FOV.
    """
    low, high = fov_deg * (1.0 - fov_tolerance), fov_deg * (1.0 + fov_tolerance)
    if fov_deg < NARROW_FOV_DEG:
        fov_min = NARROW_LEVEL_MARGIN * low
        return dict(fov_min_deg=fov_min, fov_max_deg=high, vmag_limit=vmag_limit_for_density(catalog.vmag, fov_min),
                    selection="fields", pattern_stars_per_fov=NARROW_STARS_PER_FIELD,
                    pattern_size_fraction=NARROW_PATTERN_SIZE_FRACTION)
    fov_min = LEVEL_MARGIN * low
    return dict(fov_min_deg=fov_min, fov_max_deg=high, vmag_limit=vmag_limit_for_density(catalog.vmag, fov_min),
                sparse_spacing_fraction=SPARSE_SPACING_FRACTION)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("image", help="image file: FITS, PNG, TIFF (8/16 bit) or JPEG, mono or RGB")
    parser.add_argument("--fov", type=float, default=None, metavar="DEG",
                        help=f"horizontal field of view guess, deg (default: search {DEFAULT_FOV_RANGE_DEG[0]:g}-"
                        f"{DEFAULT_FOV_RANGE_DEG[1]:g} deg)")
    parser.add_argument("--fov-tolerance", type=float, default=0.1,
                        help="relative uncertainty of --fov (default 0.1 = +-10%%)")
    parser.add_argument("--bayer", default=None, type=str.upper, choices=BAYER_PATTERNS, metavar="PATTERN",
                        help="the file is a raw Bayer mosaic with this 2x2 filter pattern (RGGB, BGGR, GRBG, GBRG): "
                        "demosaic it to luminance before extraction")
    parser.add_argument("--catalog", default=None, help="star catalog file (default: the packaged catalog)")
    parser.add_argument("--cache-dir", default=None, help="pattern-index cache directory (default $OPNAV_CACHE "
                        "or ~/.cache/opnav)")
    parser.add_argument("--velocity", type=float, nargs=3, default=None, metavar=("VX", "VY", "VZ"),
                        help="observer velocity relative to the solar-system barycentre, ICRF, km/s: report the "
                        "apparent (aberrated) pointing (default: OBS_VX/VY/VZ of a FITS header, else the geometric one)")
    parser.add_argument("--epoch", default=None, metavar="UTC",
                        help="date of the frame, ISO UTC (e.g. 2024-03-01T12:00:00): catalog stars are moved to it "
                        "(default: TDB_S, DATE-AVG or DATE-OBS of a FITS header, else the catalog's epoch)")
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


def summary(solution: PlateSolution, total_s: float, *, v_observer_km_s: np.ndarray | None = None,
            searched: list | None = None) -> dict:
    """The JSON record printed by the command (``pointing``: geometric, or apparent with a velocity)."""
    camera = solution.camera
    rotation = solution.attitude(v_observer_km_s)
    center = rotation.apply(camera.unproject(np.array([(camera.width_px - 1) / 2.0, (camera.height_px - 1) / 2.0])))
    ra, dec = unit_to_radec(center)
    record = {
        "ra_deg": round(math.degrees(float(ra)), 6),
        "dec_deg": round(math.degrees(float(dec)), 6),
        "roll_deg": round(_roll_deg(center, rotation.apply([0.0, -1.0, 0.0])), 4),
        "pointing": "geometric" if v_observer_km_s is None else "apparent",
        "fov_deg": round(math.degrees(camera.fov_x_rad), 5),
        "matched": len(solution.identification.pairs),
        "p_false": float(f"{solution.identification.p_false:.3g}"),
        "solve_ms": round(1e3 * solution.solve_s, 2),
        "extract_ms": round(1e3 * solution.extract_s, 2),
        "total_ms": round(1e3 * total_s, 2),
    }
    if v_observer_km_s is not None:
        record["velocity_km_s"] = [round(float(v), 6) for v in v_observer_km_s]
    if searched is not None:
        record["fov_searched_deg"] = [[round(low, 3), round(high, 3)] for low, high in searched]
    return record


def _header_epoch(header) -> float | None:
    """Mid-exposure (or start) epoch, TDB s past J2000, from an opnav or common FITS header; None without one."""
    if header is None:
        return None
    try:
        value = float(header["TDB_S"])
        if math.isfinite(value):
            return value
    except (KeyError, TypeError, ValueError):
        pass
    for key in ("DATE-AVG", "DATE-OBS"):
        try:
            return float(parse_epoch(str(header[key]).strip(), "utc"))
        except (KeyError, InputError):
            continue
    return None


def _header_vector(header, keys: tuple[str, str, str]) -> np.ndarray | None:
    """Three finite numbers from ``keys`` of a FITS header (opnav's OBS_X/Y/Z, km, and OBS_VX/VY/VZ, km/s:
    observer position and velocity relative to the solar-system barycentre, ICRF); None without them."""
    if header is None:
        return None
    try:
        vector = np.array([float(header[key]) for key in keys])
    except (KeyError, TypeError, ValueError):
        return None
    return vector if np.all(np.isfinite(vector)) else None


def cached_narrow_indexes(catalog, cache_dir) -> list[tuple[float, float, str]]:
    """``(fov low, fov high, path)`` of the narrow (``"fields"``) indexes cached for ``catalog``, narrowest first.

    Only indexes built with this version's narrow options (``NARROW_STARS_PER_FIELD``,
    ``NARROW_PATTERN_SIZE_FRACTION``) are offered: one left in the cache by an earlier version
    covers fewer frames and would only cost a failed search before the current one. Only each
    file's small header entries are read here; a file that cannot be read is skipped (it is
    rebuilt when its FOV is asked for with ``--fov``).
    """
    directory = default_cache_dir() if cache_dir is None else Path(cache_dir)
    digest = catalog_digest(catalog)
    current = {"selection": "fields", "pattern_stars_per_fov": NARROW_STARS_PER_FIELD,
               "pattern_size_fraction": NARROW_PATTERN_SIZE_FRACTION}
    found = []
    for path in sorted(directory.glob("starid-*.npz")):
        try:
            with np.load(path) as data:
                options = json.loads(str(data["options"]))
                if int(data["format_version"]) != FORMAT_VERSION or str(data["catalog_digest"]) != digest or any(
                        options.get(key) != value for key, value in current.items()):
                    continue
        except Exception:  # noqa: BLE001 - any unreadable cache file is simply not offered
            continue
        found.append((options["fov_min_deg"] / NARROW_LEVEL_MARGIN, options["fov_max_deg"], str(path)))
    return sorted(found)


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    if args.fov is not None and not (0.0 < args.fov < 120.0):
        raise InputError(f"--fov must be in (0, 120) deg, got {args.fov}")
    if not (0.0 < args.fov_tolerance <= 0.5):
        raise InputError(f"--fov-tolerance must be in (0, 0.5], got {args.fov_tolerance}")
    velocity = None
    if args.velocity is not None:
        velocity = np.asarray(args.velocity, dtype=float)
        if not np.all(np.isfinite(velocity)) or np.linalg.norm(velocity) >= 299792.458:
            raise InputError(f"--velocity must be finite and below the speed of light, got {args.velocity}")
    image, meta = read_image(args.image, bayer=args.bayer)
    if velocity is None:
        velocity = _header_vector(meta.header, ("OBS_VX", "OBS_VY", "OBS_VZ"))
    epoch = parse_epoch(args.epoch, "utc") if args.epoch is not None else _header_epoch(meta.header)
    position = _header_vector(meta.header, ("OBS_X", "OBS_Y", "OBS_Z")) if epoch is not None else None
    catalog = load_catalog(args.catalog)
    progress = stderr_progress
    if args.fov is not None:
        attempts = [(args.fov * (1.0 - args.fov_tolerance), args.fov * (1.0 + args.fov_tolerance),
                     lambda: load_or_build_index(catalog, cache_dir=args.cache_dir, progress=progress,
                                                 **index_options_for_fov(catalog, args.fov, args.fov_tolerance)))]
    else:
        low, high = DEFAULT_FOV_RANGE_DEG
        attempts = [(low, high, lambda: load_or_build_index(
            catalog, cache_dir=args.cache_dir, progress=progress, fov_min_deg=low, fov_max_deg=high,
            vmag_limit=vmag_limit_for_density(catalog.vmag, low)))]
        for low_n, high_n, path in cached_narrow_indexes(catalog, args.cache_dir):
            attempts.append((low_n, high_n, lambda path=path: PatternIndex.load(path)))
    searched, failures = [], []
    loaded: dict[int, PatternIndex | None] = {}

    def solve_in_each_index(xy: np.ndarray, cov: np.ndarray) -> PlateSolution:
        for k, (low, high, load) in enumerate(attempts):
            if k not in loaded:
                loaded[k] = None
                try:
                    index = load()
                except CatalogError as exc:
                    failures.append(f"{low:g}-{high:g} deg: {exc}")
                    continue
                searched.append((low, high))
                if epoch is not None:
                    index = index.at_epoch(catalog, t_tdb_s=float(epoch), r_observer_ssb_km=position)
                loaded[k] = index
            if loaded[k] is None:
                continue
            try:
                if args.fov is not None:
                    return solve_stars(xy, cov, image.shape, index=loaded[k], fov_deg=args.fov,
                                       fov_tolerance=args.fov_tolerance)
                return solve_stars(xy, cov, image.shape, index=loaded[k], fov_range_deg=(low, high),
                                   fov_tolerance=args.fov_tolerance)
            except NoSolutionError as exc:
                failures.append(f"{low:g}-{high:g} deg: {exc}")
        raise NoSolutionError(failures[-1] if failures else "no pattern index could be loaded")

    try:
        solution = solve_with_deeper_extraction(image, solve_in_each_index, saturation_adu=meta.saturation_adu,
                                                invalid=meta.invalid, lossy=meta.lossy)
        why = ""
    except NoSolutionError as exc:
        solution, why = None, str(exc)
    ranges = ", ".join(f"{low:g}-{high:g}" for low, high in searched)
    if solution is None:
        hint = "" if args.fov is not None else " (a narrower field is searched once an index for it is built: pass --fov)"
        print(f"opnav solve: no solution for {args.image}: searched horizontal FOV {ranges} deg{hint}; "
              f"{why}", file=sys.stderr)
        return 1
    record = summary(solution, time.perf_counter() - started, v_observer_km_s=velocity, searched=searched)
    record["star_epoch"] = "catalog" if epoch is None else format_epoch(float(epoch), "utc", 3)
    if args.json:
        print(json.dumps(record))
    else:
        print(f"{args.image}: RA {record['ra_deg']:.4f} deg, Dec {record['dec_deg']:.4f} deg, roll {record['roll_deg']:.2f} deg "
              f"({record['pointing']} pointing), FOV {record['fov_deg']:.3f} deg, {record['matched']} stars matched "
              f"(p_false {record['p_false']:.1g}), stars at {record['star_epoch']} epoch, searched FOV {ranges} deg, "
              f"extract {record['extract_ms']:.0f} ms, "
              f"solve {record['solve_ms']:.1f} ms, total {record['total_ms']:.0f} ms")
    return 0
