"""The service's devices: B haptic masters (position and pedal in, force out) and B robots
(measured pose in, command out), read into a ``TickInput`` and written from a ``TickOutput``.

CHAI3D's device abstraction: the tick never talks to a device but through ``read`` and ``write``.
A robot is any object of the ``service.robot`` interface (``measured_cp``, ``servo_cp``, ``hold``,
``resume``, ``step``, ``state``), in the loop's process or hosted in its own (``robot.hosted``);
``None`` is an ideal robot (X_r = X_r*: its position is its last command).

The masters' force sends are serialised by a lock: the tick sends, and so does the tick
watchdog's thread when a tick stalls (``send_zero_forces``).
"""
from __future__ import annotations

import math
import threading
from typing import Optional, Sequence

import numpy as np

from pointfence.kernels.errors import InputError

from .robot.base import RobotMode
from .tick_io import TickInput, TickOutput

_FAULT = RobotMode.FAULT


class Devices:
    """``masters`` (one per arm) and ``robots`` (one per arm, None: ideal)."""

    def __init__(self, masters: Sequence, robots: Sequence):
        self.masters = list(masters)
        self.robots = list(robots)
        if len(self.robots) != len(self.masters):
            raise InputError(f"{len(self.robots)} robots for {len(self.masters)} masters; expected one per master "
                             "(None: ideal robot)")
        n = self.n = len(self.masters)
        #: (index, robot) of the arms with a robot device
        self.real = [(b, r) for b, r in enumerate(self.robots) if r is not None]
        self.present = np.array([r is not None for r in self.robots], bool)
        self._all_real = len(self.real) == n
        self._T4 = np.zeros((n, 4, 4))
        self._T4_rows = list(self._T4)            # (views made once: no view per arm and tick)
        self._tips = self._T4[:, :3, 3]           # (n, 3) view: each measured pose's position
        self._tip_rows = list(self._tips)
        self._zero3 = np.zeros(3)
        self.tx_lock = threading.Lock()   #: held while forces are sent (the tick, the watchdog)
        #: arms whose robot refused this tick's command, and the setpoint it kept (world, m)
        self.refused = np.zeros(n, bool)
        self._refused_any = False
        self.kept = np.zeros((n, 3))
        self.refusals = 0
        self.last_refusal: Optional[str] = None

    # --- in ------------------------------------------------------------------------------------------
    def read_masters(self, inp: TickInput) -> None:
        """Poll every master at loop time ``inp.t``: position (master frame), pedal, validity."""
        t, pos, pedal, ok = inp.t, inp.master_pos, inp.pedal, inp.master_ok
        for b, m in enumerate(self.masters):
            m.poll(t)
            pos[b] = m.position
            pedal[b] = m.clutch
            ok[b] = m.ok
        isfinite = math.isfinite                 # valid: the device says so and every coordinate is finite
        for b, (x, y, z) in enumerate(pos.tolist()):
            if not (isfinite(x) and isfinite(y) and isfinite(z)):
                ok[b] = False

    def read_robots(self, inp: TickInput, ideal_pos: np.ndarray) -> None:
        """Every robot's measured tool tip (world) and fault state; an ideal robot's position is
        ``ideal_pos`` (its command)."""
        np.copyto(inp.robot_present, self.present)
        fault, T4 = inp.robot_fault, self._T4_rows
        for b, r in self.real:
            r.measured_cp(out=T4[b])
            fault[b] = r.state == _FAULT
        if self._all_real:
            np.copyto(inp.robot_pos, self._tips)
        else:
            np.copyto(inp.robot_pos, ideal_pos)
            for b, _ in self.real:
                inp.robot_pos[b] = self._tip_rows[b]

    def read_pedals(self, t: float, pedal: np.ndarray) -> None:
        """Only the pedals (the safe path): a master that cannot be read counts as pedal down."""
        for b, m in enumerate(self.masters):
            try:
                m.poll(t)
                pedal[b] = m.clutch
            except Exception:   # noqa: BLE001 -- unknown pedal: clearing faults stays refused
                pedal[b] = True

    # --- out -----------------------------------------------------------------------------------------
    def send_forces(self, force_master: np.ndarray) -> None:
        """(B, 3) forces in each master's frame (N)."""
        with self.tx_lock:
            for m, f in zip(self.masters, force_master):
                m.send_force(f)

    def send_zero_forces(self) -> bool:
        """Zero force on every master now (any thread). False if a send is in progress (a tick
        stuck inside one keeps the lock)."""
        if not self.tx_lock.acquire(blocking=False):
            return False
        try:
            for m in self.masters:
                m.send_force(self._zero3)
        finally:
            self.tx_lock.release()
        return True

    def command_robots(self, out: TickOutput, dt: float) -> bool:
        """Resume arms that couple, send the command to coupled arms, hold arms that decouple (they
        stop where they are), then step every robot by ``dt`` (s): every arm's command first, then
        every arm's step (a hosted arm's step sends the commands queued so far, robot/hosted.py:
        one message for the tick). A robot that refuses a command keeps its setpoint: ``refused``
        and ``kept`` say so (the tick's command follows). Returns whether any arm refused."""
        if self._refused_any:
            self.refused[:] = False
            self._refused_any = False
        coupled, engage, release = out.coupled.tolist(), out.engage.tolist(), out.release.tolist()
        command = out.command
        for b, r in self.real:
            if coupled[b]:
                if engage[b]:
                    r.resume()
                try:
                    r.servo_cp(command[b])
                except InputError as e:     # unreachable: the robot keeps its setpoint
                    self.refusals += 1
                    self.last_refusal = f"robot {b}: {e}"
                    r.setpoint_cp(out=self._T4[b])
                    self.kept[b] = self._T4[b, :3, 3]
                    self.refused[b] = True
                    self._refused_any = True
            elif release[b]:
                r.hold()
        for b, r in self.real:
            r.step(dt)
        return self._refused_any

    def hold_robots(self, dt: float, coupled: np.ndarray, command: np.ndarray) -> None:
        """The safe path: every robot holds where it is and keeps stepping; the command of an arm
        that was coupled moves onto its measured position."""
        for b, r in self.real:
            if coupled[b]:
                r.hold()
                r.measured_cp(out=self._T4[b])
                command[b] = self._T4[b, :3, 3]
            r.hold()
            r.step(dt)

    def hold_all_robots(self) -> None:
        for _, r in self.real:
            r.hold()

    def clear_robot_faults(self) -> None:
        """Re-enable robots in FAULT; they hold (their setpoint re-seats: no motion)."""
        for _, r in self.real:
            if r.state == RobotMode.FAULT:
                r.enable()
                r.hold()

    def robot_status(self) -> list:
        return [None if r is None else {"model": r.model, "mode": r.state.name, "fault": r.fault_reason,
                                        "process": "own" if getattr(r, "hosted", False) else "loop"}
                for r in self.robots]


__all__ = ["Devices"]
