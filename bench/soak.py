"""`pointfence bench soak`: the live service under injected faults, judged against
``../shared/SAFETY.md``.

    pointfence bench soak --json [--minutes M] [--faults all|LIST] [--out DIR]

The service runs as ``pointfence serve`` runs it, at 1 kHz on the real clock, with two
simulated devices over authenticated UDP pushing two hosted Raven II arms into the fixture
around the default scene's balloon under architecture III (``bench/soak_rig.py``). Every fault
kind of ``bench/soak_faults.py`` is injected in turn, again and again for ``--minutes`` (0: every
fault once, the CI version): camera stall, ingest exception, ingest thread death, kernel
exception, kernel hang, client silence, NaN master, forged and replayed datagram floods,
robot process kill, stall and NaN state, haptics off and architecture switches while pushing,
unauthenticated control requests, and a fault cleared while coupled. Between faults the run
must be steady: every arm coupled and nothing holding. After each fault its cause is removed
and, where the fault is latched (or a hold remains), the operator clears it as SAFETY.md S3
wants: pedals up, clear-faults, pedals down.

The recording streams to ``soak.pfrec`` (in ``--out``, or a temporary folder), and each event is
judged on it afterwards (``bench/soak_check.py``). The JSON has ``faults_injected``,
``faults_handled`` (contract kept), ``faults_failed`` (each failure with its invariant),
``max_hold_latency_ms`` (fault detectable -> arms holding; for a hung kernel call, the tick
watchdog's sight of it), ``max_robot_motion_during_hold_mm``, ``max_penetration_mm`` (both
arms, against the scene's true surface), ``ticks_recorded``, ``ticks_lost``,
``loop_miss_ratio`` (with ``loop_missed_periods_in_injected_hangs``, the periods the injected hung
kernel calls stall by design, and ``loop_miss_ratio_outside_injected_hangs``, the loop's own),
``machine_busy_pct`` and ``machine_steal_ms`` (every process on the machine over the run:
bench/machine.py), and per fault kind its count, failures and worst figures.
"""
from __future__ import annotations

import tempfile
import time
from collections import Counter
from pathlib import Path

from pointfence.kernels.errors import InputError

from .e2e import LIGHT_SCENE
from .machine import cpu_times, cpu_usage
from .soak_check import (AVAILABILITY, MAX_HOLD_MOTION, MAX_PENETRATION, Recording, failure_class, judge, load_only,
                         penetration)
from .soak_faults import FAULTS, HANG_S, Event


#: the embedded defaults with the camera at 320x240 (2 mm between points on the balloon): the
#: soak judges safety, and a 640x480 build every 33 ms would take a core of the two
SOAK_SCENE = (LIGHT_SCENE.replace("fx = 143.95\nfy = 143.95\ncx = 79.5\ncy = 59.5\nwidth = 160\nheight = 120",
                                  "fx = 287.9\nfy = 287.9\ncx = 159.5\ncy = 119.5\nwidth = 320\nheight = 240")
              # the simulated arms' process shares the two cores with the service, the devices and
              # the attackers: starved beyond 50 ms now and then, it would read as a robot fault
              + "[service]\nproxies = 2\nrobot_watchdog_s = 0.1\n")


def add_arguments(p):
    p.add_argument("--minutes", type=float, default=0.0,
                   help="keep injecting faults in turn for this long (default 0: every fault once)")
    p.add_argument("--faults", default="all", help=f"'all' or a comma-separated list of: {', '.join(FAULTS)}")
    p.add_argument("--config", default=None,
                   help="scene configuration (TOML); default: the embedded defaults with a 320x240 camera")
    p.add_argument("--out", default=None, help="keep the recording (soak.pfrec) and the events (events.json) here")
    p.add_argument("--prerender", type=int, default=30, help="pre-rendered synthetic frames (default 30)")


def _selected(spec: str) -> list:
    if spec == "all":
        return list(FAULTS.values())
    names = [s.strip() for s in spec.split(",") if s.strip()]
    unknown = [n for n in names if n not in FAULTS]
    if unknown or not names:
        raise InputError(f"--faults {spec!r}: unknown {unknown or 'empty list'}; known: all, {', '.join(FAULTS)}")
    return [FAULTS[n] for n in names]


