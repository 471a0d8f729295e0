"""CCSDS Orbit Ephemeris Messages (OEM) and Tracking Data Messages (TDM), through ccsds-ndm.

Modules: :mod:`~opnav.ccsds.oem` (OEM), :mod:`~opnav.ccsds.tdm` (TDM),
:mod:`~opnav.ccsds.sidecar` (the TDM's covariance sidecar), :mod:`~opnav.ccsds.common` (reading
and writing messages, epochs, value checks); their public functions are imported here.

Messages are read by the ``ccsds-ndm`` package (its xsdata object models, its KVN
parser) and written by it (its KVN writer and XML serializer), except the KVN data
lines, which opnav formats in that writer's layout (:func:`opnav.ccsds.common.write_kvn`) and,
for a TDM, reads (``KEYWORD = EPOCH VALUE``; ccsds-ndm takes about 1 ms a line);
the TDM's covariance sidecar is plain CSV. The format follows the file name: a name ending in
``.xml`` is NDM/XML, anything else (``.oem``, ``.tdm``, ``.kvn``, ``.txt``) is KVN.
Files are written atomically (temporary file in the same folder, then rename).

OEM (CCSDS 502.0-B-2, ``CCSDS_OEM_VERS = 2.0``, NDM/XML schema 2.0.0)
    One segment. ``TIME_SYSTEM = TDB``; epochs are ISO calendar dates in TDB
    with microseconds. States are ``X Y Z`` in km and ``X_DOT Y_DOT Z_DOT`` in
    km/s, in ``REF_FRAME`` (default ICRF) with origin ``CENTER_NAME`` (default
    MARS), each number written with Python's shortest round-trip repr (17
    significant digits at most), so a read gives back the same doubles.
    Covariances, when given, are OEM covariance blocks (lower triangle, km**2,
    km**2/s, km**2/s**2) with an ``EPOCH`` each and ``COV_REF_FRAME`` equal to
    ``REF_FRAME``. ``OBJECT_NAME``/``OBJECT_ID`` name the spacecraft (a run's
    :attr:`opnav.studies.settings.RunFile.spacecraft`); ``INTERPOLATION = HERMITE``
    with ``INTERPOLATION_DEGREE = 3`` (:data:`OEM_INTERPOLATION`). OEM 2.0 rather
    than 3.0 because every OEM reader in use accepts 2.0; :func:`read_oem` reads both.

TDM (CCSDS 503.0-B-2, ``CCSDS_TDM_VERS = 2.0``, NDM/XML schema 4.0.0)
    ``radec`` and ``radec_pair`` records (:mod:`opnav.records`): the right
    ascension and declination of a target as seen from the spacecraft, ICRF.
    Keywords: ``ANGLE_TYPE = RADEC``, ``REFERENCE_FRAME = ICRF`` (allowed by TDM
    2.0), ``TIME_SYSTEM = TDB``, ``MODE = SEQUENTIAL``, ``PATH = 2,1`` with
    ``PARTICIPANT_1`` = the spacecraft (the observer, where the light is
    received) and ``PARTICIPANT_2`` = the target in upper case (where it comes
    from): in a TDM the path lists participants in the order the signal
    travels, as in the standard's own optical example (E-16). ``ANGLE_1`` is the
    right ascension in degrees in [0, 360), ``ANGLE_2`` the declination in
    degrees; they share an epoch, one pair per direction. One segment per
    (sensor, target); a ``radec_pair`` (two moons in one frame) gives one
    direction to each of its targets' segments, at the same epoch. KVN files
    have no blank line between ``META_STOP`` and ``DATA_START`` (``ccsds-ndm-py``
    refuses one there).

    TDM 2.0 has no keyword for an observation's uncertainty (``DATA_QUALITY`` is
    RAW/VALIDATED/DEGRADED, ``CORRECTION_ANGLE_n`` a bias applied or to apply), so
    the noise goes where the standard leaves room, in ``COMMENT`` lines of the
    segment metadata, which :func:`read_tdm` reads back exactly::

        COMMENT opnav target = phobos
        COMMENT opnav sensor = nac
        COMMENT opnav covariance_rad2 = 1e-10 0.0 0.0 2.5e-10

    (the 2x2 covariance of [ra, dec], row-major, rad**2, each number a Python
    repr; written when every record of the segment has that covariance, as in
    measurement mode). Nothing in a TDM ties two directions together, so every
    record's covariance is also written to a sidecar CSV beside the TDM,
    ``<tdm name>.cov.csv`` (:func:`tdm_sidecar`), one row per record in the
    records' order: ``epoch_tdb`` (the epoch text of its observations),
    ``t_tdb_s`` (exact), ``sensor``, ``target`` (``phobos+deimos`` for a pair),
    ``frame_id``, ``flags`` and ``covariance_rad2`` (row-major; 4x4 for a pair,
    [ra_1, dec_1, ra_2, dec_2], with the moon-moon cross-covariance their shared
    attitude error gives). :func:`read_tdm` reads the sidecar when it is there:
    the records come back as written, pairs included; a sidecar whose rows and
    the TDM's observations do not match one to one is refused.

Inside opnav time is TDB seconds past J2000 (2000-01-01T12:00:00 TDB, see
:mod:`opnav.epochs`), angles are radians, positions km, velocities km/s.
"""

from .oem import OEM_INTERPOLATION, OemData, read_oem, write_estimates_oem, write_oem
from .sidecar import SIDECAR_SUFFIX, tdm_sidecar
from .tdm import read_tdm, tdm_ready, write_tdm

__all__ = ["OEM_INTERPOLATION", "OemData", "SIDECAR_SUFFIX", "read_oem", "read_tdm", "tdm_ready", "tdm_sidecar",
           "write_estimates_oem", "write_oem", "write_tdm"]
