"""The scenario layer: the published studies as run files, one runner, reports.

- :mod:`opnav.studies.settings`: run files (``[scenario]``, ``[settings]``, ``[filters]``),
  validated, with ``--set KEY=VALUE`` overrides;
- one module per study (:mod:`~opnav.studies.s1`, :mod:`~opnav.studies.s2`,
  :mod:`~opnav.studies.s3`, :mod:`~opnav.studies.s4`), each a documented ``Settings`` dataclass and
  ``simulate(settings, seed) -> Simulation`` (or, for S2 and S4, ``evaluate``);
- :mod:`opnav.studies.runner`: truth -> measurements -> filters -> report, stage by stage,
  each stage's output written atomically under a content hash so a re-run resumes;
- :mod:`opnav.studies.report`: ``report.md`` and a self-contained ``report.html``.

``opnav run RUNFILE`` (:mod:`opnav.commands.run`) is the command line.
"""

from . import s1, s2, s3, s4

#: study name -> module with ``Settings`` and either ``simulate`` (truth, records and navigation
#: set-up for the generic filter stages) or ``evaluate`` (its own evaluation: S2, S4).
STUDIES = {"s1": s1, "s2": s2, "s3": s3, "s4": s4}
