"""``opnav centroid``: detect and centroid the point sources of one frame.

Example::

    opnav centroid frame.fits --json

prints ``{"sources": [{"x", "y", "flux", "snr", "sigma_x", "sigma_y", "flags"}, ...]}``, brightest
first (x = column, y = row, px, (0, 0) the centre of the first pixel; flux in ADU; sigmas from the
fit covariance). Sources whose fit failed are left out; ``flags`` is the detection bit mask
(:mod:`opnav.image.detect`). FITS frames with the opnav header supply gain, read noise and bias;
other formats are fitted with the noise estimated from the frame. The work is
:func:`opnav.image.sources.frame_sources`; this module parses arguments and prints.

With ``--camera camera.toml`` (a camera file, docs/formats/camera.md, e.g. from ``opnav calibrate``)
each source also gets its unit direction in the camera frame through that camera's focal length,
principal point and distortion (``"direction_cam"``: +z the boresight, +x along increasing column,
+y along increasing row; docs/conventions.md); the frame must have the camera's size.
"""

from __future__ import annotations

import argparse
import json

NAME = "centroid"
HELP = "detect and centroid the point sources of a frame (FITS, PNG, TIFF, JPEG)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..image.centroid import METHODS

    parser.add_argument("frame", help="image file: FITS, PNG, TIFF (8/16 bit) or JPEG, mono or RGB")
    parser.add_argument("--method", choices=METHODS, default="gauss", help="centroid estimator (default gauss)")
    parser.add_argument("--window", type=int, default=7, help="odd stamp side, px (default 7)")
    parser.add_argument("--threshold", type=float, default=5.0, help="detection threshold, sigma (default 5)")
    parser.add_argument("--camera", default=None, metavar="CAMERA.toml",
                        help="camera file: add each source's unit direction in the camera frame, distortion removed")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


def run(args: argparse.Namespace) -> int:
    from ..image.sources import frame_sources

    camera = None
    if args.camera is not None:
        from ..camera import read_camera_file

        camera = read_camera_file(args.camera).camera
    found = frame_sources(args.frame, method=args.method, window=args.window, threshold_sigma=args.threshold)
    if camera is not None and found.detections.labels.shape != camera.shape:
        from ..errors import InputError

        rows, cols = found.detections.labels.shape
        raise InputError(f"{args.frame} is {cols} x {rows} px; --camera {args.camera} is {camera.width_px} x "
                         f"{camera.height_px} px")
    sources = found.rows()
    if camera is not None:
        import numpy as np

        directions = camera.unproject(np.array([[s["x"], s["y"]] for s in sources]).reshape(-1, 2))
        for source, direction in zip(sources, directions):
            source["direction_cam"] = [float(c) for c in direction]
    rejected = found.detections.n_rejected
    if args.json:
        print(json.dumps({"frame": str(args.frame), "sources": sources, "rejected_hits": rejected}))
    else:
        extra = f" {'x_cam':>11} {'y_cam':>11} {'z_cam':>11}" if camera is not None else ""
        print(f"{'x':>10} {'y':>10} {'flux':>12} {'snr':>8} {'sigma_x':>8} {'sigma_y':>8} flags{extra}")
        for s in sources:
            cam = "".join(f" {c:11.8f}" for c in s["direction_cam"]) if camera is not None else ""
            print(f"{s['x']:10.4f} {s['y']:10.4f} {s['flux']:12.1f} {s['snr']:8.1f} {s['sigma_x']:8.4f} {s['sigma_y']:8.4f} "
                  f"{s['flags']:5d}{cam}")
        print(f"{len(sources)} sources; {rejected} hot-pixel/cosmic-ray hits rejected")
    return 0
