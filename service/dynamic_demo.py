"""The chapter-6 part of ``pointfence demo``: moving surfaces, the tool's shadow, the self-filter
(simulated clock: 30 Hz synthetic frames, 1 kHz ticks; the scenarios of service/dynamic_scenes.py).

``pointfence demo`` runs it after the chapter-2 probes (``--no-dynamic`` skips it); its figures
go into the report's table.md / table.json (``report.dynamic_rows``). Besides the kernel-level
scenarios it runs the whole service (``service_plane``: ``[motion]``, the tick's frame time) on the
rising plane, live with the demo's live loop, on the simulated clock with ``--offline``.
"""
from __future__ import annotations

import math

import numpy as np

from . import dynamic_scenes as ds
from .record import INPUT_COLUMNS

INPUT_AGE, INPUT_DT = INPUT_COLUMNS.index("frame_age"), INPUT_COLUMNS.index("dt")
#: a live run whose longest stall let the plane move further than this (mm) fell behind
LIVE_MAX_TRAVEL_MM = 1.0
#: how long a live run waits for the service to run clear before its experiment starts (s)
LIVE_CLEAR_TIMEOUT_S = 10.0

#: the service-level run: a plane rising at ``speed`` through z = -0.1 m at t = 0 under a 160x120
#: camera 0.5 m above it, all protected by a 2 cm fixture; architecture III with an ideal robot
#: fast enough (2 m/s) to follow the proxy; the master plunges the HIP 4 cm below the plane's
#: start and holds it there
PLANE_DOC = {
    "workspace": {"min": [-0.2, -0.2, -0.15], "max": [0.2, 0.2, 0.35]},
    "fixture": {"radius": 0.02},
    "camera": [{"name": "top", "source": "synthetic:translating_plane", "fx": 143.95, "fy": 143.95, "cx": 79.5,
                "cy": 59.5, "width": 160, "height": 120,
                "T_world_cam": [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0.5, 0, 0, 0, 1],
                "options": {"travel": 0.0, "position": [0.0, 0.0, -0.1], "quantize": False}}],
    "teleop": {"architecture": "III", "scale": 1.0, "max_robot_speed": 2.0,
               "T_world_master": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0.05, 0, 0, 0, 1]},
    "robot": {"model": "none"},
    "service": {"max_frame_age_s": 0.3},
}


