"""Image stage: read frames, detect and centroid sources, identify stars, measure targets.

The public names are exported here (``opnav.image.__all__``), lazily: importing
``opnav.image`` loads nothing until a name is used. In data-flow order
(conventions in docs/conventions.md):

- reading: :func:`read_image` (FITS, PNG, TIFF, JPEG, raw Bayer mosaics) and its
  :class:`ImageMeta`;
- sources: :class:`DetectOptions`, :class:`Detections`, :class:`CentroidResult`,
  :func:`extract_stars` (detection and centroids in one call, for star identification),
  :func:`frame_sources` -> :class:`FrameSources` (a frame's sources as ``opnav centroid`` lists them);
- stars and attitude: :func:`solve_image` and :func:`solve_stars` (lost in space),
  :func:`track` (around a prior attitude), :class:`PlateSolution`,
  :class:`Identification`, :func:`wahba`, :class:`AttitudeSolution`, the pattern
  index (:func:`load_or_build_index`, :class:`IndexOptions`, :class:`PatternIndex`);
- targets: :func:`moon_direction`, :func:`fit_limb`, :func:`starlight_measurements`;
- frames -> measurement records: :func:`process_frame` (a FITS frame with the opnav
  header), :func:`frame_input` + :func:`measure_frame` (a frame in memory),
  :func:`process_directory` (:func:`process_folder`: the same with the default catalog and
  ephemeris), with :class:`PipelineOptions`, :class:`FrameInput`,
  :class:`FrameResult`; :class:`Tracker` and :class:`TrackingOptions` for the
  tracking stage that reads windows around predictions.

The functions ``detect`` and ``centroid`` are not exported: they share their
modules' names, and a package attribute of that name would be replaced by the
module as soon as anything imports ``opnav.image.detect``. Import them from
their modules (``from opnav.image.detect import detect``).
"""

from .. import lazy_exports

#: The public names of ``opnav.image``, by the module that defines each (edit here when a module moves).
_EXPORTS: dict[str, tuple[str, ...]] = {
    "opnav.image.io": ("ImageMeta", "read_image"),
    "opnav.image.detect": ("DetectOptions", "Detections"),
    "opnav.image.centroid": ("CentroidResult",),
    "opnav.image.extract": ("extract_stars",),
    "opnav.image.sources": ("FrameSources", "frame_sources"),
    "opnav.image.starid": ("Identification", "PlateSolution", "solve_image", "solve_stars", "track"),
    "opnav.image.starid_index": ("IndexOptions", "PatternIndex", "load_or_build_index"),
    "opnav.image.attitude": ("AttitudeSolution", "wahba"),
    "opnav.image.targets": ("fit_limb", "moon_direction", "starlight_measurements"),
    "opnav.image.pipeline": (
        "FrameInput", "FrameResult", "PipelineOptions", "frame_input", "measure_frame", "process_directory",
        "process_frame",
    ),
    "opnav.image.directory": ("process_folder",),
    "opnav.image.tracking": ("Tracker", "TrackingOptions"),
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
