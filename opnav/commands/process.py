"""``opnav process``: turn a directory of frames into time-tagged measurements.

Example::

    opnav process out/frames --out measurements.csv                   # the bodies the frames show
    opnav process out/frames --targets phobos deimos --out measurements.csv

reads every FITS frame (opnav header: epoch, WCS, detector, observer state), identifies the stars
around the WCS attitude, measures the targets and writes the records as CSV plus a ``.json``
metadata file (:func:`opnav.records.write_csv`). Frames that cannot be used are listed there
under ``skipped``. A tqdm progress bar shows the frames done. ``--camera camera.toml`` (a camera
file, docs/formats/camera.md, such as ``opnav calibrate`` writes) is the camera every frame is
measured with, its distortion included; without it each frame's WCS gives a pinhole camera (the
linear part of a TAN-SIP WCS: its distortion is left out). The work is
:func:`opnav.image.directory.process_folder`; this module parses arguments and prints.

Without ``--targets`` the command measures the bodies the frames show
(:func:`opnav.image.directory.frame_targets`: the truth sidecars ``opnav render`` writes, or the
FITS ``OBJECT`` keyword): the point-like ones (moons, RA/Dec), or the resolved ones (limb) when
there is no point-like one; when the frames name no body it refuses, listing the bodies it knows.
The printed count is the number of records in the file: the two moons of one frame are one
``radec_pair`` record (their shared attitude error as a cross-covariance). A run that gives no
record is an error (exit 2), naming the file that lists why each frame was skipped.
"""

from __future__ import annotations

import argparse
import math

from ..errors import InputError, OpnavError

