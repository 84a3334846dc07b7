"""The haptic tick's plain data: what one tick reads (``TickInput``) and what it decides
(``TickOutput``), in the style of libfranka's ``RobotState`` and command structs.

``Service.tick`` fills a ``TickInput`` from the devices and the frame feeder, computes a
``TickOutput`` from it (``Service.step``: teleoperation, proxies, forces, holds; it touches no
device), then sends the output to the masters and robots. Recording and replay serialise these
two structs; a test can drive ``Service.step`` with inputs of its own.

Both hold preallocated arrays that every tick overwrites in place (no allocation in the tick):
copy what you keep (``TickOutput.copy()``). B is the number of arms (master-robot pairs, one
proxy each). Positions are metres, in the world frame unless said otherwise; forces newtons;
orientations unit quaternions (w, x, y, z); angles (grasp, jaw) radians.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from .holds import HoldReason


@dataclass(eq=False)
class TickInput:
    """Everything one tick reads. Build with ``TickInput.zeros(B)``."""

    n: int
    #: the loop's period index, loop time (s, ``k * period``), the time this tick advances (s),
    #: whether it started later than ``max_lateness_s``, and the clock reading at its start (s)
    k: int = 0
    t: float = 0.0
    dt: float = 0.0
    overrun: bool = False
    now: float = 0.0
    #: (B, 3) each master's sample in the master frame (m; NaN where it gave none)
    master_pos: np.ndarray = None
    #: (B,) foot pedal down (teleoperation couples the arm while it is)
    pedal: np.ndarray = None
    #: (B,) the master's sample is valid (device ok, position, orientation and grasp finite, the
    #: orientation a unit quaternion)
    master_ok: np.ndarray = None
    #: (B, 3) each robot's measured tool tip (world); an ideal robot's is its last command
    robot_pos: np.ndarray = None
    #: (B,) False for an ideal robot (X_r = X_r*, no device)
    robot_present: np.ndarray = None
    #: (B,) the robot reports a fault (``RobotMode.FAULT``)
    robot_fault: np.ndarray = None
    #: this tick's time on the frames' clock (s; NaN while unknown): motion prediction's time
    frame_time: float = math.nan
    #: age of the newest published snapshot (s), and whether that is because frames stopped
    #: arriving (True) or because they arrive but build no snapshot (False)
    frame_age: float = 0.0
    frames_too_old: bool = False
    #: control state: architecture code (1, 2, 3 = I, II, III), haptic rendering and
    #: teleoperation engaged, and a change of control law asked for from outside the tick
    architecture: int = 3
    haptics: bool = True
    teleop: bool = True
    law_change: bool = False
    #: the tick watchdog saw this tick (or the last) stall (``Health.take_stall``, taken by
    #: ``Service.step``): recorded, so that a replay holds where the run held
    watchdog_stall: bool = False
    #: (B, 4) each master's orientation in the master frame (w, x, y, z), and (B,) its grasp (rad)
    master_orientation: np.ndarray = None
    grasp: np.ndarray = None
    #: (B, 4) each robot's measured tool orientation (world, w x y z), and (B,) its measured jaw
    #: angle (rad; NaN: unknown); an ideal robot's are its last commands
    robot_orientation: np.ndarray = None
    robot_jaw: np.ndarray = None

    @classmethod
    def zeros(cls, n: int) -> "TickInput":
        z3, zb = (lambda: np.zeros((n, 3))), (lambda: np.zeros(n, bool))
        return cls(n=n, master_pos=z3(), pedal=zb(), master_ok=zb(), robot_pos=z3(), robot_present=zb(),
                   robot_fault=zb(), master_orientation=_identity(n), grasp=np.zeros(n),
                   robot_orientation=_identity(n), robot_jaw=np.zeros(n))

    def copy(self) -> "TickInput":
        return _copy(self)

    def copy_into(self, dst: "TickInput") -> None:
        """Copy this tick's values into ``dst`` (same B) without allocating."""
        _copy_into(self, dst)


