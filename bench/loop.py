"""`pointfence bench loop`: the live 1 kHz haptic loop on a synthetic scene.

The whole service runs as in `pointfence demo`: camera reader threads render the configured
synthetic cameras at their rate, the ingest thread builds snapshots, and the haptic loop thread
runs the ticks (masters, one proxy launch for all proxies, forces, teleoperation, one simulated
robot per proxy) on absolute deadlines. Each master circles slowly over the protected object,
pressing into its fixture, so the proxies work in contact. After a warm-up, the loop's own
ring buffers give tick compute time and lateness percentiles and the deadline misses, and the
service's own ring the proxy kernel's share of the same ticks (``kernel_us_p50``, the launch with
its host copies, and ``tick_per_kernel`` = tick p50 / kernel p50).

Beside the loop's misses (periods missed) each run gives ``loop_missed_ticks`` (the ticks that
ended past their period: one long stall of the machine is many missed periods but one missed
tick) and what the whole machine did over the measured seconds (``busy_pct`` of all cores,
``steal_ms``: time the hypervisor gave a virtual core to another guest, when the VM stood still).

``--floor SECONDS`` first measures the machine's own floor in the same run: the same loop on a
tick that only spins as long as the service's median tick, beside one busy process per core.
``--late-causes`` traces the kernel's scheduler over each measured run and sorts its late ticks
by cause (``late_causes``: bench/late_causes.py).
"""
from __future__ import annotations

import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from pointfence.service import config as config_mod
from pointfence.service.canned import canned_sources
from pointfence.service.clock import RealClock
from pointfence.service.loop import HapticLoop
from pointfence.service.masters import ScriptedMaster
from pointfence.service.runner import LiveRun

from .late_causes import RunTrace
from .machine import cpu_times, cpu_usage


class _Busy:
    """A haptic-loop target whose tick only spins for ``busy_s`` (the machine's floor)."""

    def __init__(self, busy_s: float):
        self.busy_s = float(busy_s)

    def tick(self, k, t, dt, overrun, now):
        end = time.perf_counter() + self.busy_s
        while time.perf_counter() < end:
            pass

    def safe_tick(self, k, t, dt, now):
        pass


def machine_floor(cfg, seconds: float, busy_s: float, load: int = 0) -> dict:
    """The same ``HapticLoop`` (same rate, priority, clock and switch intervals) running a tick
    that only spins ``busy_s`` with nothing else in the process: what the machine itself allows
    (wake-up lateness, deadlines missed to preemption, interrupts, a stalled virtual CPU), while
    ``load`` processes of normal priority spin beside it (as cyclictest is run under stress: the
    service keeps the machine's cores busy too, and a virtual machine's host may take a core
    away for milliseconds only when all of them are busy)."""
    sc = cfg.service
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(int(load))]
    loop = HapticLoop(_Busy(busy_s), RealClock(), sc.rate_hz, sc.max_lateness_s, rt_priority=sc.rt_priority,
                      cooperate=False)
    try:
        loop.start()
        time.sleep(0.5)
        mark = loop.mark()
        c0 = cpu_times()
        time.sleep(seconds)
        tm = loop.timing(mark)
        cpu = cpu_usage(c0, cpu_times())
    finally:
        loop.stop()
        for h in hogs:
            h.kill()
            h.wait()
    return {"seconds": seconds, "busy_us": round(busy_s * 1e6, 1), "load_processes": int(load),
            "ticks": tm.ticks, "periods": tm.periods,
            "loop_late_us_p50": round(tm.late_us_p50, 1), "loop_late_us_p99": round(tm.late_us_p99, 1),
            "loop_late_us_max": round(tm.late_us_max, 1), "tick_us_max": round(tm.compute_us_max, 1),
            "loop_misses": tm.misses, "loop_missed_ticks": tm.missed_ticks, "loop_miss_ratio": round(tm.miss_ratio, 5),
            "scheduling": loop.scheduling, **cpu}


#: a run's loop figures that a comparison run beside it reports (``--record-compare``, ``bench ros2``)
LOOP_KEYS = ("tick_us_p50", "loop_late_us_p99", "loop_miss_ratio", "loop_missed_ticks", "busy_pct", "steal_ms")


