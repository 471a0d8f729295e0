"""Spacecraft and camera attitude from a CK (a SPICE C-kernel), read with spiceypy.

:func:`ck_attitude` gives ``R_icrf_frame`` (a scipy ``Rotation``, ``frame -> ICRF`` as every opnav
attitude, docs/conventions.md) of a CK frame, or of a frame an FK mounts on one (a camera), at TDB
epochs, from a :class:`~opnav.ephemeris.spice.KernelSet` holding the CK, the spacecraft's SCLK and,
for frames by name, the FK (docs/formats/ck.md).

Step by step
------------
1. **The frame.** ``frame`` is a frame name an FK defines (``"PROBE_NAVCAM"``), a frame id
   (``-77100``), or the id of a CK structure no FK names (``-77000``). A frame is walked up its
   chain of fixed (TK) frames, composing their fixed rotations (``tkfram``), until a frame of
   another class: a CK frame (class 3) is read from the CK with ``tolerance_s``; any other
   (inertial, PCK, dynamic) is oriented by SPICE's frame system (``pxform``).
2. **The clock.** A CK is indexed by spacecraft clock: each epoch is encoded in the ticks of the
   structure's clock (``ckmeta``: the FK's ``CK_<id>_SCLK``, else ``id / 1000``) with ``sce2c``,
   which needs that clock's SCLK kernel.
3. **The pointing.** ``ckgp`` gives the C-matrix (``R_frame_icrf``) at each encoded epoch: inside
   an interpolation interval of a type 2/3 segment SPICE interpolates between the pointing
   records (type 3: a constant-rate turn about one axis between two records, exact for a
   uniform spin); outside one, the record nearest within ``tolerance_s`` answers, as is.

Errors
------
Every problem ends in one :class:`~opnav.ephemeris.spice.KernelError` line naming the kernels, the
frame and CK id, and the epoch: no CK among the kernels, a frame no kernel defines, a CK id no CK
holds, no SCLK for the structure's clock, an epoch the clock cannot encode, no pointing at an epoch
(with the CK's coverage). CSPICE's own message never reaches the user.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..epochs import describe_epoch
from .spice import ICRF, KernelError, KernelSet, spice_error_type, spice_message, spiceypy_module

#: SPICE's frame classes (``frinfo``) this module treats apart: a CK-based frame and a fixed (TK) offset.
CK_CLASS, TK_CLASS = 3, 4
#: A frame chain longer than this is refused (SPICE's own limit on frame-chain length is 10).
MAX_CHAIN = 10


def _cyice():
    """spiceypy's Cython functions (one C loop over epochs), imported on first use."""
    import spiceypy.cyice

    return spiceypy.cyice


def ck_attitude(kernels: KernelSet, frame: str | int, t: float | np.ndarray, *,
                tolerance_s: float = 0.0) -> Rotation:
    """``R_icrf_frame``: the attitude of ``frame`` (``frame -> ICRF``) from a CK at TDB epochs ``t``.

    Parameters
    ----------
    kernels : KernelSet
        The CK, the SCLK of its spacecraft clock, and (for frames by name) the FK.
    frame : str or int
        A frame name an FK defines, a frame id, or a CK structure id (module notes, step 1).
    t : float or (N,) array
        TDB seconds past J2000.
    tolerance_s : float, keyword-only
        Outside the CK's interpolation intervals, a pointing record this near (s) answers; 0
        (default): interpolated pointing only.

    Returns
    -------
    Rotation
        ``frame -> ICRF``; one rotation for a scalar ``t``, N for (N,). ``R.apply(v_frame)`` gives
        ``v_icrf``; ``R.inv()`` is the CK's C-matrix (ICRF -> frame).

    Raises
    ------
    KernelError
        One line naming the kernels, the frame and the epoch (module notes).
    """
    t_arr = np.atleast_1d(np.asarray(t, dtype=float))
    if t_arr.ndim != 1 or t_arr.size == 0:
        raise KernelError(f"epochs t must be a scalar or a non-empty 1-D array, got shape {np.shape(t)}")
    if not np.all(np.isfinite(t_arr)):
        raise KernelError("epoch t is NaN or infinite")
    if not (np.isfinite(tolerance_s) and tolerance_s >= 0.0):
        raise KernelError(f"tolerance_s must be >= 0 s, got {tolerance_s!r}")
    with kernels.loaded():
        base, base_class, ck_id, R_base_frame = _chain(kernels, frame)
        if base_class == CK_CLASS or base is None:
            R_icrf_base = _ck_pointing(kernels, frame, ck_id, t_arr, tolerance_s)
        else:
            R_icrf_base = _frame_system(kernels, frame, base, t_arr)
    attitude = R_icrf_base * Rotation.from_matrix(R_base_frame)
    return attitude[0] if np.ndim(t) == 0 else attitude


