"""A folder of frames -> one measurement file, with the star catalog and ephemeris chosen for the caller.

:func:`process_folder` is :func:`opnav.image.pipeline.process_directory` (every FITS frame with
the opnav header through the image stage, the records written as CSV plus a ``.json`` metadata
file) with its defaults filled in: the packaged star catalog (or ``$OPNAV_CATALOG``,
:func:`opnav.catalog.load_catalog`) unless star identification is turned off or another catalog
is given, and the default ephemeris (:func:`opnav.ephemeris.default_ephemeris`) when targets are
measured. It is what ``opnav process`` calls.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .pipeline import FrameResult, PipelineOptions, process_directory


def process_folder(
    frames_dir: str | Path,
    out_csv: str | Path,
    *,
    identify_stars: bool = True,
    catalog=None,
    ephemeris=None,
    camera=None,
    options: PipelineOptions = PipelineOptions(),
    rng: np.random.Generator | int | None = None,
    progress: bool = False,
) -> list[FrameResult]:
    """Process every frame of ``frames_dir`` and write all records to ``out_csv`` (+ ``.json``).

    Parameters
    ----------
    frames_dir : str or Path
        Folder of FITS frames with the opnav header (``opnav render``).
    out_csv : str or Path
        Records file (:func:`opnav.records.write_csv`); frames that could not be used are listed
        in its metadata under ``skipped``.
    identify_stars : bool
        Identify the stars around each frame's WCS attitude; False uses the WCS attitude as it is
        (with ``options.prior_sigma_rad`` per axis) and loads no catalog.
    catalog : StarCatalog, str or Path, optional
        The catalog, or its file; default :func:`opnav.catalog.load_catalog` (the packaged
        catalog or ``$OPNAV_CATALOG``). Ignored when ``identify_stars`` is False.
    ephemeris : Ephemeris, optional
        Default :func:`opnav.ephemeris.default_ephemeris` when ``options.targets`` names any
        body, else none.
    camera : Camera, optional
        Default: the camera each frame's header describes.
    options : PipelineOptions
        Targets, sensor name and the image stage's settings.
    rng : numpy Generator, int or None
        Star-ID hypotheses and RANSAC draws.
    progress : bool
        Show a progress bar (tqdm, on stderr), one tick per frame; off by default.

    Returns
    -------
    list of FrameResult
        One per frame used, in file-name order.

    Raises
    ------
    CatalogError
        A catalog file that is missing or unreadable.
    """
    if not identify_stars:
        catalog = None
    elif catalog is None or isinstance(catalog, (str, os.PathLike)):
        from ..catalog import load_catalog

        catalog = load_catalog(catalog)
    if ephemeris is None and options.targets:
        from ..ephemeris import default_ephemeris

        ephemeris = default_ephemeris()
    return process_directory(frames_dir, out_csv, camera=camera, catalog=catalog, ephemeris=ephemeris,
                             options=options, rng=rng, progress=progress)