def add_arguments(p):
    p.add_argument("--seconds", type=float, default=10.0, help="measured seconds per proxy count (default 10)")
    p.add_argument("--warmup", type=float, default=1.0, help="seconds run before measuring (default 1)")
    p.add_argument("--proxies", default="1,4", help="comma-separated proxy counts (default 1,4)")
    p.add_argument("--config", default=None, help="scene configuration (default: the embedded defaults)")
    p.add_argument("--floor", type=float, default=0.0, metavar="SECONDS",
                   help="first run the same loop for SECONDS with a tick that only spins as long as the "
                        "service's median tick, nothing else in the process: the machine's own floor "
                        "(default 0: skip)")
    p.add_argument("--floor-load", type=int, default=None, metavar="N",
                   help="busy processes of normal priority beside the floor's loop (default: one per core)")
    p.add_argument("--record", action="store_true",
                   help="record each run to an MCAP file (service/mcap_record.py) in a temporary folder, as "
                        "`serve --record` does; adds the recording's disk rate and losses to the JSON")
    p.add_argument("--record-compare", action="store_true",
                   help="with --record: also run each proxy count without recording just before and just after "
                        "the recorded run, in the same call (`record_off`, `record_off_after`: the recording's cost "
                        "beside the machine's drift)")
    p.add_argument("--ros2-telemetry", action="store_true",
                   help="publish ROS 2 telemetry during each run (service/ros2/telemetry.py, the [ros2] table's rates) "
                        "on a machine-local DDS domain (loopback only); adds its counts to the JSON")
    p.add_argument("--late-causes", action="store_true",
                   help="trace the kernel's scheduler over each measured run (Linux, as root) and sort its ticks "
                        "later than 5 us by cause (bench/late_causes.py: waits for the interpreter lock and the "
                        "threads that held it, late timer wake-ups, waits for a core, stalls the guest never saw)")
    p.add_argument("--render-live", action="store_true",
                   help="render synthetic frames on the reader threads while the loop runs (default: 30 frames "
                        "pre-rendered and served at the camera rate, as a real camera's C driver would cost)")


def circling_master(i: int, n: int, duration: float) -> ScriptedMaster:
    """Master i of n: a 2 cm (robot: 1 cm) circle, 4 s period, 4.5 cm (robot) down from the start."""
    t = np.arange(0.0, duration + 0.01, 0.01)
    ph = 2 * math.pi * i / max(n, 1)
    w = 2 * math.pi / 4.0
    sink = np.minimum(t / 1.0, 1.0) * -0.09
    p = np.stack([0.02 * np.cos(w * t + ph) - 0.02 * math.cos(ph), 0.02 * np.sin(w * t + ph) - 0.02 * math.sin(ph), sink], 1)
    return ScriptedMaster(t, p, name=f"circle{i}")


def _one(cfg, n: int, seconds: float, warmup: float, backend, device, live: bool, cache: dict,
         record: bool = False, telemetry: bool = False, late_causes: bool = False) -> dict:
    import tempfile

    masters = [circling_master(i, n, seconds + warmup + 5.0) for i in range(n)]
    sources = None if live else canned_sources(cfg, 30, cache)
    tmp = tempfile.TemporaryDirectory(prefix="pointfence-loop-") if record else None
    path = Path(tmp.name) / f"loop-{n}.mcap" if record else None
    run = LiveRun(cfg, masters, backend=backend, device=device, sources=sources, record_path=path,
                  ros2_telemetry=telemetry)
    if run.telemetry is not None and not run.telemetry.wait_ready():   # (rclpy's start-up is not measured)
        run.stop()
        raise RuntimeError(f"ROS 2 telemetry did not start: {run.telemetry.error}")
    t_start = time.monotonic()
    trace = RunTrace(run) if late_causes else None
    run.start()
    try:
        run.wait(warmup)
        run.mark()
        if trace is not None:
            trace.begin()
        first = run.service.ticks
        c0 = cpu_times()
        run.wait(seconds)
        if trace is not None:
            trace.end()
        tm = run.timing()
        cpu = cpu_usage(c0, cpu_times())
        kt = run.service.kernel_timing(since=first)
        gate = run.loop.gate
        yields = (gate.waits, gate.waited_s) if gate is not None else (0, 0.0)
        st = run.service.status()
        tel = st.get("telemetry")
        ingest = list(run.frames.ingest_ms)
        frames = sum(run.frames.frames_in)
    except BaseException:
        if trace is not None:
            trace.abort()
        raise
    finally:
        run.stop()
    rec_stats = {}
    if record:
        r, size = run.service.recorder, path.stat().st_size
        rec_stats = {"record_mb": round(size / 1e6, 2), "record_s": round(time.monotonic() - t_start, 2),
                     # per second of recorded ticks (the run's loop time)
                     "record_mb_per_s": round(size / 1e6 / max(r.ticks_recorded / cfg.service.rate_hz, 1e-3), 2),
                     "record_ticks_lost": r.ticks_lost, "record_snapshots_dropped": r.snapshots_dropped,
                     "record_frames": r.frames_recorded, "record_error": r.write_error,
                     # the writer process's time (s): encoding ticks, frames, chunk writes and fsync, CPU
                     **({"record_writer_s": r.status()["writer_s"]} if hasattr(r, "status") else {})}
        tmp.cleanup()
    if tel is not None:    # the publisher's counts at the end of the measured seconds
        rec_stats["telemetry"] = {k: tel[k] for k in ("lost", "rows_sent", "rows_lost", "messages_published",
                                                      "clouds_published", "cloud_points", "error")}
    if trace is not None:
        rec_stats["late_causes"] = trace.result()
    in_contact = int((run.service.batch.states != 0).sum())
    return {**rec_stats,
        "proxies": n, "ticks": tm.ticks, "periods": tm.periods,
        "tick_us_p50": round(tm.compute_us_p50, 1), "tick_us_p99": round(tm.compute_us_p99, 1),
        "tick_us_max": round(tm.compute_us_max, 1),
        # the proxy launch inside the same ticks (host copies included) and the tick's multiple of it
        "kernel_us_p50": round(kt["kernel_us_p50"], 1), "kernel_us_p99": round(kt["kernel_us_p99"], 1),
        "tick_per_kernel": round(tm.compute_us_p50 / kt["kernel_us_p50"], 2) if kt["kernel_us_p50"] else None,
        "loop_late_us_p50": round(tm.late_us_p50, 1), "loop_late_us_p99": round(tm.late_us_p99, 1),
        "loop_late_us_max": round(tm.late_us_max, 1),
        "loop_misses": tm.misses, "loop_missed_ticks": tm.missed_ticks, "loop_miss_ratio": round(tm.miss_ratio, 5),
        "overruns": tm.overruns,
        # the machine over the measured seconds: all cores' busy share, time the hypervisor took
        **cpu,
        "proxies_in_contact_at_end": in_contact, "camera_frames": frames,
        "ingest_ms_p50": round(float(np.median(ingest)), 2) if ingest else None,
        "hold_at_end": st["hold"], "kernel_errors": st["kernel_errors"],
        "scheduling": run.loop.scheduling, "proxy_device": getattr(run.service.batch, "device_kind", None),
        # frame-thread checkpoints that slept through a tick (kernels/yielding.py), warm-up included
        "frame_yields": yields[0], "frame_yield_ms": round(yields[1] * 1e3, 1),
    }


