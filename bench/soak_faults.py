"""The faults, attacks and operator actions of ``pointfence bench soak``, each with the contract
of ``../shared/SAFETY.md`` it is judged by (``bench/soak_check.py`` judges it on the recording).

A ``Fault`` has a kind:

* ``"fault"``: the affected arms must hold within one tick of the fault being detectable (the
  hold bit ``bit`` in their recorded hold mask), their force ramp to zero within
  ``force_ramp_s``, the robots move <= 0.1 mm while held, a latched fault stays until it is
  cleared, and the run recovers after the fault is removed (and, if latched, cleared);
* ``"attack"``: refused and counted; nothing changes: no hold, no session lost;
* ``"action"``: an operator action, or a forbidden request: it moves no robot by itself
  (<= 0.1 mm while the operator holds still), and a forbidden request is refused and changes
  nothing.

``inject(rig, ev)`` makes the fault happen and returns when it should be judged over; it notes
tick numbers in ``ev`` (an ``Event``): ``inject`` (the fault starts), ``restore`` (the cause is
gone), and checks that can only be made live (HTTP answers) in ``ev.failures``.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

from pointfence.kernels.errors import KernelError
from pointfence.service.holds import INGEST, KERNEL, MASTER, ROBOT, STALE, WATCHDOG
from pointfence.service.robot.hosted import NONFINITE

from .soak_check import AVAILABILITY


@dataclass
class Event:
    """One injected fault and what happened (tick numbers of the loop)."""

    name: str
    inject: Optional[int] = None
    restore: Optional[int] = None
    clear: Optional[int] = None          # tick of the successful clear-faults (latched faults)
    recovered: Optional[int] = None      # first tick with every arm coupled and nothing holding
    notes: dict = field(default_factory=dict)
    failures: list = field(default_factory=list)   # (invariant, what) found live


@dataclass(frozen=True)
class Fault:
    name: str
    kind: str                  # "fault" | "attack" | "action"
    invariant: str
    inject: Callable
    bit: int = 0               # the hold reason a fault must show
    arms: tuple = (0, 1)       # the arms it affects
    latched: bool = False      # holds until clear-faults (pedals up)
    detect_s: object = 0.0     # detectable this long after the injection (s; "robot_watchdog": its timeout)
    still: bool = False        # an action done while the operator holds still: nothing may move


#: how long an injected hung kernel call blocks the tick (s): well past the tick watchdog's limit
HANG_S = 0.03


class FaultyBatch:
    """The service's proxy batch with an injected kernel fault: ``"raise"`` (every step raises
    KernelError) or ``"hang"`` (the next step blocks ``hang_s``, as a hung device call)."""

    def __init__(self, batch, mode: str, hang_s: float = HANG_S):
        self._batch, self.mode, self.hang_s = batch, mode, hang_s

    def __getattr__(self, name):
        return getattr(self._batch, name)

    def step(self, *a, **kw):
        if self.mode == "raise":
            raise KernelError("injected kernel failure (bench soak)")
        if self.mode == "hang":
            self.mode = "done"
            time.sleep(self.hang_s)
        return self._batch.step(*a, **kw)

    @property
    def original(self):
        return self._batch


class FailingFilter:
    """The frame feeder's filter with an injected ingest failure: an exception on every build
    (``RuntimeError``), or the ingest thread's death (``ThreadDeath``, not an ``Exception``)."""

    class ThreadDeath(BaseException):
        pass

    def __init__(self, inner, die: bool):
        self.inner, self.die = inner, die

    def __call__(self, frames):
        if self.die:
            raise FailingFilter.ThreadDeath("injected ingest thread death (bench soak)")
        raise RuntimeError("injected ingest failure (bench soak)")

    def status(self):
        return self.inner.status() if self.inner is not None else {}


# --- the injections -----------------------------------------------------------------------------------
def _camera_stall(rig, ev):
    ev.inject = rig.tick()
    rig.stall_cameras(True)
    rig.sleep(rig.max_age + 0.4)
    rig.stall_cameras(False)
    ev.restore = rig.tick()


