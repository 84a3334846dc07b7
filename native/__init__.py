"""pointfence's compiled tick core: the per-tick arithmetic of the 1 kHz haptic tick in C
(``tick_core.c``), called through ctypes.

The Python classes that own the tick's state (``service.teleop.Teleop``,
``service.health.Health``, ``kernels.forces.ForceRenderer``, ``service.app.Service``) keep
their arrays in NumPy, allocated once, and each holds one of the structs below pointing into
them; their methods call the functions of ``lib``. There is one implementation of this
arithmetic: the C one. The structs here mirror those of ``tick_core.c`` field for field.

A NumPy call costs about a microsecond whatever the size of its (B, 3) arrays, and the tick
made a few hundred of them; the same arithmetic in C takes a few microseconds for all of it.
"""
from __future__ import annotations

import ctypes
from ctypes import POINTER, Structure, c_double, c_float, c_int32, c_int64, c_uint8, c_void_p

import numpy as np

from .build import NativeBuildError, load

_D, _U8, _I64, _I32, _F = POINTER(c_double), POINTER(c_uint8), POINTER(c_int64), POINTER(c_int32), POINTER(c_float)
_CTYPE = {np.dtype(np.float64): _D, np.dtype(np.uint8): _U8, np.dtype(np.bool_): _U8,
          np.dtype(np.int64): _I64, np.dtype(np.int32): _I32, np.dtype(np.float32): _F}


def ptr(a: np.ndarray, dtype, name: str = "array"):
    """A ctypes pointer to ``a``'s data, after checking that it is C-contiguous with ``dtype``
    (bool arrays pass as bytes). Bind once, when the array is allocated, not per tick. A struct
    field set to it holds only the address: whoever binds it keeps ``a`` alive (as an attribute)
    for as long as the struct may be used."""
    dtype = np.dtype(dtype)
    if not isinstance(a, np.ndarray) or a.dtype != dtype or not a.flags.c_contiguous:
        got = f"{a.dtype}, {'contiguous' if a.flags.c_contiguous else 'strided'}" if isinstance(a, np.ndarray) \
            else type(a).__name__
        raise TypeError(f"{name}: the tick core needs a C-contiguous {dtype} array; got {got}")
    return a.ctypes.data_as(_CTYPE[dtype])


def as_array(a, dtype, shape) -> np.ndarray:
    """``a`` itself if the core can read it as it is (C-contiguous, ``dtype``, ``shape``), else a
    converted copy (broadcast to ``shape``)."""
    dtype = np.dtype(dtype)
    if isinstance(a, np.ndarray) and a.dtype == dtype and a.shape == shape and a.flags.c_contiguous:
        return a
    return np.ascontiguousarray(np.broadcast_to(np.asarray(a, dtype), shape))


def ptr_to(a, dtype, shape, name: str = "array"):
    """``ptr`` of ``as_array(a, dtype, shape)``, for one call outside the tick's bound path (the
    pointer keeps a converted copy alive for the call)."""
    return ptr(as_array(a, dtype, shape), dtype, name)


class TeleopCore(Structure):
    """``pf_teleop``: see ``service/teleop.py``."""

    _fields_ = [("n", c_int64), ("R", c_double * 9), ("p", c_double * 3), ("scale", c_double), ("vmax", c_double),
                ("dt", c_double), ("anchor_release", c_double), ("arch", c_int32), ("rebase", c_int32),
                ("blending", c_int32), ("anchoring", c_int32),
                ("dev_prev", _D), ("X_m", _D), ("hip", _D), ("e_hip", _D), ("target", _D), ("cmd", _D),
                ("goal", _D), ("moved", _D), ("live", _U8), ("anchored", _U8), ("slip_lift", c_double), ("normals", _F),
                ("wmax", c_double), ("jaw_vmax", c_double), ("anchor_release_rad", c_double), ("qR", c_double * 4),
                ("q_last", _D), ("q_off", _D), ("q_m", _D), ("q_cmd", _D), ("ang_moved", _D), ("grasp", _D),
                ("jaw_cmd", _D), ("jaw_lo", _D), ("jaw_hi", _D), ("jaw_side", _D), ("jaw_wait", _U8)]


