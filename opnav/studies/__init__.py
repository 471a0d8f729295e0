"""The scenario layer: the published studies as run files, one runner, reports.

- :mod:`opnav.studies.settings`: run files (``[scenario]``, ``[settings]``, ``[filters]``),
  validated, with ``--set KEY=VALUE`` overrides;
- one module per study (:mod:`~opnav.studies.s1`, :mod:`~opnav.studies.s2`,
  :mod:`~opnav.studies.s3`, :mod:`~opnav.studies.s4`), each a documented ``Settings`` dataclass and
  ``simulate(settings, seed) -> Simulation`` (or, for S2 and S4, ``evaluate``), seen through the
  :class:`~opnav.studies.base.Study` protocol;
- :mod:`opnav.studies.runner`: truth -> measurements -> filters -> report, stage by stage,
  each stage's output written atomically under a content hash so a re-run resumes;
- :mod:`opnav.studies.report`: ``report.md`` and a self-contained ``report.html``.

``opnav run RUNFILE`` (:mod:`opnav.commands.run`) is the command line.
"""

from .base import ModuleStudy, Study

#: study name -> :class:`~opnav.studies.base.Study` (its module imported on first use): simulating
#: studies (S1, S3) hand the runner a simulation for the generic filter stages, evaluating ones
#: (S2, S4) make their own tables; ``mission`` is any mission its run file describes (simulating).
STUDIES: dict[str, Study] = {name: ModuleStudy(name, f"{__name__}.{name}") for name in ("s1", "s2", "s3", "s4", "mission")}
