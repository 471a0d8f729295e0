"""The ``opnav run`` options a study would ignore, refused before any work.

A run's command-line options act on parts of the runner that not every study has:

- ``--filters`` and ``--checked`` act on the generic filter stages of a simulating study (S1, S3);
  an evaluating study (S2, S4: :attr:`opnav.studies.base.Study.generic_filters` False) runs its
  own filters and has none;
- ``--mode images`` renders frames, which only a study with an image mode does
  (:attr:`~opnav.studies.base.Study.image_mode`);
- ``--workers`` is the number of processes image mode renders and measures in: a run in
  measurement mode (or of a study without image mode) has none.

:func:`check_run_flags` raises :class:`~opnav.errors.InputError`, one line naming the run file, the
study and the options it does not use (and what it does take), instead of letting the run go on
without them and exit 0. ``--filters`` names are checked against the study's filters
(:func:`opnav.studies.settings.check_filters`), and a filter over the whole record set (``wls``)
is refused with ``--checked`` (it has no per-record covariance) or a study setting
``ephemeris_model`` other than ``white`` (it takes the ephemeris error as white noise only).
"""

from __future__ import annotations

from collections.abc import Sequence

from ..errors import InputError
from .settings import RunFile, check_filters, simulating_studies


def check_run_flags(run: RunFile, *, filters: Sequence[str] | None = None, mode: str | None = None,
                    checked: bool = False, workers: int | None = None) -> tuple[str, ...] | None:
    """Refuse the options of ``opnav run`` that ``run``'s study would ignore (module notes).

    Parameters
    ----------
    run : RunFile
    filters : sequence of str, optional
        ``--filters`` (None: not given).
    mode : str, optional
        ``--mode`` (None: not given; the run file's ``[scenario] mode`` applies).
    checked : bool
        ``--checked``.
    workers : int, optional
        ``--workers`` (None: not given).

    Returns
    -------
    tuple of str or None
        The ``--filters`` names, checked, or None when not given.

    Raises
    ------
    InputError
        Naming the run file, the study and every option it does not use.
    """
    from . import STUDIES

    study = STUDIES[run.study]
    effective_mode = mode or run.mode
    if not study.generic_filters:
        images = effective_mode == "images"
        ignored = [flag for flag, given in (("--filters", filters is not None), ("--checked", checked),
                                            ("--mode images", images and not study.image_mode),
                                            ("--workers", workers is not None and not images)) if given]
        if ignored:
            raise InputError(f"{run.path}: study {run.study} does not use {', '.join(ignored)}: it evaluates its own "
                             f"filters on its own data (those options act on the filter and image stages of studies "
                             f"{', '.join(simulating_studies())}); it takes --set and --seed")
    elif effective_mode == "images" and not study.image_mode:
        raise InputError(f"{run.path}: study {run.study} has no image mode; drop --mode images")
    elif workers is not None and effective_mode != "images":
        raise InputError(f"{run.path}: --workers sets the processes of image mode, and this run of study {run.study} "
                         "is in measurement mode (add --mode images to render frames, or drop --workers)")
    if not study.generic_filters:
        return None
    from ..filters.navigate import WHOLE_SET_FILTERS

    names = run.filters if filters is None else check_filters(filters, f"{run.path}: --filters", study=run.study)
    whole = [name for name in names if name in WHOLE_SET_FILTERS]
    if whole and checked:
        raise InputError(f"{run.path}: --checked verifies the covariance after every record, which "
                         f"{', '.join(whole)} (a solution over the whole record set) does not have; drop one of them")
    model = getattr(run.settings, "ephemeris_model", "white")
    if whole and model != "white":
        raise InputError(f"{run.path}: {', '.join(whole)} takes the moons' ephemeris error as white noise only, and "
                         f"[settings] ephemeris_model is {model!r}; use a sequential filter or ephemeris_model = 'white'")
    return None if filters is None else names
