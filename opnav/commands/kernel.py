"""``opnav kernel``: write an SPK (SPICE ephemeris kernel) from an OEM, a scene's propagated observer, or
orbital elements.

Examples::

    opnav kernel --oem probe.oem --body -77 --out probe.bsp
    opnav kernel --scene cruise.toml --body -77 --step 60 --out probe.bsp
    opnav kernel --elements asteroid.toml --out asteroid.bsp

An OEM's arc is written as the OEM says it interpolates (HERMITE: type 13, LAGRANGE and LINEAR:
type 9); a scene's observer (``position_km`` + ``dynamics``) is propagated over its ``[epochs]``
and written every ``--step`` seconds as type 13 of ``--degree``; an elements file
(docs/formats/kernels.md) gives a type-5 (two-body) segment. The file formats and the SPK types are
in docs/formats/kernels.md.
"""

from __future__ import annotations

import argparse

from ..errors import InputError

NAME = "kernel"
HELP = "write an SPK kernel from a CCSDS OEM, a scene's propagated observer, or orbital elements"
OUT = "file"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--oem", help="a CCSDS OEM (KVN or XML): its arc, interpolated as the OEM says")
    source.add_argument("--scene", help="a scene file whose [observer] is a propagated state: its arc over [epochs]")
    source.add_argument("--elements", help="an orbital-elements file (TOML, docs/formats/kernels.md)")
    parser.add_argument("--out", required=True, help="the SPK file to write (replaced if it exists)")
    parser.add_argument("--body", type=int, default=None,
                        help="NAIF id written for the object (a spacecraft's is negative, e.g. -77); required with "
                             "--scene, default the OEM's OBJECT_ID with --oem, not taken with --elements ([body] naif_id)")
    parser.add_argument("--step", type=float, default=60.0,
                        help="--scene: seconds between the states written (default 60)")
    parser.add_argument("--degree", type=int, default=7,
                        help="--scene: degree of the Hermite interpolation, odd, 1 to 27 (default 7)")


def run(args: argparse.Namespace) -> int:
    from ..epochs import describe_epoch

    if args.elements is not None:
        written = _from_elements(args)
    elif args.oem is not None:
        written = _from_oem(args)
    else:
        written = _from_scene(args)
    body, center, t0, t1, what = written
    print(f"wrote {args.out}: NAIF {body} relative to NAIF {center}, {describe_epoch(t0)} to {describe_epoch(t1)} "
          f"({what})")
    return 0


def _from_oem(args: argparse.Namespace) -> tuple:
    from ..ccsds import read_oem
    from ..ephemeris.spice import naif_code
    from ..ephemeris.spk_writer import oem_interpolation, write_oem_spk

    oem = read_oem(args.oem)
    write_oem_spk(args.out, oem, body=args.body)
    interpolation, degree = oem_interpolation(oem.interpolation, oem.interpolation_degree)
    body = args.body if args.body is not None else int(str(oem.object_id).strip())
    kind = "type 13, Hermite" if interpolation == "hermite" else "type 9, Lagrange"
    return (body, naif_code(oem.center), oem.t_tdb_s[0], oem.t_tdb_s[-1],
            f"{kind} of degree {degree}, {len(oem.t_tdb_s)} states")


def _from_scene(args: argparse.Namespace) -> tuple:
    import numpy as np

    from ..dynamics import get_model, propagate
    from ..ephemeris.spice import naif_code
    from ..ephemeris.spk_writer import write_spk
    from ..sim.scene import load_scene

    if args.body is None:
        raise InputError("--scene needs --body, the NAIF id to write the observer as (e.g. -77)")
    if not (np.isfinite(args.step) and args.step > 0.0):
        raise InputError(f"--step must be a positive number of seconds, got {args.step!r}")
    scene = load_scene(args.scene)
    spec = scene.observer
    if spec.dynamics is None:
        raise InputError(f"{args.scene}: --scene writes a propagated observer ([observer] position_km, velocity_km_s, "
                         f"epoch, dynamics); this one sits at body {spec.body!r}")
    start, stop = float(scene.t_tdb_s[0]), float(scene.t_tdb_s[-1])
    count = int(np.ceil((stop - start) / args.step)) + 1
    t = np.linspace(start, stop, max(count, (args.degree + 1) // 2, 2))
    model = get_model(spec.dynamics)
    state0 = np.concatenate([spec.position_km, spec.velocity_km_s])
    # both ways from the state's epoch when the scene's epochs straddle it
    before, after = t[t < spec.epoch_tdb_s], t[t >= spec.epoch_tdb_s]
    parts = []
    if before.size:
        parts.append(propagate(model, spec.epoch_tdb_s, state0, before[::-1]).states[::-1])
    if after.size:
        parts.append(propagate(model, spec.epoch_tdb_s, state0, after).states)
    center = naif_code(model.center)
    write_spk(args.out, t, np.concatenate(parts), body=args.body, center=center, degree=args.degree,
              comment=f"Observer of scene {args.scene} (force model {spec.dynamics}), written by opnav.")
    return args.body, center, start, stop, f"type 13, Hermite of degree {args.degree}, {t.size} states"


def _from_elements(args: argparse.Namespace) -> tuple:
    from ..ephemeris.elements_file import load_elements_file
    from ..ephemeris.spice import naif_code
    from ..ephemeris.spk_writer import write_elements_spk

    if args.body is not None:
        raise InputError("--body is not taken with --elements: the elements file's [body] naif_id is written")
    spec = load_elements_file(args.elements)
    center = naif_code(spec.center)
    write_elements_spk(args.out, spec.elements, body=spec.naif_id, center=center, start_tdb_s=spec.start_tdb_s,
                       stop_tdb_s=spec.stop_tdb_s, frame=spec.frame, step_s=spec.step_s,
                       comment=f"Keplerian orbit of elements file {args.elements}, written by opnav.")
    return spec.naif_id, center, spec.start_tdb_s, spec.stop_tdb_s, f"type 5, two-body, {spec.frame}"
