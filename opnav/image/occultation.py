"""Bodies in front of bodies: which centre measurements a frame cannot give, and why.

A centre fit assumes its body's light alone in the pixels it reads. Two bodies whose outlines
overlap on the detector (Phobos across Mars, the Moon in front of the Earth) or come within a
margin of each other (a moon in its primary's glare: the PSF's reach, a bright body's halo) break
that assumption for both: the nearer one hides part of the farther one's limb, and the farther
one's light is the background of the nearer one's model. :func:`conflicts` predicts this from the
bodies' predicted poses, before anything is fitted, so the affected measurements are skipped with
a reason instead of fitted to the wrong body.

Geometry: each outline is the exact horizon conic of the body's ellipsoid
(:func:`opnav.image.ellipsoid.horizon_cone`); body B hides part of body A when a point of A's
outline lies inside B's (``u^T C_B u > 0``) and B is the nearer; two outlines are "close" when
their sampled points come within ``margin_px`` of each other. :func:`frame_conflicts` does it for
a frame's bodies from the ephemeris (a UV-limb body's outline is its glowing disk, the solid body
plus ``limb_altitude_km``); the image stage (:func:`opnav.image.pipeline.target_records` with
``centre_finding="by_size"``) skips each affected body with these reasons as frame flags.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ..bodies import Body
from ..camera import Camera
from ..errors import InputError, NoSolutionError
from ..observer import Observer
from .centres import body_pose
from .ellipsoid import EllipsoidPose, horizon_cone, outline_points


@dataclass(frozen=True)
class Conflict:
    """Body ``name`` cannot be measured in this frame because of ``other``: ``reason`` is
    ``"occulted"`` (``other`` is nearer and covers part of it), ``"transit"`` (it is in front of
    ``other``: ``other``'s light is its background) or ``"glare"`` (the outlines come within the
    margin without touching)."""

    name: str
    other: str
    reason: str

    @property
    def flag(self) -> str:
        """The frame flag naming it, e.g. ``phobos_occulted_by_mars``."""
        joiner = {"occulted": "occulted_by", "transit": "transits", "glare": "in_glare_of"}[self.reason]
        return f"{self.name}_{joiner}_{self.other}"


def _inside(camera: Camera, pose: EllipsoidPose, xy: np.ndarray) -> np.ndarray:
    """Which detector points (N, 2) lie inside ``pose``'s outline."""
    u = camera.unproject(xy)
    cone = horizon_cone(pose)
    # the cone's quadratic form is positive inside the outline, in front of the camera only
    return (np.einsum("ni,ij,nj->n", u, cone, u) > 0) & (u @ pose.r_cam_km > 0)


def conflicts(camera: Camera, poses: dict[str, EllipsoidPose], *, margin_px: float = 10.0) -> list[Conflict]:
    """Every pair of bodies whose outlines overlap or come within ``margin_px`` (module docstring).

    Parameters
    ----------
    camera : Camera
    poses : dict of str to EllipsoidPose
        Predicted poses of the frame's bodies (camera frame, km).
    margin_px : float
        Outlines closer than this are in each other's glare, px.

    Returns
    -------
    list of Conflict
        One per affected body and cause (both bodies of a pair are affected).
    """
    if not margin_px >= 0:
        raise InputError(f"margin_px must be >= 0, got {margin_px!r}")
    names = list(poses)
    outlines = {name: outline_points(camera, poses[name], spacing_px=1.0) for name in names}
    found: list[Conflict] = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            pa, pb = poses[a], poses[b]
            overlap = _inside(camera, pb, outlines[a]).any() or _inside(camera, pa, outlines[b]).any()
            if overlap:
                near, far = (a, b) if np.linalg.norm(pa.r_cam_km) < np.linalg.norm(pb.r_cam_km) else (b, a)
                found += [Conflict(far, near, "occulted"), Conflict(near, far, "transit")]
                continue
            # closest approach of the two sampled outlines (1 px apart: within 0.5 px of the true one)
            d = float(np.min(cKDTree(outlines[b]).query(outlines[a])[0]))
            if d < margin_px:
                found += [Conflict(a, b, "glare"), Conflict(b, a, "glare")]
    return found


def outline_pose(body: Body, R_icrf_cam: Rotation, observer: Observer, ephemeris) -> EllipsoidPose:
    """The pose of ``body``'s outline as ``observer`` sees it (:func:`opnav.image.centres.body_pose`);
    a ``uv-limb`` body (lit by its own glow, not the Sun) as an ellipsoid ``limb_altitude_km`` larger,
    its shading a placeholder (only the outline is used)."""
    if body.shading == "uv-limb":
        body = replace(body, radii_km=tuple(r + body.limb_altitude_km for r in body.radii_km), shading="lambert")
    return body_pose(body, R_icrf_cam, observer, ephemeris)


def frame_conflicts(camera: Camera, bodies: Sequence[Body], R_icrf_cam: Rotation, observer: Observer, ephemeris, *,
                    margin_px: float) -> list[Conflict]:
    """:func:`conflicts` of ``bodies`` at their predicted poses in a frame taken at attitude
    ``R_icrf_cam`` (camera -> ICRF) from ``observer`` (SSB state, ICRF, km, km/s); a body whose
    outline reaches behind the camera is left out (it is in no frame)."""
    poses = {}
    for body in bodies:
        try:
            pose = outline_pose(body, R_icrf_cam, observer, ephemeris)
            outline_points(camera, pose, spacing_px=8.0)  # raises when the outline reaches behind the camera
        except NoSolutionError:
            continue
        poses[body.name] = pose
    return conflicts(camera, poses, margin_px=margin_px)
