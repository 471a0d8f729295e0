"""The package's layering, checked on its source: imports run one way, one loader, one loop.

Layers, lowest first (an import may stay in its layer or go to a lower one, never up):

0. foundation: constants, epochs, frames, errors, files, compiled, allocator, config, records, consistency
1. model: camera, bodies, observer, light, light_compiled, photometry, catalog, ephemeris, dynamics
2. one frame: render, image
3. measurement models and exchange files: measurements, ccsds
4. navigation: filters, observability
5. the engine: sim
6. the studies: studies
7. the command line: commands, cli

``records`` sits in the foundation: it is the plain data every layer above passes on (it imports
only ``opnav.errors`` and ``opnav.files``, how opnav reads and writes files).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "opnav"

LAYERS = {
    0: ("constants", "epochs", "frames", "errors", "files", "compiled", "allocator", "config", "records",
        "consistency"),
    1: ("camera", "bodies", "shape", "observer", "light", "light_compiled", "photometry", "catalog", "ephemeris",
        "dynamics"),
    2: ("render", "image"),
    3: ("measurements", "ccsds"),
    4: ("filters", "observability"),
    5: ("sim",),
    6: ("studies",),
    7: ("commands", "cli"),
}
RANK = {name: rank for rank, names in LAYERS.items() for name in names}


def _modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        yield path, ".".join(parts)


def _imports(path: Path, module: str):
    """``(imported module, names)`` of every ``opnav`` import in ``path``, relative ones resolved."""
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target == "opnav" or target.startswith("opnav."):
                yield target, [alias.name for alias in node.names]
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("opnav"):
                    yield alias.name, []


def _top(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def test_every_module_has_a_layer():
    unplaced = sorted({_top(module) for _, module in _modules()} - set(RANK) - {None})
    assert not unplaced, f"modules without a layer in tests/test_layers.py: {unplaced}"


def test_imports_never_point_up():
    upward = []
    for path, module in _modules():
        source = _top(module)
        if source is None:
            continue
        for target, names in _imports(path, module):
            candidates = [target] if _top(target) else [f"opnav.{name}" for name in names]
            for imported in candidates:
                top = _top(imported)
                if top in RANK and RANK[top] > RANK[source]:
                    upward.append(f"{module} imports {imported}")
    assert not upward, "imports that point up a layer:\n" + "\n".join(upward)


def test_sim_never_imports_filters_or_studies_and_nothing_imports_commands():
    wrong = []
    for path, module in _modules():
        for target, names in _imports(path, module):
            top = _top(target) or ""
            if _top(module) == "sim" and top in ("filters", "studies"):
                wrong.append(f"{module} imports {target}")
            if top == "commands" and _top(module) not in ("commands", "cli"):
                wrong.append(f"{module} imports {target}")
    assert not wrong, "\n".join(wrong)


def test_no_private_name_crosses_a_module():
    crossing = []
    for path, module in _modules():
        for target, names in _imports(path, module):
            for name in names:
                if name.startswith("_") and not name.startswith("__"):
                    crossing.append(f"{module} imports {target}.{name}")
    assert not crossing, "private names imported across modules:\n" + "\n".join(crossing)


def test_toml_is_read_in_one_place():
    readers = sorted(module for path, module in _modules() if "tomllib" in path.read_text() and module != "opnav.config")
    assert not readers, f"TOML parsed outside opnav/config.py: {readers}"


@pytest.mark.parametrize("call", ["render_frame(", "render_windows(", "process_frame(", "tracker.step("])
def test_one_render_and_measure_loop(call):
    """Frames are rendered and measured in a loop only in ``opnav/sim/loop.py``: a call of the
    renderer or of the image stage elsewhere above the image layer is a second loop. One exception,
    not a loop: the report's sample frames (one per sensor: S1's measured again to draw its
    detections, S3's two rendered whole at one epoch, where the run rendered windows)."""
    callers = []
    for path, module in _modules():
        if _top(module) in ("render", "image") or module == "opnav.sim.loop":
            continue
        if module == "opnav.studies.report_frames" and call in ("process_frame(", "render_frame("):
            continue
        if call in path.read_text():
            callers.append(module)
    assert not callers, f"{call} called outside opnav.sim.loop: {callers}"