def _recover(rig, fault, ev, clear: bool = False) -> None:
    """Conditions clear by themselves; latched faults (or a hold that stays) are cleared by the
    operator: pedals up, clear-faults, pedals down (S3)."""
    if clear or fault.latched or not rig.steady(1.5):
        up = rig.pedals(False, timeout=30.0)
        ev.notes["pedal_up_s"] = round(up, 3)
        if up == float("inf"):      # the link never brought the pedals up: no clear is tried (S3 would refuse it)
            ev.notes["pedals_unread"] = True
            ev.failures.append((AVAILABILITY, f"{fault.name}: the service never read the pedals up in 30 s (the "
                                              f"devices' link behind under load): pedals {rig.svc.status()['pedal']}"))
            rig.pedals(True)
            return
        ev.clear = rig.tick()       # the clear happens at this tick or a little later
        try:
            rig.ctl.post("/clear-faults", {})
        except Exception as e:  # noqa: BLE001 -- judged: a refused clear with the pedals up is a failure
            ev.clear = None
            ev.failures.append(("S3", f"{fault.name}: clear-faults with the pedals up refused: {e}; "
                                      f"pedals {rig.svc.status()['pedal']}"))
        rig.sleep(0.1)
        rig.pedals(True)
    if rig.steady(5.0):
        ev.recovered = rig.tick()
    else:                       # what still held: judged (soak_check) as load or as a broken contract
        st = rig.svc.status()
        ev.notes["unrecovered"] = {"hold": st["hold"], "latched": st["latched_faults"], "coupled": st["coupled"],
                                   "arms_holding": st["arms_holding"]}


def run(args) -> dict:
    from pointfence.service import config as config_mod

    faults = _selected(args.faults)
    cfg = config_mod.load(args.config) if args.config else config_mod.parse(_toml(SOAK_SCENE), "bench soak scene")
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="pf-soak-"))
    out.mkdir(parents=True, exist_ok=True)
    from .soak_rig import SoakRig

    rig = SoakRig(cfg, out, backend=args.backend, device=args.device, prerender=args.prerender)
    events, unexpected, t_end = [], [], None
    rig.start()
    c0 = None
    try:
        if not rig.steady(60.0):
            raise RuntimeError(f"bench soak: the arms never coupled: {rig.svc.status()}; clients {rig.hub.status()}")
        rig.sleep(1.0)       # the devices' approach: both arms pushing into the fixture
        c0 = cpu_times()
        t_end = time.monotonic() + 60.0 * float(args.minutes)
        stuck = False
        while not stuck:
            for fault in faults:
                if not rig.steady(5.0):     # a hold nobody injected: a failure of its own; cleared
                    st = rig.svc.status()
                    unexpected.append({"fault": None, "invariant": AVAILABILITY if load_only(st) else "S9",
                                       "what": f"not steady before {fault.name} (tick {rig.tick()}): holding "
                                               f"{st['arms_holding']}, coupled {st['coupled']}, pedals {st['pedal']}, "
                                               f"robots {[r and r['fault'] for r in st['robots']]}, {rig.robot_notes()}, "
                                               f"last error {st['last_error']}"})
                    cleared = Event("unexpected")
                    _recover(rig, fault, cleared, clear=True)
                    if not rig.steady(10.0):
                        st = rig.svc.status()
                        if not load_only(st):     # the run cannot go on: judged as far as it went
                            unexpected.append({"fault": None, "invariant": "S3", "what": f"the run stayed stuck: "
                                               f"{[w for _, w in cleared.failures]}; holding {st['arms_holding']}, "
                                               f"latched {st['latched_faults']}; {rig.robot_notes()}"})
                            stuck = True
                            break
                        # held only for load (late ticks, a device link lost): S9 as it should;
                        # the next fault goes in once the run is steady again, or after 30 s more
                        rig.steady(30.0)
                rig.sleep(0.3)
                rig.steady(5.0)         # (the last look right before it: a hold for load since the wait)
                ev = Event(fault.name)
                fault.inject(rig, ev)
                _recover(rig, fault, ev)
                events.append((fault, ev))
            if stuck or time.monotonic() >= t_end:
                break
        rig.sleep(0.3)
    finally:
        timing = rig.run.timing()
        scheduling = rig.scheduling()
        cpu = cpu_usage(c0, cpu_times())
        ages = rig.hub.status()["state_age_ms"]
        region = _region(rig)
        link = rig.stop()
    from pointfence.service.record import load_recording

    data = load_recording(rig.record_path)
    rec = Recording(data, cfg.service.rate_hz)
    sc = cfg.service
    verdicts = [judge(f, ev, rec, sc.max_frame_age_s, sc.force_ramp_s, sc.robot_watchdog_s) for f, ev in events]
    failed = unexpected + [{"fault": v["fault"], "invariant": inv, "what": what} for v in verdicts
                           for inv, what in v["failures"]]
    for f in failed:
        f["class"] = failure_class(f["invariant"], f["what"])
    classes = Counter(f["class"] for f in failed)
    pen = penetration(rec, region) if region is not None else None
    if pen is not None and pen > MAX_PENETRATION:
        failed.append({"fault": None, "invariant": "S1", "what": f"a robot entered the fixture by {pen * 1e3:.2f} mm"})
    per = {}
    for v in verdicts:
        p = per.setdefault(v["fault"], {"injected": 0, "failed": 0, "max_hold_latency_ms": None,
                                        "max_robot_motion_mm": None})
        p["injected"] += 1
        p["failed"] += bool(v["failures"])
        for key, src in (("max_hold_latency_ms", "hold_latency_ms"), ("max_robot_motion_mm", "robot_motion_during_hold_mm"),
                         ("max_robot_motion_mm", "robot_motion_mm")):
            if v.get(src) is not None:
                p[key] = max(p[key] or 0.0, v[src])
    lat = [v["hold_latency_ms"] for v in verdicts if v.get("hold_latency_ms") is not None]
    det = [v["detection_ms"] for v in verdicts if v.get("detection_ms") is not None]
    mot = [v.get("robot_motion_during_hold_mm") for v in verdicts if v.get("robot_motion_during_hold_mm") is not None]
    stops = [v["stopping_distance_mm"] for v in verdicts if v.get("stopping_distance_mm") is not None]
    meta = data["meta"]
    hung = hung_periods(rec.k, [ev.inject for f, ev in events if f.name == "kernel_hang"], HANG_S * cfg.service.rate_hz)
    (out / "events.json").write_text(__import__("json").dumps(verdicts, indent=1, default=str) + "\n")
    return {
        "minutes": round((rec.k[-1] - rec.k[0]) / cfg.service.rate_hz / 60.0, 2) if len(rec.k) else 0.0,
        "faults_injected": len(events),
        "faults_handled": sum(1 for v in verdicts if not v["failures"]),
        "faults_failed": failed,
        "contract_failures": classes["contract"],
        "bound_failures": classes["bound"],
        "availability_failures": classes["availability"],
        "max_hold_latency_ms": max(lat) if lat else None,
        "max_detection_ms": max(det) if det else None,
        "max_robot_motion_during_hold_mm": max(mot) if mot else None,
        "max_stopping_distance_mm": max(stops) if stops else None,
        "timing_holds_during_attacks_and_actions": sum(v.get("timing_holds", 0) for v in verdicts),
        "max_penetration_mm": None if pen is None else round(pen * 1e3, 3),
        # the age of the master samples the ticks used (kernel arrival -> tick), whole run and floods
        "master_state_age_ms_p50": ages["p50_ms"], "master_state_age_ms_p99": ages["p99_ms"],
        "master_state_age_ms_max": ages["max_ms"],
        "master_state_age_ms_p99_during_floods": max((v["state_age_ms"]["p99_ms"] or 0.0 for v in verdicts
                                                      if isinstance(v.get("state_age_ms"), dict)), default=None),
        "ticks_recorded": int(meta.get("ticks_recorded", len(rec.k))),
        "ticks_lost": int(meta.get("ticks_lost", 0)),
        "torn_bytes": int(data.get("torn_bytes", 0)),
        "loop_miss_ratio": round(timing.miss_ratio, 6),
        # the periods the injected hung kernel calls stall by design (the loop's thread is inside
        # the call for HANG_S), and the misses outside them: the loop's own timing under the faults
        "loop_missed_periods_in_injected_hangs": hung,
        "loop_miss_ratio_outside_injected_hangs": round(max(timing.misses - hung, 0) / max(timing.periods, 1), 6),
        "loop": timing.as_dict(),
        # the machine over the run (every process on it: service, devices, attackers, arms)
        "machine_busy_pct": cpu.get("busy_pct"), "machine_steal_ms": cpu.get("steal_ms"),
        "targets": {"robot_motion_during_hold_mm": MAX_HOLD_MOTION * 1e3, "penetration_mm": MAX_PENETRATION * 1e3,
                    "loop_miss_ratio": 0.001},
        "per_fault": per,
        "devices": link.get("devices"),
        # the service's threads that feed or watch the tick, as the OS runs them (SCHED_FIFO or normal)
        "scheduling": scheduling,
        "recording": str(rig.record_path),
        "backend": rig.svc.backend.name, "device": rig.svc.backend.device_name,
    }


