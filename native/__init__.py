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


class ChannelCore(Structure):
    """``pf_channel``: a channel's words in a shared block (``service/robot/hosted_block.py``
    ``Channel``)."""

    _fields_ = [("meta", _I64), ("sums", _I64), ("slots", _D), ("size", c_int64)]


class HostLayout(Structure):
    """``pf_host_layout``: field indices of a state row and a command row (``hosted_block``)."""

    _fields_ = [(f, c_int32) for f in ("t", "mode", "rejected", "ignored", "servo_seq", "mode_seq", "fault_ver",
                                       "error_ver", "q", "dq", "tau", "q_d", "T_meas", "T_d", "jaw", "jaw_known",
                                       "dof", "c_servo_seq", "c_mode_seq", "c_pose", "c_jaw_seq", "c_jaw")]


class HostCore(Structure):
    """``pf_host``: see ``service/robot/hosted.py`` (``RobotHost``)."""

    _fields_ = [("n", c_int64), ("S", c_int64), ("C", c_int64), ("state", ChannelCore), ("cmd", ChannelCore),
                ("ticks", _I64), ("buf", _D), ("taken", _D), ("cmds", _D), ("T_d", _D), ("q_d", _D), ("mode", _D),
                ("versions", _D), ("rejected_seen", _D), ("ws", _D), ("took", _I64), ("has_ws", _U8),
                ("latched", _U8), ("finite", _U8), ("fresh", _U8), ("L", HostLayout), ("timeout_s", c_double),
                ("rigid_tol", c_double), ("enabled_mode", c_double), ("ticks_at", c_double), ("read_at", c_double),
                ("silent", c_double), ("unread", c_double), ("ticks_last", c_int64), ("reads", c_int64),
                ("nonfinite", c_int64), ("texts", c_int64), ("staged", c_int32), ("got", c_int32), ("alive", c_int32)]


class RowField(Structure):
    """``pf_row_field`` (``tick_rows.c``): ``count`` values of type ``kind`` (``ROW_KINDS``) at
    ``src`` into a row's columns from ``col``."""

    _fields_ = [("src", c_void_p), ("col", c_int64), ("count", c_int32), ("kind", c_int32)]


#: ``RowField.kind`` of each NumPy type ``pf_row_gather`` reads
ROW_KINDS = {np.dtype(np.float64): 0, np.dtype(np.bool_): 1, np.dtype(np.uint8): 1, np.dtype(np.int64): 2,
             np.dtype(np.int32): 3, np.dtype(np.float32): 4}

#: ``pf_host_step`` / ``pf_host_sync`` flags, and ``pf_host_servo`` codes (``shm_exchange.c``)
HOST_LOST, HOST_NONFINITE, HOST_TEXTS, HOST_REFUSED = 1, 2, 4, 8
SERVO_QUEUED, SERVO_BAD_POSE, SERVO_WORKSPACE, SERVO_IGNORED, SERVO_REJECTED = 0, 1, 2, 3, 4

_T, _H, _FC, _S = POINTER(TeleopCore), POINTER(HealthCore), POINTER(ForcesCore), POINTER(StepCore)
_CH, _HO, _RF = POINTER(ChannelCore), POINTER(HostCore), POINTER(RowField)
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
    "pf_masters_take": (None, [POINTER(_D), POINTER(_D), c_int64, _D, _D, _D, _U8]),
    "pf_masters_scatter": (None, [_D, c_int64, POINTER(_D)]),
    "pf_script_at": (c_int64, [_D, _D, _D, c_int64, c_double, _D, _D]),
    "pf_pose_check": (c_int32, [c_void_p, c_double]),
    "pf_crc32": (ctypes.c_uint32, [c_void_p, c_int64]),
    "pf_chan_write": (None, [_CH, c_void_p]),
    "pf_chan_read": (c_int32, [_CH, c_void_p, c_int32]),
    "pf_host_publish": (None, [_HO]),
    "pf_host_servo": (c_int32, [_HO, c_int64, c_void_p]),
    "pf_host_step": (c_int32, [_HO, c_int64, c_double]),
    "pf_host_sync": (c_int32, [_HO, c_double]),
    "pf_host_read_poses": (None, [_HO, c_double, _D, _D, _D, _U8, _U8, _D, _U8, _D]),
    "pf_host_command": (c_int32, [_HO, _D, _U8, _I32, c_double]),
    "pf_row_gather": (None, [_RF, c_int64, _D, c_int64, c_int32]),
    "pf_neighbor_rows": (None, [c_void_p, c_void_p, c_int64, c_int64, c_void_p]),
}