@dataclass(eq=False)
class TickOutput:
    """Everything one tick decides. Build with ``TickOutput.zeros(B)``."""

    n: int
    k: int = 0
    t: float = 0.0
    #: (B, 3) the mapped master point X_m, the haptic interface point, the proxy (world, m)
    xm: np.ndarray = None
    hip: np.ndarray = None
    proxy: np.ndarray = None
    #: (B,) each proxy's contact state (kernels.proxy: 0 free, else in contact)
    state: np.ndarray = None
    #: (B, 3) force on each master in the world frame (after the hold ramp) and in its own frame (N)
    force: np.ndarray = None
    force_master: np.ndarray = None
    #: (B,) force gain in [0, 1] (ramps to zero while an arm holds)
    gain: np.ndarray = None
    #: (B, 3) robot command X_r* (world, m), sent to coupled arms
    command: np.ndarray = None
    #: (B, 3) the robot position the tick used (measured, or the command for an ideal robot)
    robot_pos: np.ndarray = None
    #: (B,) arms coupled this tick; arms that couple (resume) and that decouple (hold) on it
    coupled: np.ndarray = None
    engage: np.ndarray = None
    release: np.ndarray = None
    #: hold reasons of all arms (``HoldReason`` bits) and of each arm (B,)
    hold: int = 0
    arm_hold: np.ndarray = None
    #: the snapshot the proxies saw, and the kernel's wall-clock time this tick (us, 0: not run)
    frame_seq: int = 0
    kernel_us: float = 0.0
    #: (B, 4) commanded tool orientation (world, w x y z), sent with ``command`` as one pose
    orientation: np.ndarray = None
    #: (B,) jaw command (rad; NaN: the jaw's angle is unknown and it is not commanded): the
    #: master's grasp, clamped to the robot's jaw range and rate-limited (the grasper's input)
    jaw: np.ndarray = None

    @classmethod
    def zeros(cls, n: int) -> "TickOutput":
        z3, zb = (lambda: np.zeros((n, 3))), (lambda: np.zeros(n, bool))
        return cls(n=n, xm=z3(), hip=z3(), proxy=z3(), state=np.zeros(n, np.int32), force=z3(),
                   force_master=z3(), gain=np.zeros(n), command=z3(), robot_pos=z3(), coupled=zb(), engage=zb(),
                   release=zb(), arm_hold=np.zeros(n, np.int64), orientation=_identity(n), jaw=np.zeros(n))

    @property
    def hold_reasons(self) -> HoldReason:
        return HoldReason(self.hold)

    def copy(self) -> "TickOutput":
        return _copy(self)

    def copy_into(self, dst: "TickOutput") -> None:
        """Copy this tick's values into ``dst`` (same B) without allocating."""
        _copy_into(self, dst)


def _identity(n: int) -> np.ndarray:
    """(n, 4) identity orientations (w, x, y, z)."""
    q = np.zeros((n, 4))
    q[:, 0] = 1.0
    return q


def _copy_into(src, dst) -> None:
    arrays, scalars = _PARTS[type(src)]
    for name in arrays:
        np.copyto(getattr(dst, name), getattr(src, name))
    for name in scalars:
        setattr(dst, name, getattr(src, name))


def _copy(obj):
    """A deep copy of a tick struct (its arrays copied)."""
    kw = {f.name: (v.copy() if isinstance(v := getattr(obj, f.name), np.ndarray) else v) for f in fields(obj)}
    return type(obj)(**kw)


def _parts(cls) -> tuple:
    """(array field names, scalar field names) of a tick struct."""
    probe = cls.zeros(1)
    names = [f.name for f in fields(cls)]
    return (tuple(n for n in names if isinstance(getattr(probe, n), np.ndarray)),
            tuple(n for n in names if not isinstance(getattr(probe, n), np.ndarray)))


_PARTS = {cls: _parts(cls) for cls in (TickInput, TickOutput)}

__all__ = ["TickInput", "TickOutput"]
