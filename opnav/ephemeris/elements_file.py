"""Orbital-elements files (TOML) for ``opnav kernel --elements``: a body on a Keplerian orbit.

The file has three tables (docs/formats/kernels.md): ``[body]`` the NAIF id written, the centre and
its GM; ``[elements]`` the osculating elements at their epoch, in degrees, on the J2000 ecliptic or
the ICRF equator; ``[span]`` the interval the SPK covers. :func:`load_elements_file` converts them
once into :class:`ElementsSpec` (TDB seconds past J2000, radians, km), checked by the rules of
:mod:`opnav.config` (unknown keys and bad values are refused in one line naming the file, table and
key).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from ..config import TIME_SCALES, CalendarText, Where, build, check_zone, read_toml
from ..constants import GM_KM3_S2
from ..epochs import parse_epoch
from ..errors import InputError
from .spk_writer import KeplerElements

#: Axes the elements may be referred to, and the SPICE frame of each.
ELEMENT_FRAMES = {"ecliptic": "ECLIPJ2000", "icrf": "J2000"}


@dataclass(frozen=True)
class BodyTable:
    """``[body]``: the NAIF id written, the centre (a body name or NAIF id) and its GM (default: opnav's
    DE421 value for the Sun and the planets' systems)."""

    naif_id: int
    center: str = "sun"
    gm_km3_s2: float | None = None

    def __post_init__(self) -> None:
        if self.gm_km3_s2 is not None and not (math.isfinite(self.gm_km3_s2) and self.gm_km3_s2 > 0.0):
            raise InputError(f"[body] gm_km3_s2 must be a positive number, got {self.gm_km3_s2!r}")


@dataclass(frozen=True)
class ElementsTable:
    """``[elements]``: osculating elements at ``epoch`` (in ``epoch_scale``), angles in degrees."""

    epoch: CalendarText
    a_km: float
    e: float
    i_deg: float
    node_deg: float
    argp_deg: float
    mean_anomaly_deg: float
    epoch_scale: str = field(default="tdb", metadata={"choices": TIME_SCALES})
    frame: str = field(default="ecliptic", metadata={"choices": tuple(ELEMENT_FRAMES)})


@dataclass(frozen=True)
class SpanTable:
    """``[span]``: the interval the SPK covers (in ``scale``) and the spacing of the conic states written."""

    start: CalendarText
    stop: CalendarText
    scale: str = field(default="tdb", metadata={"choices": TIME_SCALES})
    step_s: float | None = None


@dataclass(frozen=True)
class ElementsFile:
    """An elements file as written."""

    body: BodyTable
    elements: ElementsTable
    span: SpanTable


@dataclass(frozen=True)
class ElementsSpec:
    """An elements file in internal units: what :func:`opnav.ephemeris.spk_writer.write_elements_spk` takes."""

    naif_id: int
    center: str
    elements: KeplerElements
    frame: str
    start_tdb_s: float
    stop_tdb_s: float
    step_s: float | None


def load_elements_file(path: str | Path) -> ElementsSpec:
    """Read and check an elements file; ``InputError`` naming the file, table and key on any problem."""
    source = str(path)
    data = build(ElementsFile, read_toml(Path(path), kind="elements file"), Where(source), noun="table")
    el, span, body = data.elements, data.span, data.body
    for text, scale, where in ((el.epoch, el.epoch_scale, "[elements] epoch"), (span.start, span.scale, "[span] start"),
                               (span.stop, span.scale, "[span] stop")):
        check_zone(text, scale, where)
    gm = body.gm_km3_s2
    if gm is None:
        gm = GM_KM3_S2.get(str(body.center).strip().lower())
        if gm is None:
            raise InputError(f"{source}: [body] gm_km3_s2 is needed for center {body.center!r} (opnav knows the GM of "
                             f"{', '.join(GM_KM3_S2)})")
    start, stop = parse_epoch(span.start, span.scale), parse_epoch(span.stop, span.scale)
    if not stop > start:
        raise InputError(f"{source}: [span] stop must be after start")
    if span.step_s is not None and not (math.isfinite(span.step_s) and span.step_s > 0.0):
        raise InputError(f"{source}: [span] step_s must be a positive number of seconds, got {span.step_s!r}")
    try:
        elements = KeplerElements(
            a_km=el.a_km, e=el.e, i_rad=math.radians(el.i_deg), node_rad=math.radians(el.node_deg),
            argp_rad=math.radians(el.argp_deg), mean_anomaly_rad=math.radians(el.mean_anomaly_deg),
            epoch_tdb_s=parse_epoch(el.epoch, el.epoch_scale), gm_km3_s2=gm,
        )
    except InputError as exc:
        raise InputError(f"{source}: [elements] {str(exc).removeprefix('element ')}") from None
    return ElementsSpec(naif_id=body.naif_id, center=body.center, elements=elements, frame=ELEMENT_FRAMES[el.frame],
                        start_tdb_s=start, stop_tdb_s=stop, step_s=span.step_s)


__all__ = ["ELEMENT_FRAMES", "ElementsSpec", "load_elements_file"]
