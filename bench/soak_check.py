"""Judging a soak run's recording against the contract of each injected fault
(``soak_faults``; ``../shared/SAFETY.md``). Everything here reads the streamed recording
(``service/record.load_recording``): per tick its number, frame age, every master's validity,
every arm's X_r and X_r*, arm 0's force and every arm's hold mask.
"""
from __future__ import annotations

import numpy as np

from pointfence.service.holds import INGEST, MASTER, OVERRUN, ROBOT, STALE, WATCHDOG, reason_names

#: robot motion allowed while an arm holds, and by an operator action alone (m)
MAX_HOLD_MOTION = 1e-4
#: a held arm's motion is judged once it has stopped: this long after the hold (s). Its stop
#: from the speed it had (a Raven II sliding along the fixture at up to max_robot_speed) is
#: reported as the stopping distance
STOP_S = 0.02
#: penetration of the forbidden region allowed anywhere in the run (m)
MAX_PENETRATION = 1e-3
#: a fault must hold its arms within this many ticks of becoming detectable
HOLD_TICKS = 1
#: holds that the machine's load causes (a late or long tick), whatever is injected: during an
#: attack or an operator action they are counted (``timing_holds``), not held against it
TIMING = OVERRUN | WATCHDOG
#: holds that an overloaded machine causes by itself, each as its invariant wants: late ticks, a
#: device session dropped, snapshots not built in time (S2). During an attack or an operator
#: action they are the service's availability, reported apart; any other hold breaks the contract
LOAD = TIMING | MASTER | INGEST | STALE
#: the invariant named for a device session lost during an attack or an operator action: the
#: arm held for it, as S9 wants, but the link was not available (on an overloaded machine the
#: receiver falls behind the 50 ms session timeout); reported apart from the safety contract
AVAILABILITY = "S9 (availability)"
#: the names of the LOAD reasons, as the service's status gives them
_LOAD_NAMES = set(reason_names(LOAD))


#: failures that are a measured bound (latency, motion, ramp time) exceeded: the contract kept
#: in kind, missed in degree; on a loaded machine they come and go with its load
_BOUND_MARKS = (" ms after the fault was detectable", " mm while held", "force not zero within",
                "while the operator held still")


def _unrecovered(fault, ev) -> tuple:
    """The run did not come back within the wait after the fault was removed (and cleared). If
    nothing latched stayed and every arm still holding held only for load (late ticks, a device
    link lost, snapshots late), the service did what S9 and S2 want on an overloaded machine:
    availability; anything else (a fault still latched after a clear, another reason) breaks the
    contract."""
    left = ev.notes.get("unrecovered") if isinstance(ev.notes, dict) else None
    what = f"{fault.name}: the run did not recover after the fault was removed"
    if _pedals_unread(ev):
        return AVAILABILITY, f"{what} (the pedals never read up: not cleared)"
    if left is None:
        return fault.invariant, what
    reasons = set(left.get("hold", [])) | {r for arm in left.get("arms_holding", []) for r in arm}
    if load_only({"hold": left.get("hold", []), "arms_holding": left.get("arms_holding", []),
                  "latched_faults": left.get("latched")}):
        return AVAILABILITY, f"{what} (still holding for load only: {sorted(reasons) or 'a device not coupled'})"
    return fault.invariant, f"{what} (holding: {sorted(reasons)}, latched: {left.get('latched')})"


def _pedals_unread(ev) -> bool:
    """The operator's clear was never tried: the service never read the pedals up (soak._recover)."""
    return isinstance(ev.notes, dict) and bool(ev.notes.get("pedals_unread"))


def load_only(status: dict) -> bool:
    """Whether a ``Service.status()`` holds for load alone: nothing latched, and every reason any
    arm holds for is a LOAD one (an arm merely not coupled counts as a device link lost)."""
    reasons = set(status.get("hold", [])) | {r for arm in status.get("arms_holding", []) for r in arm}
    return not status.get("latched_faults") and reasons <= _LOAD_NAMES