class HealthCore(Structure):
    """``pf_health``: see ``service/health.py``."""

    _fields_ = [("n", c_int64), ("reasons", c_int64), ("recover_s", c_double), ("master_bit", c_int64),
                ("robot_bit", c_int64), ("latched", c_int64), ("mask", c_int64), ("bits", _I64), ("seen", _D),
                ("master_seen", _D), ("robot_seen", _D), ("arm", _I64), ("arm_ok", _U8)]


class ForcesCore(Structure):
    """``pf_forces``: see ``kernels/forces.py``."""

    _fields_ = [("n", c_int64), ("cap", c_int64), ("taps_n", c_int64), ("head", c_int64), ("have_prev", c_int32),
                ("free_state", c_int32), ("dead_band", c_double), ("stiffness", c_double), ("b", c_double),
                ("rate_hz", c_double), ("max_force", c_double), ("taps", _D), ("hist", _D), ("prev", _D),
                ("raw", _D), ("forces", _D), ("sat", _U8)]


class StepCore(Structure):
    """``pf_step``: see ``service/app.py`` (``Service.step``)."""

    _fields_ = [("n", c_int64), ("master_pos", _D), ("pedal", _U8), ("master_ok", _U8), ("robot_pos", _D),
                ("coupled_prev", _U8), ("reseat", _U8), ("present", _U8), ("gain", _D), ("phip", _D),
                ("xm", _D), ("hip", _D), ("proxy", _D), ("force", _D), ("force_master", _D), ("gain_out", _D),
                ("command", _D), ("robot_pos_out", _D), ("state", _I32), ("coupled", _U8), ("engage", _U8),
                ("release", _U8), ("arm_hold", _I64), ("master_quat", _D), ("grasp", _D), ("robot_quat", _D),
                ("robot_jaw", _D), ("orientation", _D), ("jaw", _D)]


_T, _H, _FC, _S = POINTER(TeleopCore), POINTER(HealthCore), POINTER(ForcesCore), POINTER(StepCore)
_SIGNATURES = {
    "pf_teleop_map_masters": (None, [_T, _D, _D, _D, _U8, _U8]),
    "pf_teleop_update_hip": (None, [_T, _D]),
    "pf_teleop_proxy_hip": (c_void_p, [_T]),
    "pf_teleop_command_goal": (None, [_T, _F, c_int32]),
    "pf_teleop_reanchor": (None, [_T, _U8]),
    "pf_teleop_reanchor_all": (None, [_T]),
    "pf_teleop_limit_command": (None, [_T, _U8]),
    "pf_health_assess": (None, [_H, c_double, _U8, _U8]),
    "pf_health_hold_all": (None, [_H, c_int64]),
    "pf_forces_reset": (None, [_FC]),
    "pf_forces_update": (c_int32, [_FC, c_void_p, c_int32, _D, _I32]),
    "pf_step_pre": (c_int32, [_S, _T, _H, _F, c_int32, c_int32]),
    "pf_step_scale_forces": (None, [_S, _T, _FC]),
    "pf_step_post": (None, [_S, _T, _H, _FC, _F, _I32, c_int32, c_double]),
    "pf_step_publish": (None, [_S, _S]),
    "pf_quats_of_matrices": (None, [_D, c_int64, c_int64, _D]),
    "pf_poses_of": (None, [_D, _D, c_int64, _D]),
    "pf_masters_valid": (None, [_D, _D, _D, c_int64, _U8]),
    "pf_pose_check": (c_int32, [c_void_p, c_double]),
    "pf_proxy_unpack": (None, [_F, c_int64, _F, _F, _F, _I32, _I32, _U8]),
}


def _bind(dll: ctypes.CDLL):
    for name, (res, args) in _SIGNATURES.items():
        fn = getattr(dll, name)
        fn.restype, fn.argtypes = res, args
    return dll


#: the loaded library (built on first import: ``build.py``)
lib = _bind(load())

__all__ = ["ForcesCore", "HealthCore", "NativeBuildError", "StepCore", "TeleopCore", "as_array", "lib", "ptr", "ptr_to"]
