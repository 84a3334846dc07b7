"""Master devices: what the haptic loop reads (position, orientation, grasp, clutch, buttons) and
drives (force).

A ``Master`` is polled once per haptic tick with ``poll(t)``; afterwards ``position`` (3,),
``orientation`` (4,: a unit quaternion w, x, y, z in the master's frame; identity for a device
without one), ``grasp`` (rad: the gripper's opening, 0 for a device without one), ``clutch`` (True while the foot pedal is pressed: the master drives the robot), ``buttons`` (a
bit mask) and ``ok`` (False when the device is absent or silent) describe it. The loop hands
the force for the operator to ``send_force(f)`` (N, master frame). Positions are in the
master's own frame (m); the service maps them to the world with ``[teleop] T_world_master``
and ``scale``. Networked masters (UDP clients, issue 6) implement the same four members.

``ScriptedMaster`` plays a trajectory (times, positions, optional clutch, orientations and
grasps) with linear interpolation (normalised, for the quaternions): the dissertation's "master device simulated by a computer program" (fig. 3.8).
"""
from __future__ import annotations

import ctypes
import math
from abc import ABC, abstractmethod
from pathlib import Path

import numpy as np

from pointfence.clients.trajectory import read_trajectory, write_trajectory  # noqa: F401 (also importable here)
from pointfence.kernels.errors import InputError
from pointfence.native import fast, ptr


class Master(ABC):
    """A haptic master device as the loop sees it (see the module docstring)."""

    name: str = "master"

    def __init__(self):
        self.position = np.zeros(3)   #: master frame, m (written in place by poll)
        self.orientation = np.array([1.0, 0.0, 0.0, 0.0])   #: master frame, unit quaternion w, x, y, z
        self.grasp = 0.0              #: gripper opening, rad
        self.clutch = True            #: pedal pressed: teleoperation coupled
        self.buttons = 0
        self.ok = True                #: False: no valid sample (device absent, silent or faulty)
        self.force = np.zeros(3)      #: last force sent, N (master frame)

    @abstractmethod
    def poll(self, t: float) -> None:
        """Refresh ``position``, ``orientation``, ``grasp``, ``clutch``, ``buttons`` and ``ok`` for
        loop time ``t`` (s)."""

    def send_force(self, f: np.ndarray) -> None:
        """Display force ``f`` (3,) N (master frame) to the operator."""
        self.force[:] = f


class ScriptedMaster(Master):
    """Trajectory playback: ``times`` (N,) s increasing, ``positions`` (N, 3) m, ``clutch`` (N,)
    optional (pedal state, held from each sample to the next), ``orientations`` (N, 4) optional
    (w, x, y, z, master frame; interpolated linearly along the shorter arc and scaled to the
    samples' interpolated norm: unit between unit samples) and
    ``grasps`` (N,) optional (rad, interpolated). Before the first and after the last sample the
    end values hold. ``t0`` shifts the script in loop time. Non-finite or non-unit values are
    passed through (the loop must treat them as a device fault)."""

    name = "scripted"

    def __init__(self, times, positions, clutch=None, t0: float = 0.0, name: str = "scripted", orientations=None,
                 grasps=None):
        super().__init__()
        t = np.asarray(times, dtype=float).reshape(-1)
        p = np.asarray(positions, dtype=float)
        if t.size == 0 or p.shape != (t.size, 3):
            raise InputError(f"scripted master: {t.size} times and positions of shape {p.shape}; expected (N, 3) with N >= 1")
        if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise InputError("scripted master: times must be finite and strictly increasing (s)")
        c = np.ones(t.size, bool) if clutch is None else np.asarray(clutch).astype(bool).reshape(-1)
        if c.shape != t.shape:
            raise InputError(f"scripted master: {c.size} clutch values for {t.size} samples")
        q = None if orientations is None else np.asarray(orientations, dtype=float)
        if q is not None and q.shape != (t.size, 4):
            raise InputError(f"scripted master: orientations of shape {q.shape} for {t.size} samples; expected (N, 4) "
                             "quaternions w, x, y, z")
        g = None if grasps is None else np.asarray(grasps, dtype=float).reshape(-1)
        if g is not None and g.shape != t.shape:
            raise InputError(f"scripted master: {g.size} grasps for {t.size} samples")
        if q is not None:                    # each sample on the same hemisphere as the one before it
            q = q.copy()
            for i in range(1, len(q)):
                if np.dot(q[i], q[i - 1]) < 0:
                    q[i] = -q[i]
        self.orientations, self.grasps = q, g
        self._ql = None if q is None else q.tolist()
        self._gl = None if g is None else g.tolist()
        self.name = name
        self._ori = memoryview(self.orientation)   # (poll writes floats through it: no NumPy call)
        self.times = np.ascontiguousarray(t, np.float64)
        self.positions = np.ascontiguousarray(p, np.float64)
        self.clutches = c
        # the trajectory as the compiled look-up reads it (``pf_script_at``: the sample, the weight
        # and the interpolated position in one call, written into ``position``). ``times`` and
        # ``positions`` are fixed here; ``clutches`` is read at each poll (an operator script may
        # lift the pedal by writing it)
        self._d = np.ascontiguousarray(np.diff(p, axis=0) if t.size > 1 else np.zeros((1, 3)), np.float64)
        self._wk = np.zeros(2)                     # (w, finite) of the last look-up
        self._wkv = memoryview(self._wk)
        self._args = (ptr(self.times, np.float64, "times"), ptr(self.positions, np.float64, "positions"),
                      ptr(self._d, np.float64, "steps"), ctypes.c_int64(t.size))
        self._out = (ptr(self.position, np.float64, "position"), ptr(self._wk, np.float64, "weight"))
        self.t0 = float(t0)
        self.poll(self.t0 + t[0])

    @property
    def duration(self) -> float:
        return float(self.times[-1] - self.times[0])

    def poll(self, t: float) -> None:
        tp, pp, dp, n = self._args
        pos, wk = self._out
        i = fast.pf_script_at(tp, pp, dp, n, ctypes.c_double(t - self.t0), pos, wk)
        w = self._wkv[0]
        self.clutch = bool(self.clutches[i])
        self.ok = self._wkv[1] == 1.0
        if self._ql is not None:
            a = self._ql[i]
            if w >= 0.0:                     # normalised linear interpolation (nlerp), to the samples' norms
                b = self._ql[i + 1]
                q = [a[j] + (b[j] - a[j]) * w for j in range(4)]
                n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
                na, nb = math.sqrt(sum(v * v for v in a)), math.sqrt(sum(v * v for v in b))
                f = (na + (nb - na) * w) / n if n > 0.0 else 1.0
                q = [v * f for v in q]
            else:
                q = a
            o = self._ori
            o[0], o[1], o[2], o[3] = q[0], q[1], q[2], q[3]
        if self._gl is not None:
            g = self._gl
            self.grasp = g[i] + (g[i + 1] - g[i]) * w if w >= 0.0 else g[i]

    # --- files ---------------------------------------------------------------------------------
    @classmethod
    def from_csv(cls, path, t0: float = 0.0) -> "ScriptedMaster":
        """Read a trajectory CSV with header ``t,x,y,z`` and optionally ``clutch`` (0/1)."""
        t, p, c = read_trajectory(path)
        return cls(t, p, c, t0=t0, name=Path(path).stem)

    def to_csv(self, path) -> None:
        write_trajectory(path, self.times, self.positions, self.clutches)
