"""Simulation set-up: scene files, pointing laws and rendered frame sequences.

The public names are exported here (``opnav.sim.__all__``), lazily: importing
``opnav.sim`` loads nothing until a name is used.

- scenes: :func:`load_scene` reads a scene file (TOML) into a validated
  :class:`Scene` (:class:`ObserverSpec` for its observer; ``Scene.truth`` its true states);
  :func:`epochs_between` and :func:`observer_states` give the epochs and the observer's states;
  :func:`demo_scene_path` is the packaged demo scene;
- pointing: :class:`PointingLaw`, :func:`pointing_attitude` (where the camera looks),
  :func:`attitude_from_boresight`;
- the loop (:mod:`opnav.sim.loop`): :class:`Sensor` (camera, pointing or mounting, image stage
  :class:`FullFrame`, :class:`Tracking` or :class:`Limb`, random :class:`Streams`), :class:`Arc`,
  :class:`Storage`, :class:`Sky`, :class:`FrameHook`, :class:`Loop`; :func:`run_frames` renders and
  measures every frame into a :class:`LoopResult`, :func:`run_chunks` in resumable chunks and
  worker processes, :func:`render_frames` writes a scene's frames (``opnav render``),
  :func:`simulate_scene` renders and measures a scene's first frames in memory;
- checks: :func:`radec_errors`, :func:`pair_chi2`, :func:`starlight_errors`,
  :func:`misidentified_stars` compare records with the frames' truth.
"""

from .. import lazy_exports

#: The public names of ``opnav.sim``, by the module that defines each (edit here when a module moves).
_EXPORTS: dict[str, tuple[str, ...]] = {
    "opnav.sim.scene": ("ObserverSpec", "Scene", "demo_scene_path", "epochs_between", "load_scene", "observer_states"),
    "opnav.sim.pointing": ("PointingLaw", "attitude_from_boresight", "pointing_attitude"),
    "opnav.sim.sensors": ("Arc", "FrameHook", "FrameTag", "Loop", "Sensor", "Sky", "Storage", "Streams"),
    "opnav.sim.stages": ("FullFrame", "Limb", "Tracking"),
    "opnav.sim.loop": ("render_frames", "run_frames", "scene_sensor", "simulate_scene"),
    "opnav.sim.chunks": ("run_chunks",),
    "opnav.sim.results": ("LoopResult",),
    "opnav.sim.checks": ("misidentified_stars", "pair_chi2", "radec_errors", "starlight_errors"),
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
