"""``opnav calibrate``: a camera's focal length, principal point and distortion from star fields.

Example::

    opnav calibrate frames/*.fits --out camera.toml
    opnav calibrate night/*.jpg --fov 11.4 --model radial2 --out camera.toml
    opnav calibrate frames/*.fits --camera nominal.toml --fit f,k1,k2 --out camera.toml

identifies the stars of every frame (one camera; FITS, PNG, TIFF, JPEG) through the lost-in-space
path of ``opnav solve`` (or the WCS pointing of a frame no pattern index solves; ``--identify wcs``:
from a FITS frame's WCS pointing alone, without a pattern index), matches every
extracted star to the catalog and leaves out those with a catalog neighbour close enough to pull
their centroids (``--neighbour-radius-px``, ``--neighbour-depth-mag``;
:mod:`opnav.image.calibration_stars`), fits the camera and each
frame's attitude (:mod:`opnav.image.calibration`: robust least squares, outliers rejected) and writes

- ``--out`` (a camera file, docs/formats/camera.md): the calibrated camera (the starting camera's
  detector fields kept) and a ``[calibration]`` table with the parameters' sigmas and correlations;
- ``<out stem>_report.md`` and ``_report.html`` beside it, figures under ``figures/``: the
  parameters, their correlations, the fit, per-frame RMS and star counts, residual vectors across the
  detector and radial/tangential residual against field radius, before and after.

The starting camera is ``--camera`` (a camera file), else the first frame's plate solution (a
pinhole at the detector centre with the solved focal length and the default detector fields).
A frame that cannot be used (no solution, too few stars) is named on stderr and left out (no frame
left: one line with the first frame's reason); frames
of different sizes or ``CAMERA`` keywords are refused, as are fewer than 4 stars a frame, more
unknowns than residuals, or a parameter named in ``--fit`` the stars do not constrain (one line
naming it). ``--fit auto`` (the default) always answers: the principal point is estimated with a
prior (``--principal-point-sigma-px``; in a narrow field it is mostly a turn of the attitude) and
the share of its information the stars give is printed and written to the camera file, and any
other parameter the stars do not constrain is held and named.
"""

from __future__ import annotations

import argparse
import sys

NAME = "calibrate"
OUT = "file"
HELP = "calibrate a camera (focal length, principal point, distortion) from star-field frames"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..image.calibration import AUTO, FLOOR_AUTO, MAX_SIGMA_PX, MODELS, PARAMETERS, PRINCIPAL_POINT_SIGMA_PX
    from ..image.calibration_stars import MATCH_RADIUS_PX, NEIGHBOUR_DEPTH_MAG, NEIGHBOUR_RADIUS_PX

    parser.add_argument("frames", nargs="+", help="image files of one camera: FITS, PNG, TIFF or JPEG")
    parser.add_argument("--out", required=True, help="camera file to write (TOML, docs/formats/camera.md)")
    parser.add_argument("--camera", default=None, help="starting camera file (default: the first frame's plate solution)")
    parser.add_argument("--fov", type=float, default=None, metavar="DEG",
                        help="horizontal field of view guess, deg, for the plate solve (default: --camera's, else a "
                             "FITS WCS, else a search)")
    parser.add_argument("--model", default="brown", type=str.lower, choices=tuple(MODELS),
                        help="distortion coefficients the camera has (default brown: k1 k2 k3 p1 p2)")
    parser.add_argument("--fit", default=AUTO, metavar="P,P,...",
                        help=f"parameters to fit from the stars alone, comma-separated from {','.join(PARAMETERS)} "
                             f"(the others keep the starting camera's values; one the stars do not constrain is "
                             f"refused), or {AUTO} (the default): all of the model's, the principal point with a "
                             f"prior of --principal-point-sigma-px, any other parameter the stars do not constrain "
                             f"held, each named in the output")
    parser.add_argument("--principal-point-sigma-px", type=float, default=PRINCIPAL_POINT_SIGMA_PX,
                        help=f"--fit {AUTO}: 1-sigma a axis of the starting camera's principal point, px (default "
                             f"{PRINCIPAL_POINT_SIGMA_PX:g}; a narrow field's stars hardly constrain it)")
    parser.add_argument("--max-sigma-px", type=float, default=MAX_SIGMA_PX,
                        help=f"refuse a parameter whose 1-sigma moves the detector corner by more than this, px "
                             f"(default {MAX_SIGMA_PX:g})")
    parser.add_argument("--sigma-floor-px", default="0", metavar=f"PX|{FLOOR_AUTO}",
                        help=f"centroid error added in quadrature to every star's covariance, px (default 0), or "
                             f"{FLOOR_AUTO}: estimated from the stars' own residuals (printed and written)")
    parser.add_argument("--identify", default="solve", choices=("solve", "wcs"),
                        help="how each frame's stars are first identified: solve (lost in space, as opnav solve; the "
                             "default) or wcs (from a FITS frame's WCS pointing: no pattern index needed)")
    parser.add_argument("--match-radius-px", type=float, default=MATCH_RADIUS_PX,
                        help=f"largest distance of a star from its predicted place, px (default {MATCH_RADIUS_PX:g})")
    parser.add_argument("--neighbour-radius-px", type=float, default=NEIGHBOUR_RADIUS_PX,
                        help=f"a star with a catalog neighbour within this of it, px, ... (default {NEIGHBOUR_RADIUS_PX:g})")
    parser.add_argument("--neighbour-depth-mag", type=float, default=NEIGHBOUR_DEPTH_MAG,
                        help=f"... and at most this many magnitudes fainter is left out: the neighbour's light biases "
                             f"its centroid in every frame (default {NEIGHBOUR_DEPTH_MAG:g}; a negative value keeps "
                             f"every star)")
    parser.add_argument("--max-stars", type=int, default=200, help="point sources extracted a frame (default 200)")
    parser.add_argument("--epoch", default=None, metavar="UTC",
                        help="date of the frames, ISO UTC: catalog stars are moved to it (default: a FITS header's "
                             "mid-exposure epoch, else the catalog's epoch)")
    parser.add_argument("--velocity", type=float, nargs=3, default=None, metavar=("VX", "VY", "VZ"),
                        help="observer velocity relative to the solar-system barycentre, ICRF, km/s: the catalog stars "
                             "are aberrated with it (default: OBS_VX/VY/VZ of a FITS header; without either the field's "
                             "scale is off by up to |v|/c, 1e-4 for a camera on the Earth)")
    parser.add_argument("--bayer", default=None, type=str.upper, choices=("RGGB", "BGGR", "GRBG", "GBRG"),
                        metavar="PATTERN", help="the files are raw Bayer mosaics of this 2x2 pattern")
    parser.add_argument("--catalog", default=None, help="star catalog file (default: the packaged catalog)")
    parser.add_argument("--cache-dir", default=None, help="pattern-index cache directory (default $OPNAV_CACHE "
                        "or ~/.cache/opnav)")
    parser.add_argument("--no-report", action="store_true", help="write the camera file only")