def failure_class(invariant: str, what: str) -> str:
    """``"availability"`` (a session or the frames' freshness lost under load, held for as the
    invariant wants), ``"bound"`` (a measured bound exceeded) or ``"contract"`` (a fault not
    held, not latched, not cleared, not recovered from; an attack or request not refused)."""
    if invariant == AVAILABILITY:
        return "availability"
    return "bound" if any(m in what for m in _BOUND_MARKS) else "contract"


class Recording:
    """The recorded arrays, indexed by tick number."""

    def __init__(self, data: dict, rate_hz: float):
        self.k = data["inputs"][:, 0].astype(np.int64)
        self.age = data["inputs"][:, 3]
        self.law = data["inputs"][:, 4:7]          # architecture, haptics on, teleoperation on
        self.ok = data["masters"][:, :, 4] > 0.5
        self.xr = data["robots"][:, :, :3]
        self.cmd = data["robots"][:, :, 3:]
        self.force0 = np.linalg.norm(data["rows"][:, 16:19], axis=1)
        self.arm_hold = data["holds"][:, 1:].astype(np.int64)
        self.t = data["rows"][:, 0]
        self.ms = 1e3 / rate_hz

    def at(self, tick) -> int:
        """Row of the first recorded tick >= ``tick`` (len when none)."""
        return int(np.searchsorted(self.k, tick, side="left")) if tick is not None else len(self.k)


def judge(fault, ev, rec: Recording, max_age: float, force_ramp_s: float, robot_watchdog_s: float = 0.05) -> dict:
    """Failures ``[(invariant, what)]`` of one event, with its figures."""
    fails = list(ev.failures)
    out = {"fault": fault.name, "kind": fault.kind, "invariant": fault.invariant,
           "ticks": {"inject": ev.inject, "restore": ev.restore, "clear": ev.clear, "recovered": ev.recovered}}
    i0 = rec.at(ev.inject)
    if ev.inject is None or i0 >= len(rec.k):
        fails.append((fault.invariant, "the injection is not in the recording"))
        return {**out, "failures": fails}
    if fault.kind == "fault":
        fails += _judge_fault(fault, ev, rec, i0, max_age, force_ramp_s, robot_watchdog_s, out)
    else:
        i1 = rec.at(ev.restore)
        if fault.kind == "attack":
            i1 = rec.at(ev.restore + 200)
        masks = rec.arm_hold[i0:i1]
        out["timing_holds"] = int((masks & TIMING).any(axis=1).sum())
        out["load_holds"] = int((masks & LOAD).any(axis=1).sum())
        if (masks & (INGEST | STALE)).any():
            fails.append((AVAILABILITY, f"{fault.name}: snapshots too old during it (held, S2)"))
        lost = np.flatnonzero(~rec.ok[i0:i1].all(axis=1))
        out["input_lost_ticks"] = int(len(lost))
        if len(lost):       # a device's session dropped (held for it, S9): the link's availability
            fails.append((AVAILABILITY, f"{fault.name}: a device's input was lost at tick {rec.k[i0 + lost[0]]} "
                                        f"({len(lost)} ticks)"))
        held = np.flatnonzero((masks & ~LOAD).any(axis=1))
        if len(held):
            first = i0 + int(held[0])
            stall = _stall_ms(rec, first, robot_watchdog_s)
            if not (masks[held[0]] & ~(LOAD | ROBOT)).any() and stall >= robot_watchdog_s * 1e3 - 10.0:
                # the loop did not run for about the robot's command watchdog just before: the
                # robot stopped because its commands stopped (S9 as designed), whatever ran then
                fails.append((AVAILABILITY, f"{fault.name}: a robot's command watchdog held an arm at tick "
                                            f"{rec.k[first]} after the loop did not run for {stall:.0f} ms"))
            else:
                fails.append((fault.invariant, f"{fault.kind} {fault.name}: an arm held at tick {rec.k[first]} "
                                               f"(mask {int(masks[held[0]].max())})"))
        if fault.still:     # from the tick the action took effect (its request is applied between ticks)
            changed = np.flatnonzero((rec.law[i0:i1] != rec.law[i0]).any(axis=1))
            i0 = i0 + int(changed[0]) - 1 if len(changed) else i0
            # S1 is about the command: the arm itself may still settle onto a command that did
            # not move (a Raven II lags its command by up to a tenth of a millimetre)
            moved = max(float(np.linalg.norm(rec.cmd[i0:i1, b] - rec.cmd[i0, b], axis=1).max()) for b in (0, 1))
            settle = max(float(np.linalg.norm(rec.xr[i0:i1, b] - rec.xr[i0, b], axis=1).max()) for b in (0, 1))
            out["robot_motion_mm"] = round(moved * 1e3, 4)
            out["robot_settling_mm"] = round(settle * 1e3, 4)
            if moved > MAX_HOLD_MOTION:
                fails.append(("S1", f"{fault.name} moved a robot's command {moved * 1e3:.3f} mm while the "
                                    "operator held still"))
    if ev.recovered is None:
        fails.append(_unrecovered(fault, ev))
    return {**out, "failures": fails, **{k: v for k, v in ev.notes.items() if k != "ingest_status"}}


