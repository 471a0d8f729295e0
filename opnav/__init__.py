"""opnav: image-in-the-loop optical navigation for spacecraft.

The names a script needs are available here, e.g. ``opnav.load_scene``,
``opnav.render_frame``, ``opnav.process_frame``, ``opnav.build_filter``,
``opnav.run_filter`` (the full list is ``opnav.__all__``); the subpackages
:mod:`opnav.sim`, :mod:`opnav.image` and :mod:`opnav.filters` export theirs the
same way. The modules behind them are implementation detail and may move; the
exported names stay.

Exports are lazy: ``import opnav`` loads none of the modules (nor numpy, scipy,
numba or matplotlib); the first use of a name imports the module that defines it.

Conventions (units, frames, time, pixels, attitude) are stated once in
``docs/conventions.md``; every public function names the frame, origin and
units of the vectors it takes and returns.
"""

import importlib as _importlib
import sys as _sys
from collections.abc import Callable as _Callable, Mapping as _Mapping

__version__ = "0.1.0"

#: The public names of ``opnav``, by the module that defines each. When a module moves,
#: edit its key here; the names users import from ``opnav`` stay the same.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "opnav.sim.scene": ("Scene", "demo_scene_path", "load_scene"),
    "opnav.sim.loop": ("simulate_scene",),
    "opnav.camera": ("Camera",),
    "opnav.render.frame": ("render_frame",),
    "opnav.image.pipeline": ("FrameInput", "PipelineOptions", "frame_input", "measure_frame", "process_frame"),
    "opnav.records": ("Measurement", "read_csv", "write_csv"),
    "opnav.filters.base": ("Estimate",),
    "opnav.filters.factory": ("build_filter",),
    "opnav.filters.run": ("run_filter",),
    "opnav.filters.navigate": ("navigate",),
    "opnav.filters.options": ("NavigationConfig", "load_navigation"),
    "opnav.ephemeris": ("default_ephemeris",),
    "opnav.catalog": ("load_catalog",),
    "opnav.dynamics.propagate": ("propagate",),
    "opnav.errors": ("InputError", "OpnavError"),
}

#: Subpackages reachable as attributes (``opnav.image``) without an explicit import.
_SUBPACKAGES = ("filters", "image", "sim")


def lazy_exports(
    package: str, exports: _Mapping[str, tuple[str, ...]], subpackages: tuple[str, ...] = ()
) -> tuple[_Callable[[str], object], _Callable[[], list[str]], list[str]]:
    """Module ``__getattr__``, ``__dir__`` and ``__all__`` for a package with lazy exports.

    The tool opnav's own packages (``opnav``, ``opnav.image``, ``opnav.filters``,
    ``opnav.sim``) build their exports with; not itself part of ``opnav.__all__``.

    Parameters
    ----------
    package : str
        Name of the package, e.g. ``"opnav.image"``.
    exports : mapping of str to tuple of str
        Defining module (absolute name) -> the public names it provides.
    subpackages : tuple of str
        Submodules also reachable as attributes (imported on first use), not in ``__all__``.

    Returns
    -------
    getattr, dir : callable
        To bind as the package's ``__getattr__`` and ``__dir__``.
    all : list of str
        The exported names, sorted, for ``__all__``.

    Notes
    -----
    An exported name must not equal a submodule's name: importing that submodule
    binds the module on the package and would hide the exported object.
    """
    where: dict[str, str] = {}
    for module, names in exports.items():
        for name in names:
            if name in where:
                raise ImportError(f"{package}: {name} is exported from both {where[name]} and {module}")
            where[name] = module

    def __getattr__(name: str) -> object:
        module = where.get(name)
        if module is not None:
            value = getattr(_importlib.import_module(module), name)
        elif name in subpackages:
            value = _importlib.import_module(f"{package}.{name}")
        else:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        setattr(_sys.modules[package], name, value)  # later look-ups skip __getattr__
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(_sys.modules[package])) | set(where) | set(subpackages))

    return __getattr__, __dir__, sorted(where)


__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS, _SUBPACKAGES)
__all__ = ["__version__", *__all__]
