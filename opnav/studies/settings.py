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
array or a comma-separated ``--set`` value). Unknown tables or keys, values of the
wrong type and impossible values raise :class:`opnav.errors.InputError` naming the
file and the key.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError
from ..filters.options import FILTERS
from ..tomlio import convert, read_toml

TABLES = ("scenario", "settings", "filters", "faults")
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

        Settings that only image mode reads (the study's ``IMAGE_SETTINGS``) are left out of a
        measurement-mode identity, so changing them does not redo measurement-mode work.
        """
        from . import STUDIES

        image_only = () if mode == "images" else getattr(STUDIES.get(self.study), "IMAGE_SETTINGS", ())
        values = {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self.settings).items()
                  if k not in image_only}
        identity = {"study": self.study, "name": self.name, "seed": self.seed, "settings": values}
        if self.faults is not None and self.faults.active:  # runs without faults keep their old hashes
            identity["faults"] = dataclasses.asdict(self.faults)
        return identity


def _convert(value, kind, key: str, source: str):
    """``value`` (TOML value or ``--set`` string) as the field type ``kind``; errors name ``source`` and ``key``."""
    return convert(value, kind, f"{source}: [settings] {key}")


def parse_overrides(pairs: list[str] | None) -> dict[str, str]:
    """``["KEY=VALUE", ...]`` -> dict; a pair without ``=`` is an error naming it."""
    out = {}
    for pair in pairs or []:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise InputError(f"--set expects KEY=VALUE, got {pair!r}")
        out[key.strip()] = value.strip()
    return out


def build_settings(cls, values: dict, source: str):
    """An instance of the study's ``Settings`` from ``values``, every key checked and converted."""
    hints = typing.get_type_hints(cls)
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - fields)
    if unknown:
        raise InputError(f"{source}: unknown setting(s) {unknown}; known: {sorted(fields)}")
    converted = {key: _convert(value, hints[key], key, source) for key, value in values.items()}
    try:
        return cls(**converted)
    except InputError as exc:
        raise InputError(f"{source}: {exc}") from None


def load_run_file(path: str | Path, overrides: dict[str, str] | None = None) -> RunFile:
    """Read and validate run file ``path``, then apply ``overrides`` (``--set``) to its ``[settings]``."""
    from . import STUDIES

    path = Path(path)
    data = read_toml(path)
    source = str(path)
    unknown = sorted(set(data) - set(TABLES))
    if unknown:
        raise InputError(f"{source}: unknown table(s) {unknown}; a run file has {list(TABLES)}")
    for table in TABLES:
        if not isinstance(data.get(table, {}), dict):
            raise InputError(f"{source}: [{table}] must be a table, got {data[table]!r}")
    head = dict(data.get("scenario", {}))
    extra = sorted(set(head) - {"study", "name", "seed", "mode"})
    if extra:
        raise InputError(f"{source}: unknown key(s) {extra} in [scenario]; known: ['mode', 'name', 'seed', 'study']")
    mode = head.get("mode", "measurements")
    if mode not in MODES:
        raise InputError(f"{source}: [scenario] mode must be one of {list(MODES)}, got {mode!r}")
    study = str(head.get("study", ""))
    if study not in STUDIES:
        raise InputError(f"{source}: [scenario] study must be one of {sorted(STUDIES)}, got {study!r}")
    seed = head.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise InputError(f"{source}: [scenario] seed must be a non-negative integer, got {seed!r}")
    module = STUDIES[study]
    values = dict(data.get("settings", {}))
    fault_values = dict(data.get("faults", {}))
    for key, value in (overrides or {}).items():
        if key.startswith("faults."):
            fault_values[key.removeprefix("faults.")] = value
        else:
            values[key] = value
    if "seed" in values:  # --set seed=N is the seed, not a study setting
        seed = int(_convert(values.pop("seed"), int, "seed", source))
    settings = build_settings(module.Settings, values, source)
    filters_table = dict(data.get("filters", {}))
    extra = sorted(set(filters_table) - {"names"})
    if extra:
        raise InputError(f"{source}: unknown key(s) {extra} in [filters]; known: ['names']")
    names = convert(filters_table.get("names", ["ekf"]), tuple[str, ...], f"{source}: [filters] names")
    check_filters(names, source)
    name = convert(head.get("name", path.stem), str, f"{source}: [scenario] name")
    from .faults import faults_from_values

    faults = faults_from_values(fault_values, source)
    return RunFile(source, study, name, int(seed), settings, names, mode, faults)


def check_filters(names, source: str) -> tuple[str, ...]:
    """The filter names, each one a sequential filter of :data:`opnav.filters.options.FILTERS`."""
    allowed = [f for f in FILTERS if f not in ("wls", "federated")]
    bad = [n for n in names if n not in allowed]
    if bad or not names:
        raise InputError(f"{source}: filters must be some of {allowed}, got {list(names)}")
    return tuple(names)
