"""The robot process of a ``hosted.RobotHost``: it builds the arms and steps them on its own 1 kHz
clock, taking the service's commands from the shared block and publishing the arms' state.

Started as ``python -m pointfence.service.robot.hosted_child SHM TABLES DOF RATE PRIO PARENT Q``
(a fresh interpreter: nothing of the parent's program is imported again); it ends when told to
(``ctl["stop"]``) or when its parent is gone. Its schedule is a ``periodic.PeriodicLoop`` (the one
every 1 kHz loop of pointfence runs on): periods lost (the process was descheduled) are skipped,
the next step covers the time they spanned (``dt`` = elapsed periods), and the heartbeat
``ctl["ticks"]`` counts periods. The block's layout is robot/hosted_block.py's.
"""
from __future__ import annotations

import json
import math
import os
import sys
import time
from typing import Optional

import numpy as np

from pointfence.kernels.errors import InputError

from ..clock import RealClock
from ..periodic import PeriodicLoop
from .factory import robot_from_config
from .hosted_block import (ENABLE, FAULT, HOLD, INJECT_NAN, POISONED, RESUME, RING, Block, Commands, RowLayout,
                           attach_child, put_text)


def write_state(L: RowLayout, row: np.ndarray, text: np.ndarray, r, applied: tuple, texts: list,
                poison: bool) -> None:
    """Arm ``r``'s state into its state ``row`` (flat floats of layout ``L``; and ``text``, where a
    message changed; ``texts``: the messages last written); ``applied``: (setpoints, mode
    commands) applied so far; ``poison``: the fields ``POISONED`` as NaN (fault injection)."""
    row[L.t], row[L.mode], row[L.rejected], row[L.ignored] = r.t, int(r.state), r.rejected_commands, r.ignored_commands
    row[L.servo_seq], row[L.mode_seq] = applied
    fault, err = r.fault_reason, r.last_error
    if fault != texts[0]:
        texts[0] = fault
        put_text(text[0], fault)
        row[L.fault_ver] += 1
    if err != texts[1]:
        texts[1] = err
        put_text(text[1], err)
        row[L.error_ver] += 1
    r.copy_state(row[L.q], row[L.dq], row[L.tau], row[L.q_d], row[L.T_meas], row[L.T_d])
    jaw = r.measured_jaw() if r.jaw_limits is not None else math.nan
    known = math.isfinite(jaw)
    row[L.jaw], row[L.jaw_known] = (jaw if known else 0.0), float(known)
    if poison:
        for name in POISONED:
            row[getattr(L, name)] = math.nan


class ChildArms:
    """The arms of the robot process over block ``blk``: ``period(dt)`` applies the newest
    commands, steps every arm ``dt`` seconds and publishes their state."""

    def __init__(self, blk: Block, robots: list):
        self.blk, self.robots = blk, robots
        n = len(robots)
        self.seen = [[0, 0] for _ in robots]        # setpoints and mode commands applied, per arm
        self.jaw_seen = [0] * n                      # jaw setpoints applied, per arm
        self.texts = [[None, None] for _ in robots]
        self.state = np.zeros((n, blk.S))
        self._state_flat = self.state.reshape(-1)    # (one view: the channel looks its address up once)
        self.cmds = Commands(n)

    def publish(self) -> None:
        blk = self.blk
        first = 0          # arms whose injected NaN state goes out for the first time (a bit each)
        for b, r in enumerate(self.robots):
            nan = blk.inject[b] == INJECT_NAN
            write_state(blk.layout, self.state[b], blk.text[b], r, tuple(self.seen[b]), self.texts[b], nan)
            if nan and math.isnan(blk.inject_t[b]):
                first |= 1 << b
        blk.state.write(self._state_flat)
        if first:          # when the injection took effect: now that it is published (fault-injection benchmarks)
            t = time.perf_counter()
            for b in range(len(self.robots)):
                if first >> b & 1:
                    blk.inject_t[b] = t

    def period(self, dt: float) -> None:
        got = self.blk.cmd.read(self.cmds.rec)     # else (lapped) this period keeps the last commands
        c = self.cmds
        for b, r in enumerate(self.robots):
            seen = self.seen[b]
            n_mode = int(c.mode_seq[b]) if got else seen[1]
            while seen[1] < n_mode:
                code = int(c.ring[b, seen[1] % RING])
                if code == HOLD:
                    r.hold()
                elif code == RESUME:
                    r.resume()
                elif code == ENABLE:
                    r.enable()
                elif code == FAULT:
                    r.fault("fault requested by the service")
                seen[1] += 1
            if got and c.servo_seq[b] != seen[0]:
                seen[0] = int(c.servo_seq[b])
                try:
                    r.servo_cp(c.pose[b].reshape(4, 4))
                except InputError:
                    pass            # counted in rejected_commands, kept in last_error
            if got and c.jaw_seq[b] != self.jaw_seen[b]:
                self.jaw_seen[b] = int(c.jaw_seq[b])
                try:
                    r.servo_jaw(float(c.jaw[b]))
                except InputError:
                    pass            # (as above)
            r.step(dt)
        self.publish()


def main(shm_name: str, tables: list, dof: int, rate_hz: float, rt_priority: int, parent: int,
         start_q: Optional[list] = None) -> None:
    """Build the arms (placed at ``start_q``, one joint list or None per arm, after a restart),
    then step them until told to stop (or until the parent is gone)."""
    shm = attach_child(shm_name)
    try:
        blk = Block(shm.buf, len(tables), dof)
        robots = [robot_from_config(t) for t in tables]
        for r, q in zip(robots, start_q or []):
            # a real arm (crtk) is where it is; a simulated one is placed within its limits (a joint
            # read at a limit may lie past it by rounding)
            if q is not None and getattr(r, "simulated", True):
                r.reset(np.clip(q, *r.joint_limits))
        if rt_priority > 0:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(rt_priority)))
            except (AttributeError, OSError):
                pass
        arms = ChildArms(blk, robots)
        arms.publish()
        ctl = blk.ctl
        ctl["pid"] = os.getpid()
        ctl["ready"] = 1
        sched = PeriodicLoop(1.0 / rate_hz, RealClock(spin_s=0.0))

        def body(k: int) -> None:
            arms.period(sched.dt)
            ctl["ticks"] += sched.elapsed

        sched.run(body, keep_going=lambda: int(ctl["stop"]) == 0 and os.getppid() == parent)
    finally:
        shm.close()


if __name__ == "__main__":
    _shm, _tables, _dof, _rate, _prio, _parent, _q = sys.argv[1:8]
    main(_shm, json.loads(_tables), int(_dof), float(_rate), int(_prio), int(_parent), json.loads(_q))
