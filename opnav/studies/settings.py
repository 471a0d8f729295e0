"""Run files: one TOML per study run, validated on load, with ``--set KEY=VALUE`` overrides.

A run file has three tables::

    [scenario]
    study = "s1"                 # s1 | s3 (opnav.studies.STUDIES)
    name = "s1_jul_both_0.1"     # used in reports
    seed = 2014                  # one seed drives the truth draws, noise and filter start
    mode = "measurements"        # or "images": frames -> image stage (CLI --mode overrides)

    [settings]                   # the study's own settings (its Settings dataclass documents each)
    month = "jul"

    [filters]
    names = ["ekf", "ukf"]       # filters run by default (CLI --filters overrides)

    [faults]                     # optional (opnav.studies.faults), or --set faults.NAME=VALUE
    outlier_fraction = 0.01      # 1 % of the records 100 sigma off

Every ``[settings]`` key is a field of the study's frozen ``Settings`` dataclass;
its type is the field's (int, float, str, bool, or a tuple of str given as a TOML
array or a comma-separated ``--set`` value). The tables are read by
:func:`opnav.config.build`: unknown tables or keys (the nearest known one suggested),
values of the wrong type and impossible values raise :class:`opnav.errors.InputError`
naming the file, the table and the key.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from ..config import Where, build, convert, read_toml
from ..config import parse_overrides  # noqa: F401 (re-exported: the commands' --set parser)
from ..errors import InputError
from ..filters.option_types import FILTERS

#: measurements: the study's noise added to the true values (the papers' set-up); images: rendered
#: frames through the image stage.
MODES = ("measurements", "images")


@dataclass(frozen=True)
class RunFile:
    """A validated run file: the study, its settings object, the seed and the default filters."""

    path: str
    study: str
    name: str
    seed: int
    settings: object
    filters: tuple[str, ...]
    mode: str = "measurements"
    faults: object = None  # opnav.studies.faults.Faults; None: none

    def describe(self, mode: str = "measurements") -> dict:
        """JSON-ready identity of the run in ``mode`` (what the stage hashes are taken over).

        Settings that only image mode reads (the study's
        :attr:`~opnav.studies.base.Study.image_settings`) are left out of a measurement-mode
        identity, so changing them does not redo measurement-mode work.
        """
        from . import STUDIES

        image_only = () if mode == "images" else STUDIES[self.study].image_settings
        values = {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self.settings).items()
                  if k not in image_only}
        identity = {"study": self.study, "name": self.name, "seed": self.seed, "settings": values}
        if self.faults is not None and self.faults.active:  # runs without faults keep their old hashes
            identity["faults"] = dataclasses.asdict(self.faults)
        return identity


@dataclass(frozen=True)
class RunHead:
    """``[scenario]`` of a run file: the study, the run's name (default: the file's stem), its seed and mode."""

    study: str = ""
    name: str | None = None
    seed: int = 0
    mode: str = "measurements"


@dataclass(frozen=True)
class FiltersTable:
    """``[filters]`` of a run file: the filters run by default."""

    names: tuple[str, ...] = ("ekf",)


@dataclass(frozen=True)
class RunTables:
    """A run file as written (:data:`TABLES`); ``[settings]`` and ``[faults]`` are read once the study is known."""

    scenario: RunHead
    settings: dict = field(default_factory=dict)
    filters: FiltersTable = field(default_factory=FiltersTable)
    faults: dict = field(default_factory=dict)


TABLES = tuple(f.name for f in dataclasses.fields(RunTables))


def load_run_file(path: str | Path, overrides: dict[str, str] | None = None) -> RunFile:
    """Read and validate run file ``path``, then apply ``overrides`` (``--set``).

    An override ``seed`` is the run's seed, ``faults.NAME`` a fault of ``[faults]`` and any other key
    a study setting of ``[settings]``. Values in the file may also be written as text.
    """
    from . import STUDIES
    from .faults import faults_from_values

    path = Path(path)
    source = str(path)
    tables = build(RunTables, read_toml(path, kind="run file"), Where(source), text=True, noun="table")
    head = tables.scenario
    if head.mode not in MODES:
        raise InputError(f"{source}: [scenario] mode must be one of {list(MODES)}, got {head.mode!r}")
    if head.study not in STUDIES:
        raise InputError(f"{source}: [scenario] study must be one of {sorted(STUDIES)}, got {head.study!r}")
    settings_overrides, fault_overrides, seed, seed_from = {}, {}, head.seed, "[scenario] seed"
    for key, value in (overrides or {}).items():
        if key == "seed":  # --set seed=N is the seed, not a study setting
            seed, seed_from = convert(value, int, f"{source}: --set seed"), "--set seed"
        elif key.startswith("faults."):
            fault_overrides[key.removeprefix("faults.")] = value
        else:
            settings_overrides[key] = value
    if seed < 0:  # numpy's generators take non-negative seeds only
        raise InputError(f"{source}: {seed_from} must be a non-negative integer, got {seed!r}")
    settings = build(STUDIES[head.study].Settings, tables.settings, Where(source, "settings"), text=True,
                     noun="setting", overrides=settings_overrides)
    names = tables.filters.names
    check_filters(names, source)
    faults = faults_from_values(tables.faults, source, fault_overrides)
    name = head.name if head.name is not None else path.stem
    return RunFile(source, head.study, name, seed, settings, names, head.mode, faults)


def check_filters(names, source: str) -> tuple[str, ...]:
    """The filter names, each one a sequential filter of :data:`opnav.filters.option_types.FILTERS`."""
    allowed = [f for f in FILTERS if f not in ("wls", "federated")]
    bad = [n for n in names if n not in allowed]
    if bad or not names:
        raise InputError(f"{source}: filters must be some of {allowed}, got {list(names)}")
    return tuple(names)
