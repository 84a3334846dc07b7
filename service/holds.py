"""Why an arm holds: the hold reasons of the haptic tick, the safety invariant behind each
(``../shared/SAFETY.md``), and which of them are latched faults.

An arm holds (its force gain ramps to zero within ``force_ramp_s``, its robot keeps its
setpoint) while any reason is active. Two kinds:

* conditions clear by themselves: the arm comes back (re-anchored, S1) once the condition has
  been clear for ``recover_s`` (a late tick, a tick that ran past the watchdog's limit, frames
  too old, snapshots not published, an invalid or silent master): on a loaded machine a tick
  can be descheduled for milliseconds, and such a tick must not stop the run for good;
* faults are latched (S3): they hold until the operator clears them (``Service.clear_faults``,
  which needs every pedal up): a kernel error, an exception in the tick, a robot fault.

Reasons are the bits of ``HoldReason`` (an ``IntFlag``), one mask for all arms and one per arm
(``TickOutput.hold``, ``TickOutput.arm_hold``), recorded with every tick; ``describe(mask)`` names them with their invariants for the status.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import IntFlag


class HoldReason(IntFlag):
    """Why an arm holds: one bit per reason (``REASONS`` gives each its invariant and kind)."""

    OVERRUN = 1       #: a tick started later than ``max_lateness_s`` (S9)
    STALE = 2         #: the newest published snapshot is older than ``max_frame_age_s`` (S2)
    KERNEL = 4        #: the proxy kernel failed (S3, latched)
    MASTER = 8        #: a master's sample is invalid or missing (S6)
    ROBOT = 16        #: a robot fault or a rejected command (S3, latched)
    EXCEPTION = 32    #: an exception escaped the tick (S9, latched)
    INGEST = 64       #: frames arrive but no snapshot is published (S2)
    WATCHDOG = 128    #: a tick ran past the watchdog's limit (S9)


OVERRUN, STALE, KERNEL, MASTER, ROBOT, EXCEPTION, INGEST, WATCHDOG = HoldReason   # (short names)


@dataclass(frozen=True)
class Reason:
    bit: HoldReason
    name: str
    invariant: str   #: the SAFETY.md invariant this hold keeps
    latched: bool    #: a fault that holds until cleared (else a condition that clears by itself)


REASONS = {r.bit: r for r in (
    Reason(OVERRUN, "overrun", "S9", False),
    Reason(STALE, "frames too old", "S2", False),
    Reason(KERNEL, "kernel failure", "S3", True),
    Reason(MASTER, "master input invalid", "S6", False),
    Reason(ROBOT, "robot fault or rejected command", "S3", True),
    Reason(EXCEPTION, "tick exception", "S9", True),
    Reason(INGEST, "snapshots not published", "S2", False),
    Reason(WATCHDOG, "tick watchdog", "S9", False),
)}
#: the reasons that are latched faults (see the module docstring), as a mask
LATCHED = HoldReason(sum(b for b, r in REASONS.items() if r.latched))


def reason_names(mask: int) -> list:
    """The names of the reasons in ``mask``, in bit order."""
    return [r.name for bit, r in REASONS.items() if mask & bit]


def describe(mask: int) -> list:
    """``[{"reason", "invariant", "latched"}]`` for the reasons in ``mask`` (status, metrics)."""
    return [{"reason": r.name, "invariant": r.invariant, "latched": r.latched} for bit, r in REASONS.items()
            if mask & bit]