def _chain(kernels: KernelSet, frame: str | int) -> tuple[str | None, int, int, np.ndarray]:
    """``(base frame name, its class, its CK id, R_base_frame)``: ``frame`` walked up its fixed (TK)
    offsets to the first frame of another class; ``(None, CK_CLASS, id, I)`` for a CK id no FK names."""
    sp = spiceypy_module()
    code, name = _frame_code(frame)
    if code == 0:
        if isinstance(name, int):  # a CK structure id without a frame: its pointing relative to ICRF
            return None, CK_CLASS, name, np.eye(3)
        raise KernelError(f"frame {name!r} is not defined by kernels {kernels.names()}: give a frame an FK defines, "
                          "a frame id, or a CK id")
    R_base_frame = np.eye(3)
    for _ in range(MAX_CHAIN):
        with sp.no_found_check():
            _, frame_class, class_id, found = sp.frinfo(code)
        if not found:
            raise KernelError(f"frame {frame!r}: kernels {kernels.names()} do not describe frame id {code}")
        if frame_class != TK_CLASS:
            return sp.frmnam(code), int(frame_class), int(class_id), R_base_frame
        try:
            with sp.no_found_check():
                rotation, parent, found = sp.tkfram(int(class_id))
        except spice_error_type() as exc:
            raise KernelError(f"frame {frame!r}: kernels {kernels.names()} define fixed frame {sp.frmnam(code)} "
                              f"badly: {spice_message(exc)}") from None
        if not found:
            raise KernelError(f"frame {frame!r}: kernels {kernels.names()} give no TKFRAME_{class_id}_* "
                              f"offset for fixed frame {sp.frmnam(code)}")
        # tkfram's matrix turns vectors of the frame into its parent's: R_parent_frame
        R_base_frame = np.asarray(rotation, dtype=float) @ R_base_frame
        code = int(parent)
    raise KernelError(f"frame {frame!r}: kernels {kernels.names()} chain more than {MAX_CHAIN} fixed frames")


def _frame_code(frame: str | int) -> tuple[int, str | int]:
    """``(SPICE frame code or 0, frame as given: an int for an id)``; inside ``kernels.loaded()``."""
    sp = spiceypy_module()
    if isinstance(frame, (int, np.integer)) and not isinstance(frame, bool):
        code = int(frame)
    elif isinstance(frame, str) and frame.strip().lstrip("+-").isdigit():
        code = int(frame.strip())
    else:
        return int(sp.namfrm(str(frame).strip())), str(frame)
    return (code if sp.frmnam(code) else 0), code