def _floor(text: str) -> float | str:
    """``--sigma-floor-px``: a number of px, or the word that asks the fit to estimate it (range checked by
    :func:`opnav.image.calibration.calibrate`)."""
    from ..errors import InputError
    from ..image.calibration import FLOOR_AUTO

    if text.strip().lower() == FLOOR_AUTO:
        return FLOOR_AUTO
    try:
        return float(text)
    except ValueError:
        raise InputError(f"--sigma-floor-px must be a number >= 0 or {FLOOR_AUTO}, got {text!r}") from None


def _same_camera(identified) -> None:
    """Refuse frames of different sizes or ``CAMERA`` keywords (one line naming two of them)."""
    from ..errors import InputError

    first = identified[0]
    for other in identified[1:]:
        if other.shape != first.shape:
            raise InputError(f"frames of different cameras: {first.stars.name} is {first.shape[1]} x {first.shape[0]} px, "
                             f"{other.stars.name} {other.shape[1]} x {other.shape[0]} px; calibrate one camera at a time")
        if None not in (first.camera_id, other.camera_id) and other.camera_id != first.camera_id:
            raise InputError(f"frames of different cameras: {first.stars.name} has CAMERA = {first.camera_id!r}, "
                             f"{other.stars.name} {other.camera_id!r}; calibrate one camera at a time")