def service_plane(predict: bool, *, speed: float = 0.5, backend: str = "opencl", device: str | None = None,
                  live: bool = False, duration: float = 0.4, latency: float = 0.0) -> dict:
    """The whole service (``[motion] enabled = predict``) on the rising plane: the fixture's
    penetration (mm) by the proxy and by the robot once the HIP is below the fixture (t > 0.1 s),
    measured against the exact plane at each tick's scene time. ``live``: the 1 kHz loop thread
    on the real clock with a real-time synthetic camera (else the simulated clock)."""
    import copy

    from . import config, replay
    from .masters import ScriptedMaster
    from .runner import LiveRun

    doc = copy.deepcopy(PLANE_DOC)
    doc["backend"] = backend
    if device:
        doc["device"] = device
    doc["camera"][0]["options"]["speed"] = float(speed)
    doc["motion"] = {"enabled": bool(predict), "latency": float(latency)}
    if live:
        doc["service"]["max_lateness_s"] = 0.02
    cfg = config.parse(doc, "chapter-6 service run")
    master = ScriptedMaster(np.array([0.0, 0.1, 10.0]), np.array([[0, 0, 0], [0, 0, -0.19], [0, 0, -0.19]], float))
    start, go = 0.0, 0.0   # when the plane starts to rise (scene time, s) and the master's script (loop time, s)
    if live:
        # The experiment starts once the service runs clear: a real-time camera's clock starts at
        # its first frame and the start-up builds kernels, so the loop may start on an old snapshot
        # and hold (S2); a master that moved meanwhile is re-anchored (S1), and an experiment that
        # started then measures a HIP that never went down. Until then the plane rests and the
        # master waits; both start one frame period after the service is found clear.
        sources = cfg.open_sources(realtime=True)
        sources[0].scene.start = math.inf
        master.t0 = math.inf
        run = LiveRun(cfg, [master], record_s=duration + LIVE_CLEAR_TIMEOUT_S + 2.0, sources=sources)
        run.start()
        try:
            run.wait_clear(0.05, timeout=LIVE_CLEAR_TIMEOUT_S)
            at = run.clock.now() + 1.0 / cfg.cameras[0].rate_hz
            master.t0, start = at - run.loop.t0, at - run.frames.clock_minus_stamp
            sources[0].scene.start = start
            run.mark()
            run.wait(duration + max(0.0, at - run.clock.now()))
            timing = run.timing()
        finally:
            run.stop()
        svc, go = run.service, master.t0
    else:
        svc, _, sources = replay.simulate(cfg, [master], duration)
    rec = svc.recorder
    rows = rec.ticks()
    t = rows[:, 0] + svc.scene_time_offset
    scene = sources[0].scene
    # once the HIP is below the fixture (0.1 s into the script) and the plane has risen for 0.1 s
    keep = (rows[:, 0] - go > 0.1) & (t - start > 0.1)
    r_f = cfg.pipeline.radius.r_base
    pen = {}
    arr = rec.arrays()
    ages, gaps = arr["inputs"][keep, INPUT_AGE], arr["inputs"][keep, INPUT_DT]
    held = (arr["holds"][keep] != 0).any(axis=1)
    for name, pts in (("proxy", rows[:, 7:10]), ("robot", arr["robots"][:, 0, :3])):
        d = np.array([scene.distance(p[None], ti)[0] for p, ti in zip(pts[keep], t[keep])])
        pen[name] = round(1000 * max(0.0, float((r_f - d).max())), 2) if len(d) else None
    for s in sources:
        s.close()
    res = {"penetration_mm_proxy": pen["proxy"], "penetration_mm_robot": pen["robot"], "ticks": int(rec.count),
           "hold": svc.status()["hold"], "last_dt_ms": round(svc.batch.last_dt * 1000, 2),
           "frame_age_ms_max": round(1000 * float(ages.max()), 1) if len(ages) else None,
           "held_ticks": int(held.sum())}
    if live:
        res["loop_miss_ratio"] = round(timing.miss_ratio, 5)
        res["loop_late_us_p99"] = round(timing.late_us_p99, 1)
        res["tick_gap_ms_max"] = round(1000 * float(gaps.max()), 2) if len(gaps) else None
        res["fell_behind"] = fell_behind(res, float(speed), 1.0 / cfg.cameras[0].rate_hz)
    return res


def fell_behind(res: dict, speed: float, frame_period_s: float) -> list:
    """What kept a live run from being the experiment it models (empty: nothing). The plane
    advances ``speed`` (m/s) the whole time, so the longest gap between two measured ticks
    (``tick_gap_ms_max``) lets it move ``speed * gap`` into the proxy with no tick to push back:
    more than ``LIVE_MAX_TRAVEL_MM`` is the machine's lateness in the measure, not the fixture's.
    A snapshot older than two frame periods (``frame_period_s``, s) means the ingest fell behind
    the camera. Ticks that held (``held_ticks``) froze the arm while the plane rose into it, and
    the re-anchoring after the hold (S1) keeps the scripted master's HIP where it was."""
    why = []
    if res.get("held_ticks"):
        why.append(f"the service held for {res['held_ticks']} ticks during the run")
    gap = res.get("tick_gap_ms_max")
    if gap is not None and speed * gap > LIVE_MAX_TRAVEL_MM:
        why.append(f"ticks {gap:.1f} ms apart: the plane moved {speed * gap:.1f} mm between them")
    limit = 2000.0 * frame_period_s
    if res.get("frame_age_ms_max") is not None and res["frame_age_ms_max"] > limit:
        why.append(f"snapshots up to {res['frame_age_ms_max']:.0f} ms old (two frames: {limit:.0f} ms)")
    return why


