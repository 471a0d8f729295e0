"""``opnav solve``: lost-in-space plate solve of image files (FITS, PNG, TIFF, JPEG).

Example::

    opnav solve frame.fits --fov 11.4 --json
    opnav solve frames/*.fits --json

prints, for each image, the ICRF right ascension and declination of the image centre, the roll
(position angle of the image's "up", i.e. decreasing row, measured from north through east), the
horizontal field of view of the solution, the number of matched stars, the field-of-view ranges
searched and the times spent. With ``--json`` each image gives one line, a JSON object; an image
that fails gives an object with its ``"error"`` (and the line on stderr) and the others go on.
Exit status 0 when every image solved, else 1 when some had no solution that passes
verification, 2 when one was unusable (or an option was).

Which field of view (``"hint"``): ``--fov``, or the field of view of ``--camera`` (a camera file,
docs/formats/camera.md, whose distortion and principal point then turn the stars' pixels into
bearings) (``"fov"``); else a FITS frame's celestial TAN WCS
(``CDi_j`` or ``CDELTi``, ``CRVAL``, ``CTYPE`` ``RA---TAN``, SIP allowed) gives it (``"wcs"``, with
``"hint_offset_deg"``, the angle between the solved image centre and the WCS's); else (``"none"``)
the default range (``DEFAULT_FOV_RANGE_DEG``) is searched, then every narrow index already in the
cache for this catalog (built by an earlier ``--fov`` or WCS run); the ranges searched are printed.
``"method"``: ``"lost_in_space"`` (a pattern index: the WCS pointing is checked, not used), or
``"tracking"`` for a frame with a WCS that no index solves (a sparse frame), its stars matched
around the WCS pointing (:mod:`opnav.image.plate_solve`). ``--no-wcs`` ignores the WCS.

Which pointing: ``"pointing": "geometric"`` is the attitude against the catalog's astrometric
directions (no stellar aberration). With the observer's velocity (``--velocity``, or the
``OBS_VX/VY/VZ`` keywords of an opnav FITS header) the answer is the *apparent* pointing, the one
a camera moving at that velocity sees and a rendered frame's WCS holds (they differ by up to
``|v| / c``: 20" at 30 km/s).

Which stars: the catalog holds its stars at its own epoch (Hipparcos 1991.25). With the frame's
date (``--epoch``, or the FITS header's mid-exposure epoch: ``TDB_S``, ``DATE-AVG``, or
``DATE-OBS`` + ``EXPTIME/2`` in ``TIMESYS``, :mod:`opnav.image.header`) the stars are moved to it
(proper motion; parallax too with the header's ``OBS_X/Y/Z``) before the match is verified: a fast
star is 2 px from its catalog place after 30 years in a 3.5"/px camera. Without a date the
catalog epoch is used, and the output says which (``"star_epoch"``).

The pattern index is built from the star catalog for the FOV range the search needs and cached
under ``$OPNAV_CACHE`` (default ``~/.cache/opnav``), memory-mapped (:mod:`opnav.image.starid_index`,
which also chooses it): a field narrower than ``NARROW_FOV_DEG`` gets a lattice-field index,
30-50 s to build the first time (progress on stderr), then opened in milliseconds. The frames of
one command share the loaded indexes.
"""

from __future__ import annotations

import argparse
import json
import math
import sys

NAME = "solve"
HELP = "lost-in-space plate solve of images (FITS, PNG, TIFF, JPEG): pointing, roll, field of view"