def _ingest(die: bool):
    def run(rig, ev):
        feeder = rig.run.frames
        inner = feeder.frame_filter
        ev.inject = rig.tick()
        feeder.frame_filter = FailingFilter(inner, die)
        rig.sleep(rig.max_age + 0.4)
        feeder.frame_filter = inner
        ev.restore = rig.tick()
        ev.notes["ingest_status"] = feeder.status(rig.now()).get("ingest")
    return run


def _kernel(mode: str):
    def run(rig, ev):
        ev.inject = rig.in_tick(lambda s: setattr(s.scene, "batch", FaultyBatch(s.scene.batch, mode)))
        rig.sleep(0.3)
        if mode == "hang":
            wd = rig.run.loop.watchdog
            ev.notes["watchdog_seen_after_ms"] = round(1e3 * wd.last_stall_s, 3) if wd is not None else None
        ev.restore = rig.in_tick(lambda s: setattr(s.scene, "batch", s.scene.batch.original))
    return run


def _device(cmd: str, seconds: float):
    def run(rig, ev):
        ev.inject = rig.tick()
        rig.devices(cmd, 0, seconds)
        rig.sleep(seconds)
        ev.restore = rig.tick()
        rig.sleep(0.3)
    return run


def _flood(kind: str):
    def run(rig, ev):
        before = rig.hub.status()["rejected_total"]
        ages = rig.hub.ages.counts()
        ev.inject = rig.tick()
        sent = rig.flood(kind, seconds=1.0)
        ev.restore = rig.tick()
        # how old the master samples were that the ticks used during the flood (kernel arrival -> tick)
        ev.notes["state_age_ms"] = rig.hub.ages.summary([b - a for a, b in zip(ages, rig.hub.ages.counts())])
        end = time.monotonic() + 5.0     # an overloaded receiver works through its socket's backlog
        while True:
            rig.sleep(0.2)
            rejected = rig.hub.status()["rejected_total"] - before
            if rejected > 0 or time.monotonic() > end:
                break
        ev.notes.update(sent=sent, rejected=rejected)
        if rejected <= 0:   # none reached the receiver (dropped by the kernel or still queued): nothing was
            # accepted either (the judge checks the masters), so this is the link's availability, not S6
            ev.failures.append((AVAILABILITY, f"{kind} flood of {sent} datagrams: none counted as rejected "
                                              "within 5 s (the receiver behind under load)"))
    return run


def _robot(kind: str):
    def run(rig, ev):
        host = rig.run.robot_host
        ev.inject = rig.tick()
        host.inject(kind, 0 if kind == "nan" else None)
        if kind == "nan":
            # the fault went in when the robot process published it (its own period, at its own
            # priority: the request may wait there for milliseconds); the tick due just before
            # that is the first that can have seen it (started late). A stop or a kill is the
            # signal itself
            end = time.monotonic() + 0.3
            while not math.isfinite(host.injected_at(0)) and time.monotonic() < end:
                rig.sleep(0.0005)
            if math.isfinite(host.injected_at(0)):
                ev.inject = max(ev.inject, rig.tick_at(host.injected_at(0)))
        rig.sleep(0.3)
        if kind == "kill":
            host.restart()
        else:
            host.inject("none")
        if kind == "nan":
            # the fault is gone once the service has read a finite state of the arm again: the
            # robot process publishes one in its next period (at normal priority: milliseconds
            # on a loaded machine), and an operator's clear before that is refused for the arm
            # (HostedRobot.enable: not ready), as it should be
            end = time.monotonic() + 2.0
            while (host.ready(0) or "").startswith(NONFINITE) and time.monotonic() < end:
                rig.sleep(0.001)
        ev.restore = rig.tick()
    return run


def _haptics_off(rig, ev):
    rig.devices("freeze", True)
    rig.sleep(0.2)
    ev.inject = rig.tick()
    rig.ctl.engage("haptics", False)
    rig.sleep(0.5)
    rig.ctl.engage("haptics", True)
    rig.sleep(0.5)
    ev.restore = rig.tick()
    rig.devices("freeze", False)


