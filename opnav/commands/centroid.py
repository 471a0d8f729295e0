"""``opnav centroid``: detect and centroid the point sources of one frame.

Example::

    opnav centroid frame.fits --json

prints ``{"sources": [{"x", "y", "flux", "snr", "sigma_x", "sigma_y", "flags"}, ...]}``, brightest
first (x = column, y = row, px, (0, 0) the centre of the first pixel; flux in ADU; sigmas from the
fit covariance). Sources whose fit failed are left out; ``flags`` is the detection bit mask
(:mod:`opnav.image.detect`). FITS frames with the opnav header supply gain, read noise and bias;
other formats are fitted with the noise estimated from the frame. The work is
:func:`opnav.image.sources.frame_sources`; this module parses arguments and prints.
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
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


def run(args: argparse.Namespace) -> int:
    from ..image.sources import frame_sources

    found = frame_sources(args.frame, method=args.method, window=args.window, threshold_sigma=args.threshold)
    sources = found.rows()
    rejected = found.detections.n_rejected
    if args.json:
        print(json.dumps({"frame": str(args.frame), "sources": sources, "rejected_hits": rejected}))
    else:
        print(f"{'x':>10} {'y':>10} {'flux':>12} {'snr':>8} {'sigma_x':>8} {'sigma_y':>8} flags")
        for s in sources:
            print(f"{s['x']:10.4f} {s['y']:10.4f} {s['flux']:12.1f} {s['snr']:8.1f} {s['sigma_x']:8.4f} {s['sigma_y']:8.4f} {s['flags']}")
        print(f"{len(sources)} sources; {rejected} hot-pixel/cosmic-ray hits rejected")
    return 0
