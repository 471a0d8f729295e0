"""``opnav centroid``: detect and centroid the point sources of one frame.

Example::

    opnav centroid frame.fits --json

prints ``{"sources": [{"x", "y", "flux", "snr", "sigma_x", "sigma_y", "flags"}, ...]}``, brightest
first (x = column, y = row, px, (0, 0) the centre of the first pixel; flux in ADU; sigmas from the
fit covariance). Sources whose fit failed are left out; ``flags`` is the detection bit mask
(:mod:`opnav.image.detect`). FITS frames with the opnav header supply gain, read noise and bias;
other formats are fitted with the noise estimated from the frame.
"""

from __future__ import annotations

import argparse
import json
import math

from ..errors import InputError

NAME = "centroid"
HELP = "detect and centroid the point sources of a frame (FITS, PNG, TIFF, JPEG)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..image.centroid import METHODS

    parser.add_argument("frame", help="image file: FITS, PNG, TIFF (8/16 bit) or JPEG, mono or RGB")
    parser.add_argument("--method", choices=METHODS, default="gauss", help="centroid estimator (default gauss)")
    parser.add_argument("--window", type=int, default=7, help="odd stamp side, px (default 7)")
    parser.add_argument("--threshold", type=float, default=5.0, help="detection threshold, sigma (default 5)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


def _header_number(header, key: str, frame: str) -> float | None:
    """FITS header ``key`` as a finite number (None when absent); other values name the keyword."""
    if key not in header:
        return None
    value = header[key]
    try:
        if isinstance(value, bool):
            raise ValueError
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{frame}: FITS keyword {key} must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise InputError(f"{frame}: FITS keyword {key} must be finite, got {value!r}")
    return number


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..image.centroid import centroid
    from ..image.detect import DetectOptions, detect
    from ..image.io import read_image

    image, meta = read_image(args.frame)
    det = detect(image, options=DetectOptions(threshold_sigma=args.threshold), saturation_adu=meta.saturation_adu,
                 invalid=meta.invalid, lossy=meta.lossy)
    header = meta.header if meta.header is not None else {}
    read_noise = _header_number(header, "RDNOISE", args.frame)
    gain = _header_number(header, "GAIN", args.frame)
    bias = _header_number(header, "BIASLVL", args.frame)
    invalid = det.rejected if meta.invalid is None else det.rejected | meta.invalid
    res = centroid(
        image, det.xy, method=args.method, window=args.window, read_noise_e=read_noise,
        gain_e_per_adu=gain, bias_adu=0.0 if bias is None else bias,
        saturation_adu=meta.saturation_adu, invalid=invalid,
    )
    sources = [
        {
            "x": float(res.xy[i, 0]), "y": float(res.xy[i, 1]), "flux": float(res.flux[i]), "snr": float(res.snr[i]),
            "sigma_x": float(np.sqrt(res.cov[i, 0, 0])), "sigma_y": float(np.sqrt(res.cov[i, 1, 1])),
            "flags": int(det.flags[i]),
        }
        for i in np.flatnonzero(res.ok)
    ]
    if args.json:
        print(json.dumps({"frame": str(args.frame), "sources": sources, "rejected_hits": det.n_rejected}))
    else:
        print(f"{'x':>10} {'y':>10} {'flux':>12} {'snr':>8} {'sigma_x':>8} {'sigma_y':>8} flags")
        for s in sources:
            print(f"{s['x']:10.4f} {s['y']:10.4f} {s['flux']:12.1f} {s['snr']:8.1f} {s['sigma_x']:8.4f} {s['sigma_y']:8.4f} {s['flags']}")
        print(f"{len(sources)} sources; {det.n_rejected} hot-pixel/cosmic-ray hits rejected")
    return 0