def _judge_fault(fault, ev, rec, i0, max_age, force_ramp_s, robot_watchdog_s, out) -> list:
    fails = []
    bit, ms = fault.bit, rec.ms
    # when the fault became detectable: frames older than max_age, a master's input invalid, or
    # the injection itself (plus the detector's own bound: a robot process's watchdog)
    end = rec.at(ev.clear if ev.clear is not None else ev.restore)
    if fault.name in ("camera_stall", "ingest_exception", "ingest_thread_death"):
        late = np.flatnonzero(rec.age[i0:] > max_age)
        onset = i0 + int(late[0]) if len(late) else None
        bound = HOLD_TICKS
    elif bit == MASTER:
        bad = np.flatnonzero(~rec.ok[i0:, fault.arms[0]])
        onset = i0 + int(bad[0]) if len(bad) else None
        bound = HOLD_TICKS
    else:          # the injection; a robot process's own watchdog takes up to its timeout to see it
        onset = i0
        detect = robot_watchdog_s + 0.01 if fault.detect_s == "robot_watchdog" else fault.detect_s
        bound = HOLD_TICKS + int(round(detect * 1e3 / ms))
    # the service sees a robot's fault in the tick it holds the arm: its latency is the robot's
    # own detection (reported as detection_ms); every other fault is seen by the service itself
    seen_by_robot = fault.detect_s == "robot_watchdog" or fault.name == "robot_state_nan"
    if onset is None:
        return [(fault.invariant, f"{fault.name}: never became detectable in the recording")]
    # arms already holding for this fault's reason at the tick before it went in (snapshots
    # already too old on a loaded machine): its onset, latency and latching cannot be told from
    # that hold. Reported as the run's availability, never as handled
    before = [b for b in fault.arms if i0 > 0 and rec.arm_hold[i0 - 1, b] & bit]
    if before:
        return [(AVAILABILITY, f"{fault.name}: injected while arm(s) {before} already held for "
                               f"{reason_names(bit)} (load): its contract could not be judged")]
    latency, motion, stop = 0.0, 0.0, 0.0
    settle = int(round(STOP_S * 1e3 / ms))
    for b in fault.arms:
        has = np.flatnonzero(rec.arm_hold[onset:, b] & bit)
        if not len(has):
            fails.append((fault.invariant, f"{fault.name}: arm {b} never held for it"))
            continue
        h = onset + int(has[0])
        lat = float(rec.k[h] - rec.k[onset]) * ms
        out["detection_ms"] = max(out.get("detection_ms", 0.0), lat)
        latency = max(latency, 0.0 if seen_by_robot else lat)
        # "within one tick" counts the ticks the loop ran: the first tick run once the detector's
        # own bound has passed, and HOLD_TICKS after it. Periods the loop did not run (the
        # machine did not schedule it) are its misses, measured apart (loop_miss_ratio); counted
        # here, a 20 ms gap of the VM read as a hold 20 ms late
        due = rec.at(rec.k[onset] + bound - HOLD_TICKS) + HOLD_TICKS
        if h > due:
            fails.append(("S3", f"{fault.name}: arm {b} held {lat:.0f} ms after the fault was detectable "
                                f"(bound {bound * ms:.0f} ms, {h - due} ticks run after the one due)"))
        rel = np.flatnonzero(rec.arm_hold[h:, b] == 0)
        release = h + int(rel[0]) if len(rel) else len(rec.k)
        s = min(h + settle, max(release - 1, h))
        stop = max(stop, float(np.linalg.norm(rec.xr[h:s + 1, b] - rec.xr[h, b], axis=1).max()))
        moved = float(np.linalg.norm(rec.xr[s:release, b] - rec.xr[s, b], axis=1).max()) if release > s else 0.0
        motion = max(motion, moved)
        if moved > MAX_HOLD_MOTION:
            fails.append(("S3", f"{fault.name}: arm {b} moved {moved * 1e3:.3f} mm while held (after its stop)"))
        if fault.latched:
            if ev.clear is None:   # (not tried when the link never brought the pedals up: availability)
                fails.append((AVAILABILITY if _pedals_unread(ev) else "S3", f"{fault.name}: never cleared"))
            elif not (rec.arm_hold[h:end, b] & bit).all():
                fails.append(("S3", f"{fault.name}: arm {b} came back before the fault was cleared (not latched)"))
        if b == 0:
            # the force is zero by the first tick the loop ran once force_ramp_s (and one tick of
            # rounding) had passed: periods the machine did not run the loop are its misses
            # (loop_miss_ratio), as for the hold's latency above
            zero = np.flatnonzero(rec.force0[h:] == 0.0)
            ramp = (rec.k[h + int(zero[0])] - rec.k[h]) * ms if len(zero) else None
            out["force_zero_after_ms"] = ramp
            due = rec.at(rec.k[h] + int(round(force_ramp_s * 1e3 / ms)) + 1)
            if ramp is None or h + int(zero[0]) > due:
                fails.append(("S3", f"{fault.name}: force not zero within force_ramp_s ({ramp} ms)"))
    out["hold_latency_ms"] = latency
    out["robot_motion_during_hold_mm"] = round(motion * 1e3, 4)
    out["stopping_distance_mm"] = round(stop * 1e3, 4)
    if "watchdog_seen_after_ms" in ev.notes:
        out["hold_latency_ms"] = max(latency, ev.notes["watchdog_seen_after_ms"] or 0.0)
    return fails


def _stall_ms(rec: Recording, row: int, window_s: float) -> float:
    """The longest time (ms) the loop ran no tick in the ``window_s`` (plus 20 ms) before row ``row``."""
    lo = rec.at(rec.k[row] - int(round((window_s + 0.02) * 1e3 / rec.ms)))
    k = rec.k[lo:row + 1]
    return float((np.diff(k).max() - 1) * rec.ms) if len(k) > 1 else 0.0


def penetration(rec: Recording, region, every: int = 5) -> float:
    """The deepest any arm's robot went into the forbidden region (m, >= 0)."""
    worst = 0.0
    for b in range(rec.xr.shape[1]):
        x = rec.xr[::every, b]
        ok = np.isfinite(x).all(axis=1)
        if ok.any():
            d = region(x[ok], rec.t[::every][ok])
            worst = max(worst, float(-d.min()))
    return max(0.0, worst)
