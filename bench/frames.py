"""`pointfence bench frames`: frame ingest against the peers a user would otherwise pick.

ingest = upload + deproject + transform + noise + radius + selection + crop + counting sort,
for 1 and 4 cameras at 640x480 on a synthetic tabletop. Peers, on the same points and queries:
scipy cKDTree build + query_ball_point, and the dissertation's projective search (no build).
"""
from __future__ import annotations

import time

import numpy as np

from pointfence.kernels import get_backend

from .projective import ProjectiveSearch
from .scenes import tabletop_params, tabletop_rig
from .stats import pct

R3 = 0.010  # neighbourhood radius of the proxy (table 2.1), m


def add_arguments(p):
    p.add_argument("--queries", type=int, default=64, help="neighbourhood queries per snapshot (default 64)")
    p.add_argument("--cameras", type=int, default=4, help="cameras in the multi-camera case (default 4)")


def _time(fn, n):
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t0) * 1e3)
    return ts


def run(args) -> dict:
    reps = args.repeat or 60
    backend = get_backend(args.backend, args.device)
    params = tabletop_params()
    cams, frames = tabletop_rig(args.cameras)
    out = {"backend": backend.name, "device": backend.device_name, "image": "640x480"}

    one = backend.pipeline(cams[:1], params)
    for _ in range(3):
        one.ingest(frames[:1])
    t1 = _time(lambda: one.ingest(frames[:1]), reps)

    pipe = backend.pipeline(cams, params)
    for _ in range(3):
        pipe.ingest(frames)
    t4 = _time(lambda: pipe.ingest(frames), reps)
    snap = pipe.host_snapshot()
    rng = np.random.default_rng(0)
    q = snap.points[rng.integers(0, snap.n_points, args.queries), :3].copy()
    tq = _time(lambda: pipe.neighbors(q, R3, max_neighbors=4096), reps)
    nb = pipe.neighbors(q, R3, max_neighbors=4096)

    out.update({
        "points_1cam": int(one.host_snapshot().n_points),
        "points_4cam": int(snap.n_points),
        "cameras": len(cams),
        "queries": int(args.queries),
        "mean_neighbors": round(float(nb.count.mean()), 1),
        "ingest_ms_1cam_p50": round(pct(t1, 50), 3),
        "ingest_ms_1cam_p99": round(pct(t1, 99), 3),
        "ingest_ms_4cam_p50": round(pct(t4, 50), 3),
        "ingest_ms_4cam_p99": round(pct(t4, 99), 3),
        "hash_query_ms_4cam_p50": round(pct(tq, 50), 3),
    })

    from scipy.spatial import cKDTree

    pts = np.ascontiguousarray(snap.points[:, :3], dtype=np.float64)

    def kdtree():
        tree = cKDTree(pts)
        return tree.query_ball_point(q, R3)

    tk = _time(kdtree, max(3, reps // 10))
    counts = np.array([len(x) for x in kdtree()])
    proj = ProjectiveSearch(cams, frames)
    tp = _time(lambda: [proj.query(x, R3) for x in q], max(3, reps // 10))

    hash_total = pct(t4, 50) + pct(tq, 50)
    out.update({
        "ckdtree_ms_4cam_p50": round(pct(tk, 50), 3),
        "projective_ms_4cam_p50": round(pct(tp, 50), 3),
        "ckdtree_neighbors_match": bool(np.array_equal(counts, nb.count)),
        "speedup_vs_ckdtree": round(pct(tk, 50) / hash_total, 2),
        "speedup_vs_projective": round(pct(tp, 50) / hash_total, 2),
    })
    return out
