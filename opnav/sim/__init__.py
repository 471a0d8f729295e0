"""Simulation set-up: scene files, pointing laws and rendered frame sequences.

The public names are exported here (``opnav.sim.__all__``), lazily: importing
``opnav.sim`` loads nothing until a name is used.

- scenes: :func:`load_scene` reads a scene file (TOML) into a validated
  :class:`Scene` (:class:`ObserverSpec` for its observer); :func:`epochs_between`
  and :func:`observer_states` give the epochs and the observer's states;
- pointing: :class:`PointingLaw`, :func:`pointing_attitude` (where the camera looks),
  :func:`attitude_from_boresight`;
- sequences: :func:`render_sequence` renders and writes frames along a trajectory.
"""

from .. import lazy_exports

#: The public names of ``opnav.sim``, by the module that defines each (edit here when a module moves).
_EXPORTS: dict[str, tuple[str, ...]] = {
    "opnav.sim.scene": ("ObserverSpec", "Scene", "epochs_between", "load_scene", "observer_states"),
    "opnav.sim.pointing": ("PointingLaw", "attitude_from_boresight", "pointing_attitude"),
    "opnav.sim.sequence": ("render_sequence",),
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