def _ck_pointing(kernels: KernelSet, frame, ck_id: int, t: np.ndarray, tolerance_s: float) -> Rotation:
    """``R_icrf_ck`` of CK structure ``ck_id`` at ``t`` (module notes, steps 2 and 3)."""
    sp = spiceypy_module()
    cks = kernels.of_type("CK")
    what = f"CK id {ck_id}" if str(frame).strip() == str(ck_id) else f"frame {frame!r} (CK id {ck_id})"
    if not cks:
        raise KernelError(f"kernels {kernels.names()} hold no CK (a binary DAF/CK file): no attitude for {what}")
    held = sorted({int(i) for path in cks for i in sp.ckobj(str(path))})
    if ck_id not in held:
        raise KernelError(f"{what} is in no CK of kernels {kernels.names()}; the CKs hold CK ids "
                          f"{', '.join(map(str, held)) or 'none'}")
    clock = int(sp.ckmeta(ck_id, "SCLK"))
    if clock == 0:
        raise KernelError(f"{what}: kernels {kernels.names()} name no spacecraft clock for CK id {ck_id} "
                          f"(an FK's CK_{ck_id}_SCLK; an id above -1000 implies none)")
    ticks = _encode(kernels, what, clock, t)
    tolerance_ticks = 0.0
    if tolerance_s > 0.0:
        tolerance_ticks = float(np.max(_encode(kernels, what, clock, t + tolerance_s) - ticks))
    # one scalar call per epoch: spiceypy 8.3's vectorised ckgp_v writes each 4-byte found flag into a
    # 1-byte array slot, past the array's end (heap corruption)
    ckgp = _cyice().ckgp_s
    matrices, found = np.empty((ticks.size, 3, 3)), np.empty(ticks.size, dtype=bool)
    try:
        with sp.no_found_check():
            for k, tick in enumerate(ticks):
                matrices[k], _, found[k] = ckgp(ck_id, float(tick), tolerance_ticks, ICRF)
    except spice_error_type() as exc:
        raise KernelError(f"kernels {kernels.names()} cannot give the pointing of {what} near "
                          f"{describe_epoch(t[0])}: {spice_message(exc)}") from None
    if not found.all():
        raise KernelError(f"kernels {kernels.names()} have no pointing for {what} at "
                          f"{describe_epoch(t[np.argmin(found)])} (tolerance {tolerance_s:g} s); "
                          f"coverage: {_coverage(cks, ck_id)}")
    # ckgp's C-matrix turns ICRF vectors into the frame: R_frame_icrf; opnav's attitude is its inverse
    return Rotation.from_matrix(matrices).inv()


def _encode(kernels: KernelSet, what: str, clock: int, t: np.ndarray) -> np.ndarray:
    """Epochs ``t`` (TDB s) as continuous encoded ticks of spacecraft clock ``clock``."""
    try:
        return np.asarray(_cyice().sce2c_v(clock, np.array(t, order="C")), dtype=float).reshape(-1)
    except spice_error_type() as exc:
        if getattr(exc, "short", "") == "SPICE(KERNELVARNOTFOUND)":
            raise KernelError(f"kernels {kernels.names()} hold no SCLK for spacecraft clock {clock} "
                              f"(needed by {what}): load the spacecraft's SCLK kernel (.tsc)") from None
        if getattr(exc, "short", "") == "SPICE(MISSINGTIMEINFO)":
            raise KernelError(f"spacecraft clock {clock} of kernels {kernels.names()} keeps TT, not TDB (needed by "
                              f"{what}): load a leapseconds kernel (.tls) for TDB to TT") from None
        sp = spiceypy_module()
        bad = float(t[0])
        for epoch in t:  # the error path only: the first epoch the clock cannot encode
            try:
                sp.sce2c(clock, float(epoch))
            except spice_error_type():
                bad = float(epoch)
                break
        raise KernelError(f"spacecraft clock {clock} of kernels {kernels.names()} cannot encode "
                          f"{describe_epoch(bad)} (for {what}): {spice_message(exc)}") from None


def _coverage(cks, ck_id: int) -> str:
    """The interpolation intervals of ``ck_id`` in each CK, for messages (at most 4 listed per file)."""
    sp = spiceypy_module()
    spans = []
    for path in cks:
        window = sp.ckcov(str(path), ck_id, False, "INTERVAL", 0.0, "TDB")
        count = sp.wncard(window)
        for k in range(min(count, 4)):
            a, b = sp.wnfetd(window, k)
            spans.append(f"{path.name} {describe_epoch(a)} to {describe_epoch(b)}")
        if count > 4:
            spans.append(f"{path.name}: {count - 4} more intervals")
    return "; ".join(spans) or "none"


def _frame_system(kernels: KernelSet, frame, base: str, t: np.ndarray) -> Rotation:
    """``R_icrf_base`` of a non-CK frame through SPICE's frame system."""
    try:
        matrices = _cyice().pxform_v(base, ICRF, np.array(t, order="C"))
    except spice_error_type() as exc:
        raise KernelError(f"kernels {kernels.names()} cannot orient frame {frame!r} (through {base}) near "
                          f"{describe_epoch(t[0])}: {spice_message(exc)}") from None
    return Rotation.from_matrix(np.asarray(matrices, dtype=float).reshape(-1, 3, 3))


__all__ = ["ck_attitude"]