def _arch_switch(rig, ev):
    rig.devices("freeze", True)
    rig.sleep(0.2)
    ev.inject = rig.tick()
    for a in ("I", "II", "III"):
        rig.ctl.set_architecture(a)
        rig.sleep(0.3)
    ev.restore = rig.tick()
    rig.devices("freeze", False)


def _unauthenticated(rig, ev):
    before = rig.svc.status()
    ev.inject = rig.tick()
    for path, body, auth in (("/haptics", {"engaged": False}, False), ("/architecture", {"architecture": "I"}, "Bearer 0"),
                             ("/radius", {"radius": 0.001}, False), ("/clear-faults", {}, False)):
        code = rig.raw_control("POST", path, body, auth)
        if code not in (401, 403):
            ev.failures.append(("S4", f"unauthenticated POST {path} answered {code}, not 401/403"))
    rig.sleep(0.1)
    ev.restore = rig.tick()
    after = rig.svc.status()
    for key in ("haptics", "architecture", "teleop"):
        if before[key] != after[key]:
            ev.failures.append(("S4", f"an unauthenticated request changed {key}: {before[key]} -> {after[key]}"))
    if rig.svc.pipeline.params.radius.r_base != rig.radius:
        ev.failures.append(("S4", "an unauthenticated request changed the radius"))


def _clear_while_coupled(rig, ev):
    ev.inject = rig.in_tick(lambda s: setattr(s.scene, "batch", FaultyBatch(s.scene.batch, "raise")))
    rig.sleep(0.2)
    rig.in_tick(lambda s: setattr(s.scene, "batch", s.scene.batch.original))
    pedals = rig.svc.status()["pedal"]
    if not all(pedals):      # a device's session lapsed under load: its pedal reads up, a clear would be right
        ev.failures.append((AVAILABILITY, f"fault_cleared_while_coupled: not tried, a device's pedal was not down "
                                          f"(its link lost under load): pedals {pedals}"))
        ev.restore = rig.tick()
        return
    code = rig.raw_control("POST", "/clear-faults", {}, True)     # the pedals are down
    rig.sleep(0.1)
    if code != 409:
        ev.failures.append(("S3", f"clear-faults with the pedals down answered {code}, not 409"))
    if not rig.svc.status()["latched_faults"]:
        ev.failures.append(("S3", "clear-faults with the pedals down cleared the latched fault"))
    ev.restore = rig.tick()


FAULTS = {f.name: f for f in (
    Fault("camera_stall", "fault", "S2", _camera_stall, bit=STALE),
    Fault("ingest_exception", "fault", "S2", _ingest(False), bit=INGEST),
    Fault("ingest_thread_death", "fault", "S9", _ingest(True), bit=INGEST, latched=True),
    Fault("kernel_exception", "fault", "S3", _kernel("raise"), bit=KERNEL, latched=True),
    Fault("kernel_hang", "fault", "S9", _kernel("hang"), bit=WATCHDOG),
    Fault("client_silence", "fault", "S9", _device("silence", 0.2), bit=MASTER, arms=(0,), detect_s=0.06),
    Fault("nan_master", "fault", "S6", _device("nan", 0.2), bit=MASTER, arms=(0,), detect_s=0.06),
    Fault("forged_flood", "attack", "S6", _flood("forged")),
    Fault("replayed_flood", "attack", "S6", _flood("replay")),
    Fault("robot_process_kill", "fault", "S9", _robot("kill"), bit=ROBOT, latched=True, detect_s="robot_watchdog"),
    Fault("robot_process_stall", "fault", "S9", _robot("stall"), bit=ROBOT, latched=True, detect_s="robot_watchdog"),
    Fault("robot_state_nan", "fault", "S3", _robot("nan"), bit=ROBOT, arms=(0,), latched=True, detect_s=0.002),
    Fault("haptics_off_while_pushing", "action", "S1", _haptics_off, still=True),
    Fault("architecture_switch_while_pushing", "action", "S1", _arch_switch, still=True),
    Fault("unauthenticated_control_request", "action", "S4", _unauthenticated),
    Fault("fault_cleared_while_coupled", "fault", "S3", _clear_while_coupled, bit=KERNEL, latched=True),
)}
