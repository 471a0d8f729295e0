"""What an evaluating study (S2, S4) hands the runner: its figures, the arrays its report plots, and
the trajectories it estimated.

The runner (:func:`opnav.studies.runner.run_study`) writes :attr:`Evaluation.summary` into
``evaluation.json`` and ``summary.json``, :attr:`Evaluation.arrays` into ``evaluation.npz`` (the
report's figures are drawn from it, so a re-run that reuses the stage draws the same plots) and
each :class:`EstimatedTrajectory` as a CCSDS OEM ``filters/<name>.oem``; all of them are checksummed
in ``evaluation.json``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from ..filters.estimates import Track

#: What a trajectory's name may be: it names its OEM file.
_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


@dataclass(frozen=True)
class EstimatedTrajectory:
    """One estimated trajectory of an evaluating study, written as ``filters/<name>.oem``.

    Attributes
    ----------
    name : str
        File stem (letters, digits, ``_ . -``).
    center : str
        Origin of the states (``sun``, ``mars``).
    track : Track
        Epochs (TDB s past J2000), states ``[r km, v km/s]`` (ICRF, about ``center``) and covariances.
    description : str
        One line for the OEM's COMMENT (what the estimate is).
    """

    name: str
    center: str
    track: Track
    description: str = ""

    def __post_init__(self) -> None:
        if not _NAME.match(self.name):
            raise ValueError(f"trajectory name {self.name!r} must be letters, digits, '_', '.' or '-'")


@dataclass(frozen=True)
class Evaluation:
    """An evaluating study's result (module notes).

    Attributes
    ----------
    summary : dict
        JSON-ready figures: ``filters`` (per estimator), ``facts``, ``paper`` and any other section
        (S2: ``observability``); the terminal table (:func:`opnav.studies.base.evaluation_summary_lines`)
        and the report read them.
    arrays : dict of str to ndarray
        What the report plots (saved as ``evaluation.npz``); names are the study's.
    trajectories : tuple of EstimatedTrajectory
        Written as CCSDS OEMs.
    """

    summary: dict
    arrays: dict = field(default_factory=dict)
    trajectories: tuple[EstimatedTrajectory, ...] = ()

    def __post_init__(self) -> None:
        names = [t.name for t in self.trajectories]
        if len(set(names)) != len(names):
            raise ValueError(f"trajectory names must differ, got {names}")
        for key, value in self.arrays.items():
            if not isinstance(value, np.ndarray):
                raise TypeError(f"evaluation array {key!r} must be a numpy array, got {type(value).__name__}")
