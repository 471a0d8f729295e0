"""A folder of frames -> one measurement file, with the star catalog and ephemeris chosen for the caller.

:func:`process_folder` is :func:`opnav.image.pipeline.process_directory` (every FITS frame with
the opnav header through the image stage, the records written as CSV plus a ``.json`` metadata
file) with its defaults filled in: the packaged star catalog (or ``$OPNAV_CATALOG``,
:func:`opnav.catalog.load_catalog`) unless star identification is turned off or another catalog
is given, and the default ephemeris (:func:`opnav.ephemeris.default_ephemeris`) when targets are
measured. It is what ``opnav process`` calls.

:func:`frame_targets` says which bodies a folder's frames show, from their truth sidecars
(``NAME.truth.json``, :mod:`opnav.render.frames_io`) or, for frames without one, the FITS
``OBJECT`` keyword; :meth:`FrameTargets.default` is what ``opnav process`` measures when no
``--targets`` are given: the point-like bodies the frames show (the moons, measured as RA/Dec), or
the resolved ones (:data:`opnav.image.pipeline.RESOLVED_BODIES`, measured by their limb) when the
frames show no point-like body. A resolved body beside point-like ones is their primary, in the
frame for its glare; its limb, cut by the terminator (the demo's Mars at 42 degrees of phase),
gives directions several arcseconds off, so it is measured only when asked for.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from .pipeline import RESOLVED_BODIES, FrameResult, PipelineOptions, frame_paths, process_directory


@dataclass(frozen=True)
class FrameTargets:
    """The bodies a folder of frames shows (:func:`frame_targets`).

    Attributes
    ----------
    named : tuple of str
        Every known body (:data:`opnav.bodies.BODIES`) a frame's truth sidecar or ``OBJECT`` keyword
        names, sorted.
    frames : int
        FITS frames in the folder.
    described : int
        Frames whose sidecar or ``OBJECT`` keyword could be read.
    source : str
        Where the names came from: ``"the frames' truth files"``, ``"the frames' OBJECT keyword"``,
        both, or ``""``.
    """

    named: tuple[str, ...]
    frames: int
    described: int
    source: str

    @property
    def point(self) -> tuple[str, ...]:
        """The named bodies the image stage measures as point sources (RA/Dec)."""
        return tuple(name for name in self.named if name not in RESOLVED_BODIES)

    @property
    def resolved(self) -> tuple[str, ...]:
        """The named bodies the image stage measures by their limb (line of sight, starlight)."""
        return tuple(name for name in self.named if name in RESOLVED_BODIES)

    def default(self) -> tuple[str, ...]:
        """The bodies to measure when none are asked for: the point-like ones, else the resolved ones
        (module notes); empty when the frames name none."""
        return self.point or self.resolved


def known_bodies() -> tuple[str, ...]:
    """The bodies the image stage can measure (:data:`opnav.bodies.BODIES`), sorted."""
    from ..bodies import BODIES

    return tuple(sorted(BODIES))


def frame_targets(frames_dir: str | Path) -> FrameTargets:
    """The bodies the frames of ``frames_dir`` show: the ``targets`` of each frame's truth sidecar
    (``NAME.truth.json``), or the ``OBJECT`` keyword of a frame without one (a body name, or several
    separated by commas or spaces), keeping the names of :func:`known_bodies`. A sidecar or header that
    cannot be read is passed over (it is not needed to measure the frame).

    Raises
    ------
    InputError
        When ``frames_dir`` is not a folder or holds no FITS frame (:func:`opnav.image.pipeline.frame_paths`).
    """
    known = set(known_bodies())
    names: set[str] = set()
    described, sources = 0, set()
    paths = frame_paths(frames_dir)
    for path in paths:
        found = _sidecar_names(path)
        if found is not None:
            sources.add("the frames' truth files")
        else:
            found = _object_names(path)
            if found is not None:
                sources.add("the frames' OBJECT keyword")
        if found is not None:
            described += 1
            names |= {name for name in found if name in known}
    return FrameTargets(tuple(sorted(names)), len(paths), described, " and ".join(sorted(sources)))


def _sidecar_names(path: Path) -> list[str] | None:
    """The target names of frame ``path``'s truth sidecar, or None without a readable one."""
    stem = path.name
    for suffix in (".fits", ".fit", ".fts"):
        if stem.lower().endswith(suffix):
            stem = stem[: -len(suffix)]
    try:
        data = json.loads(path.with_name(stem + ".truth.json").read_text(encoding="utf-8"))
        return [str(t["name"]).strip().lower() for t in data["targets"]]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _object_names(path: Path) -> list[str] | None:
    """The body names of frame ``path``'s FITS ``OBJECT`` keyword, or None without one."""
    from astropy.io import fits

    try:
        value = fits.getheader(path).get("OBJECT")
    except (OSError, ValueError, IndexError, KeyError):
        return None
    if not isinstance(value, str) or not value.strip():
        return None
    return [word.strip().lower() for word in value.replace(",", " ").split() if word.strip()]


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
    camera_covariance=None,
    camera_error: str = "white",
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
    camera_covariance : opnav.camera.CameraCovariance, optional
        The camera file's calibration covariance, added to each moon record's as it moves the moon
        relative to the frame's stars, or kept as Jacobians (``camera_error = "consider"``)
        (:func:`opnav.image.pipeline.process_frame`). Needs ``identify_stars``.
    camera_error : str
        ``"white"`` or ``"consider"`` (:func:`opnav.image.camera_noise.check_camera_error`).

    Returns
    -------
    list of FrameResult
        One per frame used, in file-name order.

    Raises
    ------
    CatalogError
        A catalog file that is missing or unreadable.
    InputError
        ``camera_covariance`` without ``identify_stars``, or an unknown ``camera_error``.
    """
    from .camera_noise import check_camera_error

    check_camera_error(camera_error)
    if camera_covariance is not None and not identify_stars:
        raise InputError("the camera's covariance is added relative to the frame's identified stars: it needs star "
                         "identification (not --no-catalog)")
    if not identify_stars:
        catalog = None
    elif catalog is None or isinstance(catalog, (str, os.PathLike)):
        from ..catalog import load_catalog

        catalog = load_catalog(catalog)
    if ephemeris is None and options.targets:
        from ..ephemeris import default_ephemeris

        ephemeris = default_ephemeris()
    return process_directory(frames_dir, out_csv, camera=camera, catalog=catalog, ephemeris=ephemeris,
                             options=options, rng=rng, progress=progress, camera_covariance=camera_covariance,
                             camera_error=camera_error)
