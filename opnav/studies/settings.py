"""Run files: one TOML per study run, validated on load, with ``--set KEY=VALUE`` overrides.

A run file has these tables::

    [scenario]
    study = "s1"                 # s1 | s3 (opnav.studies.STUDIES)
    name = "s1_jul_both_0.1"     # used in reports
    spacecraft = "probe"         # optional: OBJECT_NAME of the OEMs, PARTICIPANT_1 of the TDM (default: name)
    seed = 2014                  # one seed drives the truth draws, noise and filter start
    mode = "measurements"        # or "images": frames -> image stage (CLI --mode overrides)

    [settings]                   # the study's own settings (its Settings dataclass documents each)
    month = "jul"

    [filters]
    names = ["ekf", "ukf"]       # filters run by default (CLI --filters overrides)

    [faults]                     # optional (opnav.studies.faults), or --set faults.NAME=VALUE
    outlier_fraction = 0.01      # 1 % of the records 100 sigma off

    [navigation]                 # optional: for ``opnav navigate`` over the run's OUT/measurements.csv
    epoch = "2014-07-01T00:00:00" # (opnav.filters.options; checked on load, not read by ``opnav run``)

Every ``[settings]`` key is a field of the study's frozen ``Settings`` dataclass;
its type is the field's (int, float, str, bool, or a tuple of str given as a TOML
array or a comma-separated ``--set`` value). The tables are read by
:func:`opnav.config.build`: unknown tables or keys (the nearest known one suggested),
values of the wrong type and impossible values raise :class:`opnav.errors.InputError`
naming the file, the table and the key.

``[filters]`` and ``[faults]`` act on the generic filter stages of a simulating study (S1, S3):
a run file of an evaluating study (S2, S4, :attr:`opnav.studies.base.Study.generic_filters`)
that sets them is refused, as is a filter the study cannot run (:func:`study_filters`).
``[navigation]`` is the filter set-up ``opnav navigate`` reads from the file (the study's own
for the file as written); ``opnav run`` checks it and sets its filters up from ``[settings]``.

Files of the wrong kind are named as such (:func:`opnav.config.read_toml`): a scene file given where a
run file is needed (or the reverse) says which it is and which command takes it, and a file
that does not exist suggests the nearest ``*.toml`` of its folder.
"""

from __future__ import annotations

import dataclasses
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path

from ..config import Where, build, convert, read_toml
from ..config import parse_overrides  # noqa: F401 (re-exported: the commands' --set parser)
from ..errors import InputError
from ..filters.option_types import FILTERS

#: The folder of the run file whose ``[settings]`` are being read (None while none is): settings that
#: name files (:mod:`opnav.studies.mission`) take a relative path from the run file's folder, as a
#: scene's ``[kernels]`` does from the scene file's.
RUN_FILE_FOLDER: ContextVar[Path | None] = ContextVar("opnav_run_file_folder", default=None)

#: measurements: the study's noise added to the true values (the papers' set-up); images: rendered
#: frames through the image stage.
MODES = ("measurements", "images")


@dataclass(frozen=True)
class RunFile:
    """A validated run file: the study, its settings object, the seed and the default filters.

    ``spacecraft`` names the spacecraft in the files the run writes (the OEMs' ``OBJECT_NAME`` and
    ``OBJECT_ID``, the TDM's ``PARTICIPANT_1``): ``[scenario] spacecraft``, else the run's name.
    """

    path: str
    study: str
    name: str
    seed: int
    settings: object
    filters: tuple[str, ...]
    mode: str = "measurements"
    faults: object = None  # opnav.studies.faults.Faults; None: none
    spacecraft: str = ""

    def __post_init__(self) -> None:
        if not self.spacecraft:
            object.__setattr__(self, "spacecraft", self.name)

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
        if self.spacecraft != self.name:  # it is written in the files; runs that leave it out keep their hashes
            identity["spacecraft"] = self.spacecraft
        return identity


@dataclass(frozen=True)
class RunHead:
    """``[scenario]`` of a run file: the study, the run's name (default: the file's stem), its seed and mode,
    and the spacecraft's name in the OEMs and TDM it writes (default: the run's name)."""

    study: str = ""
    name: str | None = None
    seed: int = 0
    mode: str = "measurements"
    spacecraft: str | None = None

    def __post_init__(self) -> None:
        # numpy's generators take seeds 0 to 2**63 - 1 (a campaign adds its run index to the seed)
        if not 0 <= self.seed < 2**62:
            raise InputError(f"[scenario] seed must be a whole number from 0 to 2**62, got {self.seed}")


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
    navigation: dict = field(default_factory=dict)  # for opnav navigate (opnav.filters.options)


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
    data = read_toml(path, kind="run file")
    tables = build(RunTables, data, Where(source), text=True, noun="table")
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
    study = STUDIES[head.study]
    if not study.generic_filters:
        # S2 and S4 run their own filters on their own data: a [filters] or [faults] table would be ignored
        unused = [f"[{name}]" for name in ("filters", "faults") if name in data]
        unused += [f"--set faults.{key}" for key in fault_overrides]
        if unused:
            raise InputError(f"{source}: study {head.study} evaluates its own filters on its own data and does not "
                             f"use {', '.join(unused)} (those act on the filter stages of studies "
                             f"{', '.join(simulating_studies())})")
    folder = RUN_FILE_FOLDER.set(path.resolve().parent)
    try:
        settings = build(study.Settings, tables.settings, Where(source, "settings"), text=True,
                         noun="setting", overrides=settings_overrides)
    finally:
        RUN_FILE_FOLDER.reset(folder)
    names = tables.filters.names
    if study.generic_filters:
        check_filters(names, source, study=head.study)
    faults = faults_from_values(tables.faults, source, fault_overrides)
    if tables.navigation:  # checked here so that a typo fails at once, not in a later opnav navigate
        from ..filters.options import navigation_from_dict

        navigation_from_dict(tables.navigation, source)
    name = head.name if head.name is not None else path.stem
    spacecraft = name if head.spacecraft is None else _spacecraft_name(head.spacecraft, source)
    return RunFile(source, head.study, name, seed, settings, names, head.mode, faults, spacecraft)


