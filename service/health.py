"""The tick's health: which arms hold this tick, and why (``holds.HoldReason``).

Each tick ``assess`` turns a ``TickInput`` into hold masks: a condition seen on this tick (a late
tick, frames too old, snapshots not published, a master invalid, a robot fault) holds for
``recover_s`` after it was last seen; latched faults (``holds.LATCHED``) hold until ``clear``.
Global reasons hold every arm; master and robot reasons hold their own arm. Between ``assess``
and the end of the tick, ``hold_all`` adds a reason found later in the tick (a kernel failure,
a stall seen by the watchdog): every arm holds and decouples from then on (S3).

The watchdog's thread reports a stall with ``note_stall``; the tick takes it with
``take_stall`` (a plain attribute hand-over: one writer, one reader).
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from .holds import LATCHED, REASONS, HoldReason
from .tick_io import TickInput

#: row of each global reason in the last-seen table
_ROW = {bit: i for i, bit in enumerate(REASONS)}


class Health:
    """Hold reasons of ``n`` arms; ``recover_s``: how long a condition must be clear (s)."""

    def __init__(self, n: int, recover_s: float):
        self.n = int(n)
        self.recover_s = float(recover_s)
        self._seen = np.full(len(_ROW), -math.inf)     # last loop time each global reason was seen (s)
        self._master_seen = np.full(n, -math.inf)      # per arm: master invalid
        self._robot_seen = np.full(n, -math.inf)       # per arm: robot fault or rejected command
        #: latched faults (``HoldReason`` bits) until ``clear``
        self.latched = 0
        #: this tick's reasons for all arms, and per arm
        self.mask = 0
        self.arm = np.zeros(n, np.int64)
        #: arms with no reason to hold this tick
        self.arm_ok = np.zeros(n, bool)
        self._flag = np.zeros(n, bool)
        self._since = np.zeros(n)
        self._bits = np.zeros(n, np.int64)
        self._stall_at: Optional[float] = None
        self.watchdog_trips = 0

    # --- per tick --------------------------------------------------------------------------------
    def assess(self, inp: TickInput, max_frame_age_s: float) -> None:
        """This tick's hold masks from its input (see the module docstring)."""
        t, rec = inp.t, self.recover_s
        if inp.overrun:
            self.seen(HoldReason.OVERRUN, t)
        if inp.frame_age > max_frame_age_s:            # S2: the newest published snapshot is too old
            self.seen(HoldReason.STALE if inp.frames_too_old else HoldReason.INGEST, t)
        np.logical_not(inp.master_ok, out=self._flag)
        np.copyto(self._master_seen, t, where=self._flag)
        np.copyto(self._robot_seen, t, where=inp.robot_fault)
        hold = self.latched
        for bit, i in _ROW.items():
            if t - self._seen[i] < rec:
                hold |= bit
        self.mask = int(hold)
        arm = self.arm
        self._per_arm(self._master_seen, t, HoldReason.MASTER, arm, first=True)
        self._per_arm(self._robot_seen, t, HoldReason.ROBOT, arm, first=False)
        np.bitwise_or(arm, self.mask, out=arm)
        np.equal(arm, 0, out=self.arm_ok)

    def _per_arm(self, seen, t, bit, arm, first: bool) -> None:
        np.subtract(t, seen, out=self._since)
        np.less(self._since, self.recover_s, out=self._flag)
        if first:
            np.multiply(self._flag, int(bit), out=arm)
        else:
            np.multiply(self._flag, int(bit), out=self._bits)
            np.bitwise_or(arm, self._bits, out=arm)

    def seen(self, reason: HoldReason, t: float) -> None:
        """Condition ``reason`` (a global one) was seen at loop time ``t`` (s)."""
        self._seen[_ROW[reason]] = t

    def robot_seen(self, arm: int, t: float) -> None:
        """Arm ``arm``'s robot faulted or refused a command at loop time ``t`` (s)."""
        self._robot_seen[arm] = t

    def latch(self, reason: HoldReason) -> None:
        """A fault that holds until ``clear`` (and every arm, from now on)."""
        self.latched |= int(reason)
        self.hold_all(reason)

    def hold_all(self, reason: HoldReason) -> None:
        """Every arm holds for ``reason`` from now on in this tick."""
        self.mask |= int(reason)
        np.bitwise_or(self.arm, int(reason), out=self.arm)
        self.arm_ok[:] = False

    # --- the watchdog's hand-over -------------------------------------------------------------------
    def note_stall(self, now: float) -> None:
        """(Watchdog thread.) A tick was seen running past the watchdog's limit at ``now``."""
        self._stall_at = now
        self.watchdog_trips += 1

    def take_stall(self) -> bool:
        """(Tick thread.) Whether a stall was reported since the last call."""
        if self._stall_at is None:
            return False
        self._stall_at = None
        return True

    # --- operator ------------------------------------------------------------------------------------
    def clear(self) -> None:
        """Forget latched faults and robot faults (``Service.clear_faults`` checks the pedals first)."""
        self._seen[:] = -math.inf
        self._robot_seen[:] = -math.inf
        self.latched = 0

    @property
    def latched_reasons(self) -> HoldReason:
        return HoldReason(self.latched & LATCHED)


__all__ = ["Health"]