NAME = "process"
OUT = "file"
HELP = "process a directory of FITS frames into measurement records (CSV + JSON)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("frames_dir", help="directory of FITS frames written by `opnav render`")
    parser.add_argument("--out", default="measurements.csv", help="output CSV (default measurements.csv)")
    parser.add_argument("--targets", nargs="+", default=None, metavar="BODY",
                        help="bodies to measure: phobos deimos mars earth (default: the point-like bodies the "
                             "frames' truth files or OBJECT keyword name, else the resolved ones)")
    parser.add_argument("--camera", default=None, metavar="CAMERA.toml",
                        help="camera file (docs/formats/camera.md, e.g. from opnav calibrate): its focal length, "
                             "principal point and distortion turn pixels into directions (default: a pinhole camera "
                             "from each frame's WCS); the detector keywords of the headers still apply")
    parser.add_argument("--camera-covariance", action="store_true",
                        help="add the --camera file's calibration covariance to each moon record's, as it moves the "
                             "moon relative to the frame's stars (docs/formats/camera.md; default: the camera is exact)")
    parser.add_argument("--camera-error", choices=("white", "consider"), default="white",
                        help="with --camera-covariance: white adds the camera's share to each moon record's "
                             "covariance (independent at every record); consider writes each record's Jacobian by "
                             "the camera's parameters instead (CSV columns camera_parameters, camera_jacobian), for "
                             "an EKF that holds the camera's one error over the arc ([navigation] camera_error = "
                             "'consider', docs/formats/navigation.md; default white)")
    parser.add_argument("--catalog", default=None, help="star catalog file (default: the packaged catalog)")
    parser.add_argument("--no-catalog", action="store_true", help="skip star identification; use the WCS attitude")
    parser.add_argument("--prior-sigma-deg", type=float, default=0.05, help="a-priori attitude error per axis, deg")
    parser.add_argument("--seed", type=int, default=0, help="random seed (star-ID hypotheses, RANSAC)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def choose_targets(frames_dir: str, asked: list[str] | None) -> tuple[tuple[str, ...], str]:
    """The bodies to measure and how they were chosen (for the summary line): ``asked`` (``--targets``),
    checked against the bodies the image stage knows, or the frames' own (module notes)."""
    from ..image.directory import frame_targets, known_bodies

    known = known_bodies()
    if asked is not None:
        names = tuple(dict.fromkeys(name.strip().lower() for name in asked))
        unknown = [name for name in names if name not in known]
        if unknown:
            raise InputError(f"--targets: unknown bod{'ies' if len(unknown) > 1 else 'y'} {', '.join(unknown)}; "
                             f"known: {', '.join(known)}")
        return names, "from --targets"
    found = frame_targets(frames_dir)
    chosen = found.default()
    if not chosen:
        if found.described:
            why = f"{found.source} name no body the image stage knows"
        else:
            why = "the frames have neither truth files (NAME.truth.json) nor an OBJECT keyword naming a body"
        raise InputError(f"{frames_dir}: --targets is needed: {why}; give some of {', '.join(known)}")
    left = [name for name in found.named if name not in chosen]
    note = f"named by {found.source}"
    if left:
        note += f"; {', '.join(left)} also, measured only with --targets"
    return chosen, note


def _check_camera_size(path, camera, name: str) -> None:
    """Refuse a camera file of another detector size than the frames (the first one's header), in one line."""
    from astropy.io import fits

    try:
        header = fits.getheader(path)
        cols, rows = int(header["NAXIS1"]), int(header["NAXIS2"])
    except (OSError, KeyError, ValueError, TypeError):
        return  # an unreadable frame is reported with the others, frame by frame
    if (rows, cols) != camera.shape:
        raise InputError(f"--camera {name} is {camera.width_px} x {camera.height_px} px; the frames ({path}) are "
                         f"{cols} x {rows} px")


def count_line(records, frames_used: int, frames_total: int) -> str:
    """``"58 records (33 radec_pair, 25 radec) from 60 of 60 frames"``: the records of the file by kind."""
    from collections import Counter

    kinds = Counter(record.kind for record in records).most_common()
    detail = f" ({', '.join(f'{n} {kind}' for kind, n in kinds)})" if kinds else ""
    return f"{len(records)} record{'s' if len(records) != 1 else ''}{detail} from {frames_used} of {frames_total} frames"


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ..camera import read_camera_file
    from ..image.directory import process_folder
    from ..image.pipeline import PipelineOptions, frame_paths
    from ..records import read_csv

    if not args.prior_sigma_deg > 0:
        raise InputError(f"--prior-sigma-deg must be positive, got {args.prior_sigma_deg}")
    camera_file = read_camera_file(args.camera) if args.camera else None
    camera = camera_file.camera if camera_file else None
    if args.camera_error != "white" and not args.camera_covariance:
        raise InputError(f"--camera-error {args.camera_error} needs --camera-covariance (and --camera with a "
                         "[calibration] table)")
    if args.camera_covariance and (camera_file is None or camera_file.calibration is None):
        raise InputError("--camera-covariance needs --camera with a [calibration] table (docs/formats/camera.md; "
                         "opnav calibrate writes one)" + (f": {args.camera} has none" if args.camera else ""))
    paths = frame_paths(args.frames_dir)
    total = len(paths)
    if camera is not None:
        _check_camera_size(paths[0], camera, args.camera)
    targets, how = choose_targets(args.frames_dir, args.targets)
    options = PipelineOptions(targets=targets, prior_sigma_rad=math.radians(args.prior_sigma_deg))
    results = process_folder(args.frames_dir, args.out, identify_stars=not args.no_catalog, catalog=args.catalog,
                             camera=camera, options=options, rng=args.seed, progress=not args.no_progress,
                             camera_covariance=camera_file.calibration if args.camera_covariance else None,
                             camera_error=args.camera_error)
    records = read_csv(args.out)  # what the file holds: the count printed is the file's
    metadata = Path(args.out).with_suffix(".json")
    skipped = total - len(results)
    if not records:
        if not results and total:
            # every frame refused (a header that lies or lacks the WCS): the first reason is the line to read
            import json

            first = next(iter(json.loads(metadata.read_text()).get("skipped", {}).values()), "")
            raise OpnavError(f"no records: every one of the {total} frames of {args.frames_dir} was skipped; the "
                             f"first: {first} (all reasons in {metadata})")
        missed = sum(1 for result in results if any(flag.startswith("no_") for flag in result.flags))
        raise OpnavError(f"no records: none of the {total} frames of {args.frames_dir} gave a measurement of "
                         f"{', '.join(targets)} ({skipped} skipped, {missed} without the target); the reasons and "
                         f"frame flags are in {metadata}")
    print(f"{count_line(records, len(results), total)} in {args.out}; targets {', '.join(targets)} ({how})"
          + (f"; {skipped} frames skipped, reasons in {metadata}" if skipped else ""))
    return 0