def _bind(dll: ctypes.CDLL):
    for name, (res, args) in _SIGNATURES.items():
        fn = getattr(dll, name)
        fn.restype, fn.argtypes = res, args
    return dll


#: the loaded library (built on first import: ``build.py``)
lib = _bind(load())


class Functions:
    """A namespace of compiled functions called without ``argtypes`` (``fast``, ``unchecked``)."""


#: every namespace ``unchecked`` made: (namespace, raw functions, signatures)
_NAMESPACES: list = []
_checking = False


def unchecked(dll: ctypes.CDLL, signatures: dict) -> Functions:
    """The functions of ``signatures`` (name -> (restype, argtypes)) of ``dll`` for the 1 kHz
    tick's calls: without ``argtypes``, so ctypes converts no argument (the conversion through
    ``argtypes`` costs about a microsecond a call, several when the tick runs with cold caches,
    and the tick makes a dozen calls or more). Every argument must then already be what the
    signature says: a pointer (``ptr``) or ``ctypes.byref`` of the right type, a ``c_int64`` /
    ``c_double`` / ``c_void_p`` object, a Python int for ``c_int32`` and ``c_int``.
    ``check_calls()`` (the test suite runs under it) makes each function check that first."""
    ns, raw = Functions(), Functions()
    for name, (res, _) in signatures.items():
        for target in (ns, raw):
            fn = dll[name]                   # (a function object of its own: getattr's keeps its argtypes)
            fn.restype = res
            setattr(target, name, fn)
    _NAMESPACES.append((ns, raw, signatures))
    if _checking:
        _check(ns, raw, signatures)
    return ns


#: the tick core's functions for the tick's calls (see ``unchecked``)
fast = unchecked(lib, _SIGNATURES)
_BYREF = type(ctypes.byref(c_int32()))


def _fits(a, t) -> bool:
    """Whether argument ``a`` is passed as type ``t`` of a signature without conversion."""
    if isinstance(t, type(ctypes._Pointer)) and issubclass(t, ctypes._Pointer):
        return (isinstance(a, t) or (isinstance(a, _BYREF) and isinstance(a._obj, t._type_))
                or (isinstance(a, ctypes.Array) and a._type_ is t._type_))     # (an array passes its first element's address)
    if t is c_void_p:
        return isinstance(a, (c_void_p, ctypes._Pointer, _BYREF))
    if t in (c_int32, ctypes.c_int):
        return isinstance(a, t) or (type(a) in (int, bool) and -2 ** 31 <= a < 2 ** 31)
    return type(a) is t


def _check(ns: Functions, raw: Functions, signatures: dict) -> None:
    for name, (_, types) in signatures.items():
        def checked(*args, _raw=getattr(raw, name), _name=name, _types=types):
            if len(args) != len(_types):
                raise TypeError(f"{_name}: {len(args)} arguments; expected {len(_types)}")
            for i, (a, t) in enumerate(zip(args, _types)):
                if not _fits(a, t):
                    raise TypeError(f"{_name}: argument {i} is {type(a).__name__}; expected {t.__name__} "
                                    "(an unchecked call converts nothing)")
            return _raw(*args)
        setattr(ns, name, checked)


def check_calls() -> None:
    """Make every function of every ``unchecked`` namespace (those made later too) check its
    arguments against its signature before it calls the compiled code (a TypeError names the
    function and the argument); the test suite runs under it, so a call that would pass a wrong
    type fails there, not in the tick."""
    global _checking
    _checking = True
    for ns, raw, signatures in _NAMESPACES:
        _check(ns, raw, signatures)


__all__ = ["Functions", "check_calls", "fast", "unchecked", "ChannelCore", "ForcesCore", "HOST_LOST",
           "HOST_NONFINITE", "HOST_TEXTS", "HealthCore", "HostCore", "HostLayout", "NativeBuildError",
           "ROW_KINDS", "RowField", "SERVO_BAD_POSE", "SERVO_IGNORED", "SERVO_QUEUED", "SERVO_REJECTED",
           "SERVO_WORKSPACE", "StepCore", "TeleopCore", "as_array", "lib", "ptr", "ptr_to"]