def run(args) -> dict:
    cfg = config_mod.load(args.config)
    telemetry = getattr(args, "ros2_telemetry", False)
    if telemetry:   # (benches keep DDS on this machine: a domain of its own, loopback only)
        from pointfence.service.ros2 import dds

        dds.apply(dds.local_env(dds.unique_domain_id()))
    counts = [int(x) for x in str(args.proxies).split(",") if x.strip()]
    cache: dict = {}
    floor = None
    if args.floor > 0:
        # (spin as long as the largest proxy count's median tick: a short run to measure it)
        probe = _one(cfg, counts[-1], 2.0, args.warmup, args.backend, args.device, args.render_live, cache)
        load = (os.cpu_count() or 1) if args.floor_load is None else args.floor_load
        floor = machine_floor(cfg, args.floor, probe["tick_us_p50"] * 1e-6, load)
    record = getattr(args, "record", False)
    compare = record and getattr(args, "record_compare", False)

    def one(n: int, rec: bool) -> dict:
        return _one(cfg, n, args.seconds, args.warmup, args.backend, args.device, args.render_live, cache, rec, telemetry,
                    getattr(args, "late_causes", False))

    runs = []
    for n in counts:
        if not compare:
            runs.append(one(n, record))
            continue
        before, r, after = one(n, False), one(n, True), one(n, False)
        r["record_off"] = {k: before.get(k) for k in LOOP_KEYS + ("late_causes",) if k in before}
        r["record_off_after"] = {k: after.get(k) for k in LOOP_KEYS + ("late_causes",) if k in after}
        runs.append(r)
    from pointfence.kernels import get_backend

    be = get_backend(args.backend or cfg.backend, args.device or cfg.device)
    out = {"backend": be.name, "device": be.device_name, "seconds": args.seconds, "rate_hz": cfg.service.rate_hz,
           "cameras": [f"{c.source} {c.camera.width}x{c.camera.height}@{c.rate_hz:g}Hz" for c in cfg.cameras],
           "frames": "rendered live" if args.render_live else "30 pre-rendered frames served in real time",
           "ros2_telemetry": bool(telemetry), "runs": runs}
    if floor is not None:
        out["machine_floor"] = floor
    last = runs[-1]
    for key in ("loop_late_us_p50", "loop_late_us_p99", "loop_miss_ratio", "tick_us_p50", "tick_us_p99",
                "kernel_us_p50", "tick_per_kernel"):
        out[key] = last[key]     # the largest proxy count, at top level
    return out