def hung_periods(k, injected: list, hang_periods: float) -> int:
    """Missed periods of the injected hung kernel calls: in the recorded ticks' period indices
    ``k`` (increasing), each gap that opens within 10 ticks after an injection (the hang blocks
    the next step), counted up to ``hang_periods`` + 2 (the call's own length and the tick
    around it; the rest of a longer gap is the loop's own miss), and the hung tick itself, which
    ended past its period."""
    import numpy as np

    k = np.asarray(k, np.int64)
    if k.size < 2:
        return 0
    gaps = np.diff(k) - 1
    at = np.flatnonzero(gaps > 0)
    total = 0
    cap = int(np.ceil(hang_periods)) + 2
    for t in injected:
        if t is None:
            continue
        near = at[(k[at] >= t) & (k[at] <= t + 10)]
        if near.size:                        # the first gap after the injection: the hang's
            total += min(int(gaps[near[0]]), cap) + 1
    return total


def _toml(text: str) -> dict:
    try:
        import tomllib
    except ModuleNotFoundError:          # Python 3.10
        import tomli as tomllib
    return tomllib.loads(text)


def _region(rig):
    """The scene's true forbidden region (synthetic scenes; None for others)."""
    from pointfence.service import measures

    try:
        return measures.region_for(rig.cfg, rig.sources)
    except ValueError:
        return None