def add_arguments(parser: argparse.ArgumentParser) -> None:
    if "numpy" not in sys.modules:
        # this process is the command, numpy not loaded yet: a plate solve's linear algebra is 3 x 3
        # (Wahba, projections), and OpenBLAS's idle worker threads spin a second core (0.2 s of CPU a
        # one-frame process, 0.1 s of wall on a busy 2-core machine); a value the user set stands
        import os

        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from ..image.io import BAYER_PATTERNS
    from ..image.starid_index import DEFAULT_FOV_RANGE_DEG

    parser.add_argument("image", nargs="+", help="image files: FITS, PNG, TIFF (8/16 bit) or JPEG, mono or RGB")
    parser.add_argument("--fov", type=float, default=None, metavar="DEG",
                        help=f"horizontal field of view guess, deg (default: a FITS frame's WCS, else search "
                        f"{DEFAULT_FOV_RANGE_DEG[0]:g}-{DEFAULT_FOV_RANGE_DEG[1]:g} deg)")
    parser.add_argument("--fov-tolerance", type=float, default=0.1,
                        help="relative uncertainty of --fov or of the WCS's field of view (default 0.1 = +-10%%)")
    parser.add_argument("--no-wcs", action="store_true", help="ignore a FITS WCS (its field of view, and the pointing a "
                        "frame no pattern index solves is tracked from)")
    parser.add_argument("--bayer", default=None, type=str.upper, choices=BAYER_PATTERNS, metavar="PATTERN",
                        help="the files are raw Bayer mosaics with this 2x2 filter pattern (RGGB, BGGR, GRBG, GBRG): "
                        "demosaic them to luminance before extraction")
    parser.add_argument("--catalog", default=None, help="star catalog file (default: the packaged catalog)")
    parser.add_argument("--cache-dir", default=None, help="pattern-index cache directory (default $OPNAV_CACHE "
                        "or ~/.cache/opnav)")
    parser.add_argument("--velocity", type=float, nargs=3, default=None, metavar=("VX", "VY", "VZ"),
                        help="observer velocity relative to the solar-system barycentre, ICRF, km/s: report the "
                        "apparent (aberrated) pointing (default: OBS_VX/VY/VZ of a FITS header, else the geometric one)")
    parser.add_argument("--epoch", default=None, metavar="UTC",
                        help="date of the frames, ISO UTC (e.g. 2024-03-01T12:00:00): catalog stars are moved to it "
                        "(default: a FITS header's mid-exposure epoch, else the catalog's epoch)")
    parser.add_argument("--camera", default=None, metavar="CAMERA.toml",
                        help="camera file (docs/formats/camera.md, e.g. from opnav calibrate): its distortion and "
                             "principal point turn the stars' pixels into bearings, its field of view is the guess "
                             "(instead of --fov)")
    parser.add_argument("--json", action="store_true", help="print one JSON object per image, one a line")


def stderr_progress(stage: str, done: int, total: int) -> None:
    """A ``progress`` callback for an index build writing one updating line to stderr."""
    end = "\n" if done >= total else ""
    print(f"\r  building pattern index: {stage} {100.0 * done / max(total, 1):5.1f} %", end=end, file=sys.stderr, flush=True)


def _roll_deg(center_icrf, up_icrf) -> float:
    """Position angle (deg, north through east) of ``up_icrf`` at ``center_icrf``."""
    import numpy as np

    pole = np.array([0.0, 0.0, 1.0])
    east = np.cross(pole, center_icrf)
    if np.linalg.norm(east) < 1e-12:  # at a celestial pole, north is undefined: use +x as the reference
        east = np.cross(center_icrf, np.array([1.0, 0.0, 0.0]))
    east /= np.linalg.norm(east)
    north = np.cross(center_icrf, east)
    return math.degrees(math.atan2(up_icrf @ east, up_icrf @ north)) % 360.0


def summary(solution, total_s: float, *, v_observer_km_s=None, searched: list | None = None) -> dict:
    """The JSON record printed for a :class:`opnav.image.starid.PlateSolution` (``pointing``: geometric, or
    apparent with a velocity)."""
    import numpy as np

    from ..frames import unit_to_radec

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


