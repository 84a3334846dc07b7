"""The tick's health: which arms hold this tick, and why (``holds.HoldReason``).

Each tick ``assess`` turns a ``TickInput`` into hold masks: a condition seen on this tick (a late
tick, frames too old, snapshots not published, a master invalid, a robot fault) holds for
``recover_s`` after it was last seen; latched faults (``holds.LATCHED``) hold until ``clear``.
Global reasons hold every arm; master and robot reasons hold their own arm. Between ``assess``
and the end of the tick, ``hold_all`` adds a reason found later in the tick (a kernel failure,
a stall seen by the watchdog): every arm holds and decouples from then on (S3).

The watchdog's thread reports a stall with ``note_stall``; the tick takes it with
``take_stall`` (a plain attribute hand-over: one writer, one reader).

The per-tick arithmetic runs in the compiled tick core (``native/tick_core.c``, ``pf_health_*``)
on this class's arrays.
"""
from __future__ import annotations

import ctypes
import math
from typing import Optional

import numpy as np

from pointfence.native import HealthCore, fast, lib, ptr, ptr_to

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
        self._bits = np.array([int(b) for b in _ROW], np.int64)
        self._master_seen = np.full(n, -math.inf)      # per arm: master invalid
        self._robot_seen = np.full(n, -math.inf)       # per arm: robot fault or rejected command
        #: this tick's reasons per arm
        self.arm = np.zeros(n, np.int64)
        #: arms with no reason to hold this tick
        self.arm_ok = np.zeros(n, bool)
        c = self.core = HealthCore(n=self.n, reasons=len(_ROW), recover_s=self.recover_s,
                                   master_bit=int(HoldReason.MASTER), robot_bit=int(HoldReason.ROBOT))
        c.bits, c.seen = ptr(self._bits, np.int64, "bits"), ptr(self._seen, np.float64, "seen")
        c.master_seen = ptr(self._master_seen, np.float64, "master_seen")
        c.robot_seen = ptr(self._robot_seen, np.float64, "robot_seen")
        c.arm, c.arm_ok = ptr(self.arm, np.int64, "arm"), ptr(self.arm_ok, bool, "arm_ok")
        self.ref = ctypes.byref(c)
        self._stall_at: Optional[float] = None
        self.watchdog_trips = 0

    @property
    def mask(self) -> int:
        """This tick's reasons for all arms (``HoldReason`` bits)."""
        return self.core.mask

    @property
    def latched(self) -> int:
        """Latched faults (``HoldReason`` bits) until ``clear``."""
        return self.core.latched

    # --- per tick --------------------------------------------------------------------------------
    def assess(self, inp: TickInput, max_frame_age_s: float, bound: Optional[tuple] = None) -> None:
        """This tick's hold masks from its input (see the module docstring). ``bound``: the
        input's ``master_ok`` and ``robot_fault`` as pointers bound once (``native.ptr``; the
        tick's path), else they are converted here."""
        t = inp.t
        if inp.overrun:
            self._seen[_ROW[HoldReason.OVERRUN]] = t
        if inp.frame_age > max_frame_age_s:            # S2: the newest published snapshot is too old
            self._seen[_ROW[HoldReason.STALE if inp.frames_too_old else HoldReason.INGEST]] = t
        n = self.n
        ok, fault = bound if bound is not None else (ptr_to(inp.master_ok, bool, (n,), "master_ok"),
                                                     ptr_to(inp.robot_fault, bool, (n,), "robot_fault"))
        fast.pf_health_assess(self.ref, ctypes.c_double(t), ok, fault)

    def seen(self, reason: HoldReason, t: float) -> None:
        """Condition ``reason`` (a global one) was seen at loop time ``t`` (s)."""
        self._seen[_ROW[reason]] = t

    def robot_seen(self, arm: int, t: float) -> None:
        """Arm ``arm``'s robot faulted or refused a command at loop time ``t`` (s)."""
        self._robot_seen[arm] = t

    def latch(self, reason: HoldReason) -> None:
        """A fault that holds until ``clear`` (and every arm, from now on)."""
        self.core.latched |= int(reason)
        self.hold_all(reason)

    def hold_all(self, reason: HoldReason) -> None:
        """Every arm holds for ``reason`` from now on in this tick."""
        lib.pf_health_hold_all(self.ref, int(reason))

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
        self.core.latched = 0

    @property
    def latched_reasons(self) -> HoldReason:
        return HoldReason(self.latched & LATCHED)


__all__ = ["Health"]
