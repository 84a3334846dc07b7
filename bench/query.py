"""`pointfence bench query`: the haptic tick (batched proxy kernel) on a real close-range frame.

Scene: apc_shelfbin_50f (../shared/data), frames at 0.25-0.45 m, fused into one snapshot with
their recorded poses (default frames 47 and 49, so that about 1500 points lie within R3 of the
proxy: one frame of this set holds at most about 1100 there). The proxies sit on the densest
surface spots; each HIP circles 5 mm around its spot at 0.1 m/s while its depth swings from
3 mm in front of the surface to 6 mm behind it at 2 Hz (free motion, contact, sliding).

Figures:
* tick_us_{1,64,1024}proxy_p50/p99: one full tick = HIP check and upload, the one kernel launch
  with every proxy step of the tick, read-back and unpacking into the host arrays, us, over
  ``--ticks`` timed ticks for every batch size (60 for ``--big``);
* tick_with_forces_us_1proxy_p50/p99: the same plus force rendering (``HapticScene.step``);
* steps_per_s_1proxy: proxy steps per second of wall time for one proxy sliding along the
  surface with a 1000-step budget per tick and the turn-back rule off (``turn_back_cos`` -1:
  the raw cost of a step, every tick spends most of its budget);
* ckdtree_tick_us_1proxy_p50: the peer, the same proxy algorithm (NumPy, the reference's step
  functions) over scipy cKDTree neighbourhoods, on the same trajectory.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from pointfence.kernels import DepthFrame, PipelineParams, Workspace, get_backend
from pointfence.kernels.haptics import HapticParams, HapticScene, haptic_pipeline_params

from .stats import pct

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
APC = SHARED / "apc_shelfbin_50f"
R3 = 0.010


def add_arguments(p):
    p.add_argument("--frames", default="49", help="apc_shelfbin_50f frame indices fused into one snapshot with their poses (default 49)")
    p.add_argument("--ticks", type=int, default=None, help="timed ticks per case (default: --repeat or 2000)")
    p.add_argument("--data", default=str(SHARED), help="the shared data folder (default ../shared/data)")
    p.add_argument("--big", type=int, default=0, help="also time one batch of this many proxies (e.g. 65536): "
                   "tick_us_<N>proxy_p50/p99 and proxies_per_s")


def apc_rig(indices, data=SHARED):
    """(cameras, frames) of apc_shelfbin frames with their recorded poses (a static rig)."""
    from pointfence.service.sources import RecordedSource

    root = Path(data) / "apc_shelfbin_50f"
    if not root.is_dir():
        raise SystemExit(f"bench query needs {root} (the shared real-data folder); not found")
    src = RecordedSource(root, loop=False)
    cams, frames = [], []
    for k, i in enumerate(indices):
        depth, _, pose = src.load(int(i))
        cam = src.camera.with_pose(pose) if pose is not None else src.camera
        cam = type(cam)(**{**cam.__dict__, "name": f"apc{i}"})
        cams.append(cam)
        frames.append(DepthFrame(cam.name, depth, 0.0))
    return cams, frames


def scene_params(p: HapticParams) -> PipelineParams:
    return haptic_pipeline_params(p, PipelineParams(workspace=Workspace((-0.3, -0.3, 0.05), (0.3, 0.3, 0.7))))


def dense_spots(pts: np.ndarray, n: int, target: int = 1500, seed: int = 0):
    """n surface points whose R3 neighbourhood count is closest to ``target`` (and the counts)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(pts)
    rng = np.random.default_rng(seed)
    cand = pts[rng.choice(len(pts), min(len(pts), 4000), replace=False)]
    counts = tree.query_ball_point(cand, R3, return_length=True)
    order = np.argsort(np.abs(counts - target))
    pick = order[: max(n, 1)]
    if n > len(pick):
        pick = np.resize(pick, n)
    return cand[pick].astype(np.float64), counts[pick], tree


