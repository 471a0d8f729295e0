"""Image stage: read frames, detect and centroid sources, measure targets, produce measurements.

Modules, in data-flow order (each usable alone; conventions in docs/conventions.md):

- :mod:`opnav.image.io` — :func:`read_image` for FITS, PNG, TIFF and JPEG.
- :mod:`opnav.image.detect` — background, threshold, components, rejection, de-blending.
- :mod:`opnav.image.centroid` — centre of gravity, weighted centroid, batched Gaussian fit, CRB.
- :mod:`opnav.image.starid`, :mod:`opnav.image.attitude` — star identification and attitude.
- :mod:`opnav.image.targets` — moon phase correction, limb fits, starlight angles.
- :mod:`opnav.image.pipeline` — frame -> :class:`opnav.records.Measurement` records.

Nothing is re-exported here: the functions ``centroid`` and ``detect`` share their
modules' names, and binding them on the package would hide the modules from
``import opnav.image.centroid``. Import from the modules.
"""