def frame_record(found) -> dict:
    """The JSON record of an :class:`opnav.image.plate_solve.FrameSolution`."""
    from ..epochs import utc_text  # format_epoch's text without astropy's leap-second file (~60 ms a process)

    record = {"image": found.path, **summary(found.solution, found.total_s, v_observer_km_s=found.v_observer_km_s,
                                             searched=list(found.searched))}
    record["star_epoch"] = "catalog" if found.epoch_tdb_s is None else utc_text(float(found.epoch_tdb_s), 3)
    record["hint"] = found.hint
    record["method"] = found.method
    if found.wcs is not None:
        record["hint_fov_deg"] = round(found.wcs.fov_deg, 5)
        record["hint_offset_deg"] = round(math.degrees(found.hint_offset_rad()), 6)
    return record


def _text(record: dict) -> str:
    ranges = ", ".join(f"{low:g}-{high:g}" for low, high in record["fov_searched_deg"])
    return (f"{record['image']}: RA {record['ra_deg']:.4f} deg, Dec {record['dec_deg']:.4f} deg, "
            f"roll {record['roll_deg']:.2f} deg ({record['pointing']} pointing), FOV {record['fov_deg']:.3f} deg, "
            f"{record['matched']} stars matched (p_false {record['p_false']:.1g}), stars at {record['star_epoch']} "
            f"epoch, searched FOV {ranges} deg (hint: {record['hint']}, {record['method'].replace('_', ' ')}), extract {record['extract_ms']:.0f} ms, "
            f"solve {record['solve_ms']:.1f} ms, total {record['total_ms']:.0f} ms")


def run(args: argparse.Namespace) -> int:
    import gc

    if not all(image in sys.argv[1:] for image in args.image):  # called inside a longer process
        return _solve_frames(args, started=lambda: None)
    # this process is the command: the imports, the index and the first frame's kernels are its
    # start-up, which the collector is kept out of (as opnav.cli does while it parses)
    gc.disable()

    def started() -> None:
        gc.freeze()  # what start-up made lives as long as the process: later collections leave it out
        gc.enable()

    status = _solve_frames(args, started)
    # the process ends here: its exit then skips the collector's sweeps over every object left
    # (0.15-0.2 s of a one-frame solve)
    gc.freeze()
    return status


def _solve_frames(args: argparse.Namespace, started) -> int:
    """Solve ``args.image`` one after the other, printing each; ``started()`` is called once the first
    is done. Returns the exit status."""
    from ..catalog import load_catalog
    from ..errors import OpnavError
    from ..image.plate_solve import NoPlateSolution, PlateSolver, SolveOptions

    epoch_tdb_s = None
    if args.epoch is not None:
        from ..epochs import parse_epoch

        epoch_tdb_s = float(parse_epoch(args.epoch, "utc"))
    camera = None
    if args.camera is not None:
        from ..camera import read_camera_file
        from ..errors import InputError

        if args.fov is not None:
            raise InputError("--fov and --camera: give one (the camera file's field of view is the guess)")
        camera = read_camera_file(args.camera).camera
    options = SolveOptions(
        fov_deg=args.fov, fov_tolerance=args.fov_tolerance, bayer=args.bayer, epoch_tdb_s=epoch_tdb_s,
        velocity_km_s=args.velocity, use_wcs=not args.no_wcs, camera=camera)
    solver = PlateSolver(load_catalog(args.catalog), options, cache_dir=args.cache_dir, progress=stderr_progress)
    status = 0
    for k, image in enumerate(args.image):
        if k == 1:
            started()
        try:
            record = frame_record(solver.solve_file(image))
        except NoPlateSolution as exc:
            advice = " (a narrower field is searched once an index for it is built: pass --fov)" \
                if exc.hint == "none" else ""
            message, code = f"no solution for {image}: {exc}{advice}", 1
            print(f"opnav solve: {message}", file=sys.stderr)
        except OpnavError as exc:
            message, code = str(exc), 2
            print(f"opnav solve: error: {message}", file=sys.stderr)
        else:
            print(json.dumps(record) if args.json else _text(record), flush=True)
            continue
        status = max(status, code)
        if args.json:
            print(json.dumps({"image": image, "error": message, "exit_status": code}), flush=True)
    return status