def _spacecraft_name(value: str, source: str) -> str:
    """``[scenario] spacecraft`` if a CCSDS keyword value can hold it (it becomes ``OBJECT_NAME``)."""
    if not value.strip() or value != value.strip() or any(ord(c) < 32 or ord(c) == 127 for c in value):
        raise InputError(f"{source}: [scenario] spacecraft must be a non-empty name without line breaks, control "
                         f"characters or surrounding blanks (it is the OEMs' OBJECT_NAME), got {value!r}")
    return value


#: Filters no study of ``opnav run`` can run, with the reason: the federated filter fuses one local
#: filter per sensor, and every study's records come from one sensor.
NOT_IN_STUDIES = {"federated": "it fuses one local filter per sensor and the study's records all come from one "
                               "sensor (use opnav navigate --filter federated on records of several sensors)"}


def simulating_studies() -> list[str]:
    """The studies whose filters ``opnav run`` runs by name (:attr:`~opnav.studies.base.Study.generic_filters`)."""
    from . import STUDIES

    return [name for name, study in STUDIES.items() if study.generic_filters]


def study_filters(study: str | None = None) -> tuple[str, ...]:
    """The filters of :data:`opnav.filters.option_types.FILTERS` that ``opnav run`` runs in ``study``
    (every study of :func:`simulating_studies` when None); none for a study with its own filters."""
    if study is not None:
        from . import STUDIES

        if study in STUDIES and not STUDIES[study].generic_filters:
            return ()
    return tuple(f for f in FILTERS if f not in NOT_IN_STUDIES)


def check_filters(names, source: str, study: str | None = None) -> tuple[str, ...]:
    """The filter names, each one of :data:`opnav.filters.option_types.FILTERS` (the one list of every
    command) that study ``study`` runs (:func:`study_filters`); ``InputError`` naming ``source``
    (and the study) otherwise."""
    names = tuple(names)
    unknown = [n for n in names if n not in FILTERS]
    if unknown or not names:
        raise InputError(f"{source}: filters must be some of {list(FILTERS)}, got {list(names)}")
    accepted = study_filters(study)
    where = f"study {study}" if study else "opnav run"
    if not accepted:
        raise InputError(f"{source}: study {study} runs its own filters and takes no filter names, got {list(names)}")
    refused = [n for n in names if n not in accepted]
    if refused:
        reasons = "; ".join(f"{n}: {NOT_IN_STUDIES[n]}" for n in refused)
        raise InputError(f"{source}: {where} runs the filters {', '.join(accepted)}, not {', '.join(refused)} "
                         f"({reasons})")
    return names


#: Study settings that, set to ``"consider"``, hold an error as consider parameters, which only the EKF
#: takes (:func:`opnav.filters.factory.build_filter`): S1's ``ephemeris_model`` and ``camera_error``.
EKF_ONLY_CONSIDER = ("ephemeris_model", "camera_error")


def check_run_filters(run: RunFile, names) -> tuple[str, ...]:
    """The filter names for ``run`` (:func:`check_filters`), refused before any work when a setting of
    :data:`EKF_ONLY_CONSIDER` is ``"consider"`` and a filter is not the EKF (the filter stage would refuse
    it after the simulation and the EKF: a 30-day image run's minutes). One :class:`InputError` line
    naming the run file, the setting and the filters."""
    names = check_filters(names, run.path)
    held = [key for key in EKF_ONLY_CONSIDER if getattr(run.settings, key, None) == "consider"]
    others = [name for name in names if name != "ekf"]
    if held and others:
        raise InputError(f"{run.path}: {held[0]} = 'consider' works with filter 'ekf' only, not "
                         f"{', '.join(others)} (--filters ekf)")
    return names


# ---- the kinds of TOML file opnav reads

def read_toml_file(path: str | Path, kind: str) -> dict:
    """Parse the ``kind`` file ``path`` (:func:`opnav.config.read_toml`: the nearest file suggested
    when it does not exist, a file of another kind refused)."""
    return read_toml(path, kind=kind)