def outward(spots: np.ndarray, cams) -> np.ndarray:
    """Unit vectors from each spot towards the first camera (the free side of the surface)."""
    eye = np.asarray(cams[0].T_world_cam)[:3, 3]
    d = eye - spots
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def trajectory(spots, out, n_ticks, rate=1000.0):
    """HIPs (n_ticks, B, 3): 5 mm circles at 0.1 m/s, depth swinging from +3 mm to -6 mm at 2 Hz."""
    B = len(spots)
    a = np.cross(out, [0.0, 0.0, 1.0])
    bad = np.linalg.norm(a, axis=1) < 1e-6
    a[bad] = np.cross(out[bad], [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(out, a)
    t = np.arange(n_ticks)[:, None, None] / rate
    phase = np.linspace(0, 2 * np.pi, B, endpoint=False)[None, :, None]
    w = 0.1 / 0.005
    circ = 0.005 * (np.cos(w * t + phase) * a + np.sin(w * t + phase) * b)
    depth = 0.0015 - 0.0045 * np.sin(2 * np.pi * 2.0 * t + phase)
    return spots[None] + circ + depth * out[None]


def time_ticks(step, hips, warm=100):
    for h in hips[:warm]:
        step(h)
    ts = np.empty(len(hips) - warm)
    for i, h in enumerate(hips[warm:]):
        t0 = time.perf_counter()
        step(h)
        ts[i] = time.perf_counter() - t0
    return ts * 1e6


def ckdtree_peer(pts, tree, p: HapticParams):
    """The same proxy algorithm (reference step functions) over cKDTree neighbourhoods."""
    from pointfence.kernels.reference.proxy import pack_rows, run_tick

    rho = np.full(len(pts), np.float32(p.r1), np.float32)
    pts32 = np.ascontiguousarray(pts, np.float32)
    radius = p.reach() + p.skin

    def gather(X0):
        lists = tree.query_ball_point(X0.astype(np.float64), radius)
        own = np.concatenate([np.full(len(ix), i) for i, ix in enumerate(lists)]).astype(np.int64)
        idx = np.concatenate([np.asarray(ix, np.int64) for ix in lists]) if own.size else np.zeros(0, np.int64)
        if idx.size:
            o = np.lexsort((idx, own))
            own, idx = own[o], idx[o]
        return pack_rows(own, idx, len(X0), pts32, rho)

    state = {"X": None}

    def step(h):
        X, *_ = run_tick(state["X"], np.asarray(h, np.float32), gather, p)
        state["X"] = X

    return state, step


def run(args) -> dict:
    n_ticks = args.ticks or args.repeat or 2000
    frames_idx = [int(s) for s in str(args.frames).split(",") if s.strip()]
    backend = get_backend(args.backend, args.device)
    p = HapticParams()
    cams, frames = apc_rig(frames_idx, args.data)
    out = {"backend": backend.name, "device": backend.device_name, "scene": f"apc_shelfbin_50f frames {frames_idx}"}

    hs = HapticScene(cams, np.zeros((1, 3)), p, scene_params(p), backend=args.backend, device=args.device)
    hs.ingest(frames)
    snap = hs.pipeline.host_snapshot()
    pts = snap.points[:, :3].astype(np.float64)
    out["points"] = int(snap.n_points)

    # 1 proxy: the spot with about 1500 points within R3
    spot, count, tree = dense_spots(pts, 1)
    o = outward(spot, cams)
    hips1 = trajectory(spot, o, n_ticks + 100)
    batch = hs.batch
    batch.reset(spot + 0.02 * o)
    ts = time_ticks(batch.step, hips1)
    near = tree.query_ball_point(batch.positions[0].astype(np.float64), R3, return_length=True)
    out.update({
        "points_within_r3_of_spot": int(count[0]),
        "tick_us_1proxy_p50": round(pct(ts, 50), 2),
        "tick_us_1proxy_p99": round(pct(ts, 99), 2),
        "steps_per_tick_1proxy_mean": round(float(np.mean(_steps_of(batch, hips1[-200:]))), 2),
        "points_within_r3_of_proxy_last": int(near),
    })
    hs.reset(spot + 0.02 * o)
    tf = time_ticks(hs.step, hips1)
    out["tick_with_forces_us_1proxy_p50"] = round(pct(tf, 50), 2)
    out["tick_with_forces_us_1proxy_p99"] = round(pct(tf, 99), 2)
    batch.close()   # (its resident kernel leaves now, not 0.1 s into the next case)
    if hasattr(batch, "resident"):   # Warp: whether small batches ran on the resident kernel
        out["resident_1proxy"] = batch.resident()
        if batch.resident():   # the same ticks on the launched graph, for comparison
            lb = hs.pipeline.proxies(spot + 0.02 * o, p, resident=False)
            tl = time_ticks(lb.step, hips1)
            out["tick_us_1proxy_launched_p50"] = round(pct(tl, 50), 2)
            out["tick_us_1proxy_launched_p99"] = round(pct(tl, 99), 2)

    # steps per second: a 1000-step budget, HIP 3 cm along the surface and 5 mm behind it
    fast = HapticParams(max_steps=1000, turn_back_cos=-1.0)
    far = hs.pipeline.proxies(spot + 0.0051 * o, fast)
    a = np.cross(o[0], [0.0, 0.0, 1.0])
    a /= np.linalg.norm(a)
    steps = tt = 0
    for k in range(max(20, n_ticks // 50)):
        far.reset(spot + 0.0051 * o)
        h = spot + 0.03 * np.cos(k) * a - 0.005 * o
        t0 = time.perf_counter()
        far.step(h)
        tt += time.perf_counter() - t0
        steps += int(far.steps[0])
    far.close()
    out["steps_per_s_1proxy"] = int(steps / tt)
    out["steps_per_tick_in_steps_run_mean"] = round(steps / max(20, n_ticks // 50), 1)

    # 64 and 1024 (and --big) proxies on spots spread over the frame
    for B in (64, 1024) + ((args.big,) if args.big else ()):
        spots, _, _ = dense_spots(pts, B, target=int(np.median(tree.query_ball_point(pts[::97], R3, return_length=True))), seed=B)
        ob = outward(spots, cams)
        hb = trajectory(spots, ob, (n_ticks if B <= 1024 else min(n_ticks, 60)) + 50)
        pb = hs.pipeline.proxies(spots + 0.02 * ob, p)
        tb = time_ticks(pb.step, hb, warm=50)
        out[f"tick_us_{B}proxy_p50"] = round(pct(tb, 50), 2)
        out[f"tick_us_{B}proxy_p99"] = round(pct(tb, 99), 2)
        if B == args.big:
            out["proxies_per_s"] = int(B / (pct(tb, 50) * 1e-6))
        if hasattr(pb, "block_dim"):   # Warp: threads per proxy chosen for this batch size
            out.setdefault("threads_per_proxy", {})[str(B)] = pb.block_dim()
        pb.close()

    # peer: cKDTree neighbourhoods + the same algorithm in NumPy
    state, peer_step = ckdtree_peer(pts, tree, p)
    state["X"] = (spot + 0.02 * o).astype(np.float32)
    tp = time_ticks(peer_step, hips1[: min(len(hips1), 600)], warm=50)
    out["ckdtree_tick_us_1proxy_p50"] = round(pct(tp, 50), 2)
    out["ckdtree_tick_us_1proxy_p99"] = round(pct(tp, 99), 2)
    out["speedup_vs_ckdtree_1proxy_p50"] = round(out["ckdtree_tick_us_1proxy_p50"] / out["tick_us_1proxy_p50"], 1)
    out["ticks"] = n_ticks
    return out


def _steps_of(batch, hips):
    s = []
    for h in hips:
        batch.step(h)
        s.append(int(batch.steps[0]))
    return s
