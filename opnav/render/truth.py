"""Truth records of a rendered frame, and their JSON form (the sidecar file).

Units in memory are internal (rad, km, km/s, s TDB past J2000, px); the JSON
names each unit in its key (``ra_deg``, ``range_km``). Quaternions are
scalar-last ``[x, y, z, w]``, camera -> ICRF (docs/conventions.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import FrameError

TRUTH_FORMAT = "opnav-truth-1"


@dataclass(frozen=True)
class StarTruth:
    """Every rendered star: ``star_id`` (N,), ``xy_px`` (N, 2) true mid-exposure pixel
    position, ``electrons`` (N,) expected photo-electrons in the exposure, ``vmag`` (N,),
    ``direction_icrf`` (N, 3) apparent unit vectors."""

    star_id: np.ndarray
    xy_px: np.ndarray
    electrons: np.ndarray
    vmag: np.ndarray
    direction_icrf: np.ndarray

    def __len__(self) -> int:
        return int(self.star_id.size)


@dataclass(frozen=True)
class TargetTruth:
    """One extended or point-like target.

    ``xy_cof_px``: centre of figure; ``xy_photocentre_px``: flux-weighted centre of
    the lit body; ``ra_rad``/``dec_rad``: apparent direction of the centre of figure
    (light time + aberration); ``range_km``: light-time-corrected range;
    ``phase_angle_rad``: Sun-target-observer angle; ``vmag``: apparent V magnitude
    (None for the UV Earth disk); ``electrons``: expected photo-electrons in the exposure;
    ``angular_radius_rad``: of the largest semi-axis; ``resolved``: drawn by ray casting
    (True) or as a PSF at the photocentre (False).
    """

    name: str
    xy_cof_px: np.ndarray
    xy_photocentre_px: np.ndarray
    ra_rad: float
    dec_rad: float
    range_km: float
    phase_angle_rad: float
    vmag: float | None
    electrons: float
    angular_radius_rad: float
    resolved: bool


@dataclass(frozen=True)
class FrameTruth:
    """Everything true about one frame.

    ``R_icrf_cam`` is the mid-exposure attitude; ``r_observer_ssb_km``/``v_observer_ssb_km_s``
    the observer's SSB state (ICRF); ``flags`` names conditions such as ``"sun_keepout"``.
    """

    t_tdb_s: float
    exposure_s: float
    camera_id: str
    R_icrf_cam: Rotation
    r_observer_ssb_km: np.ndarray
    v_observer_ssb_km_s: np.ndarray
    omega_cam_rad_s: np.ndarray
    stars: StarTruth
    targets: tuple[TargetTruth, ...]
    flags: tuple[str, ...] = ()

    def target(self, name: str) -> TargetTruth:
        """The target called ``name``; raise ``FrameError`` when absent."""
        for item in self.targets:
            if item.name == name:
                return item
        raise FrameError(f"frame has no target {name!r}; targets: {[t.name for t in self.targets]}")


def _xy(value: np.ndarray) -> list[float]:
    return [float(v) for v in value]


def _pixel(value: float) -> float | None:
    """A pixel coordinate for JSON: ``None`` (``null``) where it is undefined (NaN: a target behind the camera
    has no pixel), as JSON has no NaN."""
    value = float(value)
    return value if math.isfinite(value) else None


def _pixel_back(value) -> float:
    """Inverse of :func:`_pixel`: ``null`` -> NaN."""
    return math.nan if value is None else float(value)


def truth_to_json(truth: FrameTruth) -> dict:
    """JSON-ready dict of ``truth`` (units in the keys)."""
    stars = truth.stars
    return {
        "format": TRUTH_FORMAT,
        "t_tdb_s": truth.t_tdb_s,
        "exposure_s": truth.exposure_s,
        "camera_id": truth.camera_id,
        "quaternion_cam_to_icrf_xyzw": _xy(truth.R_icrf_cam.as_quat()),
        "r_observer_ssb_km": _xy(truth.r_observer_ssb_km),
        "v_observer_ssb_km_s": _xy(truth.v_observer_ssb_km_s),
        "omega_cam_rad_s": _xy(truth.omega_cam_rad_s),
        "flags": list(truth.flags),
        "stars": [
            {
                "star_id": int(sid),
                "x_px": float(xy[0]),
                "y_px": float(xy[1]),
                "electrons": float(e),
                "vmag": float(m),
                "direction_icrf": _xy(d),
            }
            for sid, xy, e, m, d in zip(stars.star_id, stars.xy_px, stars.electrons, stars.vmag, stars.direction_icrf)
        ],
        "targets": [
            {
                "name": t.name,
                "x_cof_px": _pixel(t.xy_cof_px[0]),
                "y_cof_px": _pixel(t.xy_cof_px[1]),
                "x_photocentre_px": _pixel(t.xy_photocentre_px[0]),
                "y_photocentre_px": _pixel(t.xy_photocentre_px[1]),
                "ra_deg": math.degrees(t.ra_rad),
                "dec_deg": math.degrees(t.dec_rad),
                "range_km": t.range_km,
                "phase_angle_deg": math.degrees(t.phase_angle_rad),
                "vmag": t.vmag,
                "electrons": t.electrons,
                "angular_radius_deg": math.degrees(t.angular_radius_rad),
                "resolved": t.resolved,
            }
            for t in truth.targets
        ],
    }


def truth_from_json(data: dict, *, source: str = "truth JSON") -> FrameTruth:
    """Inverse of :func:`truth_to_json`; ``FrameError`` naming ``source`` on a malformed record."""
    try:
        if data.get("format") != TRUTH_FORMAT:
            raise FrameError(f"{source}: not an opnav truth record (format {data.get('format')!r})")
        stars = data["stars"]
        star_truth = StarTruth(
            star_id=np.array([s["star_id"] for s in stars], dtype=np.int64),
            xy_px=np.array([[s["x_px"], s["y_px"]] for s in stars], dtype=float).reshape(-1, 2),
            electrons=np.array([s["electrons"] for s in stars], dtype=float),
            vmag=np.array([s["vmag"] for s in stars], dtype=float),
            direction_icrf=np.array([s["direction_icrf"] for s in stars], dtype=float).reshape(-1, 3),
        )
        targets = tuple(
            TargetTruth(
                name=t["name"],
                xy_cof_px=np.array([_pixel_back(t["x_cof_px"]), _pixel_back(t["y_cof_px"])]),
                xy_photocentre_px=np.array([_pixel_back(t["x_photocentre_px"]), _pixel_back(t["y_photocentre_px"])]),
                ra_rad=math.radians(t["ra_deg"]),
                dec_rad=math.radians(t["dec_deg"]),
                range_km=float(t["range_km"]),
                phase_angle_rad=math.radians(t["phase_angle_deg"]),
                vmag=None if t["vmag"] is None else float(t["vmag"]),
                electrons=float(t["electrons"]),
                angular_radius_rad=math.radians(t["angular_radius_deg"]),
                resolved=bool(t["resolved"]),
            )
            for t in data["targets"]
        )
        return FrameTruth(
            t_tdb_s=float(data["t_tdb_s"]),
            exposure_s=float(data["exposure_s"]),
            camera_id=str(data["camera_id"]),
            R_icrf_cam=Rotation.from_quat(data["quaternion_cam_to_icrf_xyzw"]),
            r_observer_ssb_km=np.array(data["r_observer_ssb_km"], dtype=float),
            v_observer_ssb_km_s=np.array(data["v_observer_ssb_km_s"], dtype=float),
            omega_cam_rad_s=np.array(data["omega_cam_rad_s"], dtype=float),
            stars=star_truth,
            targets=targets,
            flags=tuple(data["flags"]),
        )
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, FrameError):
            raise
        raise FrameError(f"{source}: malformed truth record ({type(exc).__name__}: {exc})") from None
