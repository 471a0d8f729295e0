"""What the render -> measure loop (:mod:`opnav.sim.loop`) gives: frozen results.

:class:`LoopResult` holds the records, the frames skipped and why, the targets missed, the trackers'
events, each frame's true target directions (:class:`FrameTargets`, what :mod:`opnav.sim.checks`
compares the records with), the frames on disk and the counts; :meth:`LoopResult.combine` joins
the results of consecutive chunks, :func:`result_to_json` / :func:`result_from_json` store one
beside its records (:mod:`opnav.sim.chunks`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..records import Measurement


#: The counts of a :class:`LoopResult` (summed over chunks).
COUNTS = ("frames_full", "frames_windowed", "frames_dropped", "frames_reused", "stars_used", "stars_misidentified",
          "navigation_star_not_tracked")


@dataclass(frozen=True)
class Direction:
    """A target's true apparent direction, ICRF, rad."""

    ra_rad: float
    dec_rad: float


@dataclass(frozen=True)
class FrameTargets:
    """The true apparent RA/Dec (rad) of the measured targets in one frame (``directions``: name ->
    (ra, dec)), what :mod:`opnav.sim.checks` compares the records with (``target(name)``)."""

    directions: dict

    def target(self, name: str) -> Direction:
        ra, dec = self.directions[name]
        return Direction(ra, dec)


@dataclass(frozen=True)
class Miss:
    """A target the stage did not measure in a frame (hidden by its primary's glare, or not found)."""

    frame_id: str
    target: str
    hidden_by_primary: bool


@dataclass(frozen=True)
class LoopResult:
    """What the loop gave.

    Attributes
    ----------
    records : tuple of Measurement
        In frame order (the moons of a frame as one ``radec_pair``, :func:`opnav.records.join_frame_radec`).
    skipped : dict
        Frame id -> why the frame gave no records.
    missed : tuple of Miss
    targets : tuple of str
        The targets the stages measure (``missed`` counts per target).
    events : tuple of dict
        The trackers' acquisitions and losses of lock (:class:`opnav.image.tracking.Tracker`).
    truths : dict
        Frame id -> :class:`FrameTargets`.
    paths : tuple of Path
        Frames on disk, written or reused.
    frames_full, frames_windowed : int
        Frames rendered in full and in windows (a limb sensor's annulus is not counted).
    frames_dropped : int
        Frames the hook declared lost.
    frames_reused : int
        Frames on disk reused; ``rerendered``: file name -> why an old file was not.
    stars_used, stars_misidentified : int
        Stars the tracked frames' attitudes used, and those away from their truth
        (:func:`opnav.sim.checks.misidentified_stars`).
    navigation_star_not_tracked : int
        Limb frames whose navigation star was not among the reference sensor's guide stars.
    chunks_reused : int
        Chunks read back from an earlier run (:mod:`opnav.sim.chunks`).
    attitudes : dict
        ``"<frame id>:<sensor index>"`` -> (quaternion ``[x, y, z, w]`` of the star-identified attitude,
        camera -> ICRF; its 3 x 3 covariance, camera-frame small rotation, rad^2), for every frame of a
        full-frame or tracking stage that gave one (a sun sensor on the same body reads through it).
    """

    records: tuple[Measurement, ...] = ()
    skipped: dict = field(default_factory=dict)
    missed: tuple[Miss, ...] = ()
    targets: tuple[str, ...] = ()
    events: tuple[dict, ...] = ()
    truths: dict = field(default_factory=dict)
    paths: tuple[Path, ...] = ()
    frames_full: int = 0
    frames_windowed: int = 0
    frames_dropped: int = 0
    frames_reused: int = 0
    rerendered: dict = field(default_factory=dict)
    stars_used: int = 0
    stars_misidentified: int = 0
    navigation_star_not_tracked: int = 0
    chunks_reused: int = 0
    attitudes: dict = field(default_factory=dict)

    def missed_counts(self) -> dict:
        """Frames each measured target was missed in (every target listed, 0 included)."""
        return {name: sum(m.target == name for m in self.missed) for name in self.targets}

    @classmethod
    def combine(cls, parts: list["LoopResult"], chunks_reused: int = 0) -> "LoopResult":
        """The results of consecutive parts of one arc as one."""
        return cls(
            records=tuple(r for part in parts for r in part.records),
            skipped={k: v for part in parts for k, v in part.skipped.items()},
            missed=tuple(m for part in parts for m in part.missed),
            targets=parts[0].targets if parts else (),
            events=tuple(e for part in parts for e in part.events),
            truths={k: v for part in parts for k, v in part.truths.items()},
            paths=tuple(p for part in parts for p in part.paths),
            rerendered={k: v for part in parts for k, v in part.rerendered.items()},
            chunks_reused=chunks_reused,
            attitudes={k: v for part in parts for k, v in part.attitudes.items()},
            **{name: sum(getattr(part, name) for part in parts) for name in COUNTS},
        )


def result_to_json(result: LoopResult) -> dict:
    """Everything of ``result`` but its records, as JSON-ready values."""
    return {
        "skipped": result.skipped, "targets": list(result.targets),
        "missed": [[m.frame_id, m.target, m.hidden_by_primary] for m in result.missed],
        "events": list(result.events),
        "truths": {frame: {name: list(direction) for name, direction in truth.directions.items()}
                   for frame, truth in result.truths.items()},
        "paths": [str(p) for p in result.paths], "rerendered": result.rerendered,
        "attitudes": result.attitudes,
        **{name: getattr(result, name) for name in COUNTS},
    }


def result_from_json(data: dict, records) -> LoopResult:
    """The :class:`LoopResult` of :func:`result_to_json` with ``records``."""
    return LoopResult(
        records=tuple(records), skipped=dict(data["skipped"]), targets=tuple(data["targets"]),
        missed=tuple(Miss(frame, target, bool(hidden)) for frame, target, hidden in data["missed"]),
        events=tuple(data["events"]),
        truths={frame: FrameTargets({name: (float(d[0]), float(d[1])) for name, d in directions.items()})
                for frame, directions in data["truths"].items()},
        paths=tuple(Path(p) for p in data["paths"]), rerendered=dict(data["rerendered"]),
        attitudes={k: (list(q), [list(row) for row in c]) for k, (q, c) in data.get("attitudes", {}).items()},
        **{name: int(data[name]) for name in COUNTS},
    )
