"""The Study protocol: what the runner, the campaign and ``opnav run`` ask of a study.

A study is either **simulating** (S1, S3: ``simulate(settings, seed) -> Simulation``, the runner
then runs the generic filter stages on it; some can also render frames and measure them,
``simulate_images``) or **evaluating** (S2, S4: ``evaluate(settings, seed, log) -> dict``, its own
tables and filter runs in one stage). Callers ask the protocol (:attr:`Study.generic_filters`,
:attr:`Study.image_mode`) instead of probing the study module for functions.

:class:`ModuleStudy` is the protocol over a study module (``opnav/studies/s1.py`` ...): the module
holds ``Settings`` (a frozen dataclass), ``simulate`` and ``dynamics`` or ``evaluate``, optionally
``simulate_images`` and ``IMAGE_SETTINGS`` (settings only image mode reads). It imports the module
on first use.
"""

from __future__ import annotations

import importlib
import json
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
        ``simulate_images`` renders frames and measures them (``--mode images``).
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

    def evaluate(self, settings, seed: int, log: Callable[[str], None]) -> dict: ...

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
    """An evaluating study's filter figures, as indented JSON."""
    return json.dumps(summary["filters"], indent=2, default=float).splitlines()


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

    @property
    def generic_filters(self) -> bool:
        return not hasattr(self.module, "evaluate")

    @property
    def image_mode(self) -> bool:
        return hasattr(self.module, "simulate_images")

    @property
    def image_settings(self) -> tuple[str, ...]:
        return tuple(getattr(self.module, "IMAGE_SETTINGS", ()))

    def dynamics(self, settings):
        return self.module.dynamics(settings)

    def simulate(self, settings, seed: int):
        return self.module.simulate(settings, seed)

    def simulate_images(self, settings, seed: int, out, *, progress: bool, workers: int, faults):
        return self.module.simulate_images(settings, seed, out, progress=progress, workers=workers, faults=faults)

    def evaluate(self, settings, seed: int, log: Callable[[str], None]) -> dict:
        return self.module.evaluate(settings, seed, log)

    def summary_lines(self, summary: dict) -> list[str]:
        return filter_summary_lines(summary) if self.generic_filters else evaluation_summary_lines(summary)