def _speed(v):
    return f">{ds.SPEEDS[-1]:g}" if v is None else f"{v:g}"


def run(backend: str = "opencl", device: str | None = None, latency: float = 0.1, out=print,
        live: bool = False) -> dict:
    """Print the chapter-6 table and return its figures. The service-level rising-plane run uses
    the live loop with ``live`` (else the simulated clock, like the rest of the section)."""
    out("\nchapter 6: dynamic scene (simulated 1 kHz ticks, 30 Hz frames, 2 cm fixture)")
    res = {}
    svc = {}
    for predict in (False, True):
        svc["with_prediction" if predict else "without_prediction"] = service_plane(
            predict, backend=backend, device=device, live=live)
    res["service_plane_0.5mps"] = svc
    clock = "live 1 kHz loop" if live else "simulated clock"
    out(f"  service ({clock}), plane rising at 0.5 m/s, architecture III: fixture penetration "
        f"{svc['without_prediction']['penetration_mm_robot']:.2f} mm without motion prediction, "
        f"{svc['with_prediction']['penetration_mm_robot']:.2f} mm with it (robot; proxy "
        f"{svc['without_prediction']['penetration_mm_proxy']:.2f} / {svc['with_prediction']['penetration_mm_proxy']:.2f} mm)")
    for name, r in svc.items() if live else ():   # a busy machine's live run measures the machine: say so
        out(f"    live run {name.replace('_', ' ')}: loop misses {100 * r['loop_miss_ratio']:.2f} %, lateness "
            f"p99 {r['loop_late_us_p99']:.0f} us, longest gap between ticks {r['tick_gap_ms_max']:.1f} ms, "
            f"snapshot age max {r['frame_age_ms_max']:.0f} ms")
        if r.get("fell_behind"):
            out(f"    the live run {name.replace('_', ' ')} fell behind ({'; '.join(r['fell_behind'])}): its "
                f"penetration is the machine's lateness, not the fixture's; `pointfence demo --offline` gives "
                f"the simulated-clock figure")
    for label, kw in (("no latency", {}), (f"camera latency {latency * 1000:.0f} ms", {"latency": latency})):
        off = ds.popthrough_speed(False, backend=backend, device=device, **kw)
        on = ds.popthrough_speed(True, backend=backend, device=device, **kw)
        res[label] = {"without_prediction": off["popthrough_mps"], "with_prediction": on["popthrough_mps"]}
        out(f"  translating plane, {label:22s}: pop-through at {_speed(off['popthrough_mps'])} m/s without "
            f"motion prediction, {_speed(on['popthrough_mps'])} m/s with it (held {on['held_mps']} m/s)")
    one, two = ds.occlusion_run(1, backend=backend, device=device), ds.occlusion_run(2, backend=backend, device=device)
    res["occlusion_penetration_mm_1cam"] = round(one.max_penetration * 1e3, 2)
    res["occlusion_penetration_mm_2cam"] = round(two.max_penetration * 1e3, 2)
    out(f"  tool's shadow over a protected disc, architecture III: penetration {res['occlusion_penetration_mm_1cam']:.2f} mm "
        f"with the top camera alone, {res['occlusion_penetration_mm_2cam']:.2f} mm with a second (side) camera")
    sf = ds.self_filter_ratio(backend=backend, device=device)
    res["self_filter"] = sf
    out(f"  robot self-filter: {sf['false_fixture_points_without']} protected points on the instrument without it, "
        f"{sf['false_fixture_points_with']} with it (ratio {sf['self_filter_false_fixture_ratio']:g}); tips fenced "
        f"in by their own tool {sf['tips_fenced_without']} -> {sf['tips_fenced_with']}")
    return res