def run(args: argparse.Namespace) -> int:
    import math
    from pathlib import Path

    from ..camera import CameraCovariance, read_camera_file, write_camera_file
    from ..catalog import load_catalog
    from ..errors import FrameError, InputError, NoSolutionError
    from ..image.calibration import AUTO, FLOOR_AUTO, calibrate
    from ..image.calibration_stars import frame_stars
    from ..image.plate_solve import PlateSolver, SolveOptions
    from ..studies.report_calibration import write_calibration_report
    from ..studies.report_page import provenance

    if args.max_stars < 4:
        raise InputError(f"--max-stars must be at least 4, got {args.max_stars}")
    floor = _floor(args.sigma_floor_px)
    fit = None if args.fit.strip().lower() == AUTO else [name for name in args.fit.split(",")]
    if not math.isfinite(args.neighbour_depth_mag):
        raise InputError(f"--neighbour-depth-mag must be a number of magnitudes, got {args.neighbour_depth_mag!r}")
    depth = None if args.neighbour_depth_mag < 0 else args.neighbour_depth_mag
    start = read_camera_file(args.camera).camera if args.camera else None
    fov = args.fov if args.fov is not None else (math.degrees(start.fov_x_rad) if start is not None else None)
    epoch_tdb_s = None
    if args.epoch is not None:
        from ..epochs import parse_epoch

        epoch_tdb_s = float(parse_epoch(args.epoch, "utc"))
    # with --camera the plate solve uses it (distortion and principal point; its field of view the guess)
    options = SolveOptions(fov_deg=fov, bayer=args.bayer, epoch_tdb_s=epoch_tdb_s, velocity_km_s=args.velocity,
                           camera=start)
    solver = PlateSolver(load_catalog(args.catalog), options, cache_dir=args.cache_dir)
    identified, notes, left_out = [], {}, []
    for path in args.frames:
        try:
            found = frame_stars(path, solver, start, max_stars=args.max_stars, match_radius_px=args.match_radius_px,
                                identify=args.identify, neighbour_radius_px=args.neighbour_radius_px,
                                neighbour_depth_mag=depth)
        except (NoSolutionError, FrameError) as exc:
            left_out.append(str(exc) if str(path) in str(exc) else f"{path}: {exc}")
            continue
        identified.append(found)
        notes[found.stars.name] = f"{found.method.replace('_', ' ')}, {found.solved_matches} stars first matched"
    if not identified:
        more = f" (and {len(left_out) - 1} more frames)" if len(left_out) > 1 else ""
        raise InputError(f"none of the {len(args.frames)} frames gave identified stars: {left_out[0]}{more}")
    for reason in left_out:  # the frames that could not be used, named, before the fit of the others
        print(f"opnav calibrate: left out {reason}", file=sys.stderr)
    _same_camera(identified)
    if start is None:
        start = identified[0].solved_camera
    result = calibrate([f.stars for f in identified], start, model=args.model, fit=fit,
                       max_sigma_px=args.max_sigma_px, sigma_floor_px=floor,
                       principal_point_sigma_px=args.principal_point_sigma_px)
    prov = provenance(["opnav", *sys.argv[1:]] if sys.argv and sys.argv[0].endswith("opnav") else None, None)
    summary = {"model": result.model, "frames": len(result.frames), "stars": result.n_stars,
               "rejected": result.n_rejected, "chi2_per_dof": round(result.chi2_per_dof, 4),
               "rms_px": round(result.rms_px, 5), "sigma_floor_px": round(result.sigma_floor_px, 6), "date_utc": prov.date_utc,
               "fit": ",".join(result.names) if fit is not None else AUTO}
    priors = {n: float(s) for n, s in zip(result.names, result.prior_sigma) if math.isfinite(s)}
    if priors:  # what the stars constrain and what came from the prior, in the file too
        summary["prior_sigma"] = priors
        summary["stars_share"] = {n: round(float(v), 4) for n, v in zip(result.names, result.stars_share) if n in priors}
    if result.held:
        summary["held"] = list(result.held)
    for reason in result.dropped:  # frames whose stars do not fit the others' camera: named, left out
        print(f"opnav calibrate: left out {reason}", file=sys.stderr)
    if result.dropped:
        summary["dropped"] = list(result.dropped)
    out = Path(args.out)
    write_camera_file(out, result.camera, CameraCovariance(result.names, result.covariance, summary),
                      comment=f"opnav calibrate: {len(result.frames)} frames, {result.n_stars} stars\n"
                              f"docs/formats/camera.md")
    pages = () if args.no_report else write_calibration_report(out.parent, f"{out.stem}_report", result, prov,
                                                               frame_notes=notes)
    sigma = dict(zip(result.names, result.sigma))
    shown = ", ".join(f"{n} {result.value(n):.6g} +- {sigma[n]:.2g}" for n in result.names)
    print(f"{len(result.frames)} frames, {result.n_stars} stars ({result.n_rejected} rejected), chi2/dof "
          f"{result.chi2_per_dof:.3f}, RMS {result.rms_px:.3g} px: {shown}")
    if floor == FLOOR_AUTO:
        print(f"centroid floor estimated from the stars: {result.sigma_floor_px:.4f} px (--sigma-floor-px auto)")
    share = dict(zip(result.names, result.stars_share))
    for name, prior in priors.items():
        print(f"{name}: prior {prior:g} px a axis; the stars give {100 * max(share[name], 0.0):.0f} % of its information"
              + (" (it stays near the starting camera's)" if share[name] < 0.5 else ""))
    if result.held:
        print(f"held at the starting camera's values (the stars do not constrain them): {', '.join(result.held)}")
    print(f"camera in {out}" + (f"; report in {pages[1]} and {pages[0]}" if pages else ""))
    return 0

