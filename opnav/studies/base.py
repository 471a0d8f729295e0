"""The Study protocol: what the runner, the campaign and ``opnav run`` ask of a study.

A study is either **simulating** (S1, S3: ``simulate(settings, seed) -> Simulation``, the runner
then runs the generic filter stages on it; some can also render frames and measure them,
``simulate_images``) or **evaluating** (S2, S4: ``evaluate(settings, seed, log) ->``
:class:`~opnav.studies.evaluation.Evaluation`, its own tables, arrays and estimated trajectories in
one stage, and ``report_blocks(summary, arrays)``, its report page drawn from them). Callers ask the
protocol (:attr:`Study.generic_filters`, :attr:`Study.image_mode`) instead of probing the study
module for functions.

:class:`ModuleStudy` is the protocol over a study module (``opnav/studies/s1.py`` ...). The module
declares what it is: ``KIND`` (:data:`KINDS`: ``"simulating"`` with ``simulate`` and ``dynamics``, or
``"evaluating"`` with ``evaluate`` and ``report_blocks``), ``IMAGE_MODE`` (True: it has
``simulate_images``, or for an evaluating study ``evaluate_images``: the same evaluation on records
measured from rendered frames) and ``IMAGE_SETTINGS`` (settings only image mode reads), beside ``Settings`` (a frozen dataclass).
:func:`check_study` verifies a module against its declaration; the module is imported on first use.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from types import ModuleType
from typing import Callable, Protocol, runtime_checkable


@runtime_checkable
class Study(Protocol):
    """A study as the runner sees it.

    Attributes
    ----------
    name : str
        The run file's ``[scenario] study`` (``s1``).
    Settings : type
        Frozen dataclass of the ``[settings]`` table, each field a ``--set`` key.
    generic_filters : bool
        True: ``simulate`` hands a :class:`~opnav.studies.common.Simulation` to the runner's filter
        stages (any filter by name, lockstep campaigns, the Monte Carlo NEES test); False: the
        study has its own ``evaluate``.
    image_mode : bool
        ``simulate_images`` (simulating) or ``evaluate_images`` (evaluating) renders frames and
        measures them (``--mode images``).
    image_settings : tuple of str
        Settings only image mode reads (left out of a measurement-mode run's identity).
    """

    name: str

    @property
    def Settings(self) -> type: ...

    @property
    def generic_filters(self) -> bool: ...

    @property
    def image_mode(self) -> bool: ...

    @property
    def image_settings(self) -> tuple[str, ...]: ...

    def dynamics(self, settings): ...

    def simulate(self, settings, seed: int): ...

    def simulate_images(self, settings, seed: int, out, *, progress: bool, workers: int, faults): ...

    def evaluate(self, settings, seed: int, log: Callable[[str], None]): ...

    def evaluate_images(self, settings, seed: int, log: Callable[[str], None], out, *, progress: bool,
                        workers: int): ...

    def report_blocks(self, summary: dict, arrays: dict) -> list: ...

    def summary_lines(self, summary: dict) -> list[str]: ...


def filter_summary_lines(summary: dict) -> list[str]:
    """One line per filter of a simulating study's ``summary.json``: position and velocity RMS, mean
    NEES, final error and 1-sigma, consistency flags."""
    lines = []
    for name, figures in summary["filters"].items():
        final = figures["final"]
        lines.append(f"{name:9s} position RMS {figures['position_rms_km']:10.3f} km  velocity RMS "
                     f"{figures['velocity_rms_m_s']:9.4f} m/s  NEES {figures['nees_mean']:8.2f}  final error "
                     f"{final['position_error_km']:.3f} km (1-sigma {final['position_sigma_km']:.3f} km)  "
                     f"flags: {', '.join(figures['consistency']['flags']) or 'none'}")
    return lines


def evaluation_summary_lines(summary: dict) -> list[str]:
    """An evaluating study's filter figures as a table: S2's switching filter per phase (position and
    velocity error after convergence, NEES, 1-sigma at the end, beside S2 Table 3), S4's federated runs
    per case (final position and velocity errors with their 1-sigmas, worst axis error in sigmas,
    refused records, beside the paper's claim); figures of another shape one per line."""
    lines = []
    paper = summary.get("paper") or {}
    for name, figures in summary["filters"].items():
        if not isinstance(figures, dict):
            lines.append(f"{name}: {_figure(figures)}")
            continue
        phases = {key: value for key, value in figures.items()
                  if isinstance(value, dict) and "position_error_mean_km" in value}
        if phases:
            lines += _phase_lines(name, figures, phases, paper.get("table3") or {})
        elif "final_position_error_km" in figures:
            if not any(line.startswith("filter ") for line in lines):
                lines.append(f"{'filter':14s} {'final position error':>21s} {'1-sigma':>11s} {'final velocity error':>21s} "
                             f"{'1-sigma':>12s} {'worst axis / sigma':>19s} {'refused':>11s}")
            lines.append(f"{name:14s} {_cell(figures, 'final_position_error_km', 18, 3)} km "
                         f"{_cell(figures, 'final_position_sigma_km', 8, 3)} km "
                         f"{_cell(figures, 'final_velocity_error_m_s', 17, 4)} m/s "
                         f"{_cell(figures, 'final_velocity_sigma_m_s', 8, 4)} m/s "
                         f"{_cell(figures, 'max_axis_error_in_sigma', 19, 2)} "
                         f"{str(figures.get('refused', '-')) + '/' + str(figures.get('records', '-')):>11s}")
        else:
            lines.append(f"{name}: " + ", ".join(f"{key} {_figure(value)}" for key, value in figures.items()
                                                 if not isinstance(value, (dict, list))))
    if isinstance(paper.get("claim"), str):
        lines.append(f"paper: {paper['claim']}")
    return lines


def _cell(figures: dict, key: str, width: int, digits: int) -> str:
    """``figures[key]`` right-aligned in ``width`` with ``digits`` decimals, or ``-`` when absent."""
    value = figures.get(key)
    return f"{value:{width}.{digits}f}" if isinstance(value, (int, float)) else f"{'-':>{width}s}"


def _figure(value) -> str:
    """A figure for a summary line: floats to 4 significant digits."""
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def _phase_lines(name: str, figures: dict, phases: dict, table3: dict) -> list[str]:
    """S2: one row per phase of a switching run, the paper's Table 3 row beside it."""
    accepted = figures.get("accepted_fraction")
    head = f"{name}: " + (f"{accepted:.1%} of the records accepted; " if isinstance(accepted, float) else "") + \
        "errors after convergence (second half of each phase), paper: S2 Table 3"
    lines = [head, f"  {'phase':14s} {'position error mean':>20s} {'variance':>13s} {'velocity error mean':>20s} "
                   f"{'NEES':>6s} {'1-sigma at end':>15s}   {'paper position mean / variance':>32s} "
                   f"{'paper velocity mean':>19s}"]
    for phase, row in phases.items():
        paper = table3.get(phase.split()[0])
        paper_text = (f"{paper[0]:13.4f} km / {paper[1]:8.4f} km^2 {1e3 * paper[2]:15.1f} m/s"
                      if paper and len(paper) >= 3 else f"{'-':>32s} {'-':>19s}")
        lines.append(f"  {phase:14s} {row['position_error_mean_km']:17.3f} km {row['position_error_var_km2']:8.2f} km^2 "
                     f"{1e3 * row['velocity_error_mean_km_s']:16.4f} m/s {row['nees_mean']:6.2f} "
                     f"{row['sigma_position_km_at_end']:12.3f} km   {paper_text}")
    return lines


#: What a study module's ``KIND`` may say.
KINDS = ("simulating", "evaluating")
#: The functions each declaration promises.
_PROMISED = {"simulating": ("simulate", "dynamics"), "evaluating": ("evaluate", "report_blocks")}


@dataclass(frozen=True)
class ModuleStudy:
    """:class:`Study` over the study module ``module`` (dotted path), imported on first use."""

    name: str
    module_path: str

    @property
    def module(self) -> ModuleType:
        return importlib.import_module(self.module_path)

    @property
    def Settings(self) -> type:
        return self.module.Settings

    def declared(self, name: str):
        """The study module's declaration ``name`` (``KIND``, ``IMAGE_MODE``, ``IMAGE_SETTINGS``)."""
        try:
            return getattr(self.module, name)
        except AttributeError:
            raise TypeError(f"study module {self.module_path} does not declare {name} (opnav.studies.base)") from None

    @property
    def generic_filters(self) -> bool:
        return self.declared("KIND") == "simulating"

    @property
    def image_mode(self) -> bool:
        return bool(self.declared("IMAGE_MODE"))

    @property
    def image_settings(self) -> tuple[str, ...]:
        return tuple(self.declared("IMAGE_SETTINGS"))

    def dynamics(self, settings):
        return self.module.dynamics(settings)

    def simulate(self, settings, seed: int):
        return self.module.simulate(settings, seed)

    def simulate_images(self, settings, seed: int, out, *, progress: bool, workers: int, faults):
        return self.module.simulate_images(settings, seed, out, progress=progress, workers=workers, faults=faults)

    def evaluate(self, settings, seed: int, log: Callable[[str], None]):
        return self.module.evaluate(settings, seed, log)

    def evaluate_images(self, settings, seed: int, log: Callable[[str], None], out, *, progress: bool,
                        workers: int):
        return self.module.evaluate_images(settings, seed, log, out, progress=progress, workers=workers)

    def report_blocks(self, summary: dict, arrays: dict) -> list:
        return self.module.report_blocks(summary, arrays)

    def summary_lines(self, summary: dict) -> list[str]:
        return filter_summary_lines(summary) if self.generic_filters else evaluation_summary_lines(summary)


def check_study(study: ModuleStudy) -> None:
    """Raise ``TypeError`` when ``study``'s module does not hold what it declares: a known ``KIND``
    and its functions, ``simulate_images`` (``evaluate_images`` for an evaluating study) exactly when
    ``IMAGE_MODE``, ``Settings`` a dataclass
    holding every name of ``IMAGE_SETTINGS``."""
    import dataclasses

    kind = study.declared("KIND")
    if kind not in KINDS:
        raise TypeError(f"{study.module_path}: KIND must be one of {KINDS}, got {kind!r}")
    missing = [name for name in _PROMISED[kind] if not callable(getattr(study.module, name, None))]
    image_function = "simulate_images" if kind == "simulating" else "evaluate_images"
    if study.image_mode != callable(getattr(study.module, image_function, None)):
        missing.append(image_function if study.image_mode else f"IMAGE_MODE = True (it has {image_function})")
    if missing:
        raise TypeError(f"{study.module_path} ({kind}) lacks {', '.join(missing)}")
    fields = {f.name for f in dataclasses.fields(study.Settings)}
    if not set(study.image_settings) <= fields:
        raise TypeError(f"{study.module_path}: IMAGE_SETTINGS {sorted(set(study.image_settings) - fields)} "
                        "are not Settings fields")
