"""`pointfence bench frames`: frame ingest against the peers a user would otherwise pick.

ingest = upload + deproject + transform + noise + radius + selection + crop + counting sort
(with each cell put into pixel order, so that builds are deterministic),
for 1 and 4 cameras at 640x480 on a synthetic tabletop; where the backend has a depth staging
buffer (Warp), also with the frames already written into it by the cameras
(``ingest_staged_ms_4cam_*``: the ingest without its host copy). Peers, on the same points and queries:
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
    staged = None
    if pipe.depth_staging(0) is not None:   # frames written by the cameras into the upload buffer
        from dataclasses import replace

        views = [pipe.depth_staging(i) for i in range(len(cams))]
        for v, f in zip(views, frames):
            np.copyto(v, f.depth)
        in_place = [replace(f, depth=v) for f, v in zip(frames, views)]
        staged = _time(lambda: pipe.ingest(in_place), reps)
    snap = pipe.host_snapshot()
    rng = np.random.default_rng(0)
    q = snap.points[rng.integers(0, snap.n_points, args.queries), :3].copy()
    tq = _time(lambda: pipe.neighbors(q, R3, max_neighbors=4096), reps)
    nb = pipe.neighbors(q, R3, max_neighbors=4096)
    # the same queries on a grid of R3 cells (as the proxy's pipeline sizes its cells to its reach,
    # and as wp.HashGrid is built below): 27 cells of 1 cm scanned instead of 27 of 3 cm
    fine = backend.pipeline(cams, tabletop_params(cell_size=R3))
    fine.ingest(frames)
    tqf = _time(lambda: fine.neighbors(q, R3, max_neighbors=4096), reps)
    nbf = fine.neighbors(q, R3, max_neighbors=4096)

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
        **({} if staged is None else {"ingest_staged_ms_4cam_p50": round(pct(staged, 50), 3),
                                      "ingest_staged_ms_4cam_p99": round(pct(staged, 99), 3)}),
        "hash_query_ms_4cam_p50": round(pct(tq, 50), 3),
        "hash_query_r3_cells_ms_4cam_p50": round(pct(tqf, 50), 3),
    })

    from scipy.spatial import cKDTree

    pts = np.ascontiguousarray(snap.points[:, :3], dtype=np.float64)

    def kdtree():
        tree = cKDTree(pts)
        return tree.query_ball_point(q, R3)

    tk = _time(kdtree, max(3, reps // 10))
    # the hash compares float32 distances: points within float32 rounding of R3 may go either way
    tree = cKDTree(pts)
    lo = tree.query_ball_point(q, R3 * (1 - 1e-6), return_length=True)
    hi = tree.query_ball_point(q, R3 * (1 + 1e-6), return_length=True)
    proj = ProjectiveSearch(cams, frames)
    tp = _time(lambda: [proj.query(x, R3) for x in q], max(3, reps // 10))

    if backend.name == "warp":
        out.update(_warp_hashgrid_peer(backend, snap, q, reps))
    hash_total = pct(t4, 50) + pct(tq, 50)
    out.update({
        "ckdtree_ms_4cam_p50": round(pct(tk, 50), 3),
        "projective_ms_4cam_p50": round(pct(tp, 50), 3),
        "ckdtree_neighbors_match": bool(np.all((lo <= nb.count) & (nb.count <= hi))
                                        & np.all((lo <= nbf.count) & (nbf.count <= hi))),
        "speedup_vs_ckdtree": round(pct(tk, 50) / hash_total, 2),
        "speedup_vs_projective": round(pct(tp, 50) / hash_total, 2),
    })
    return out


def _warp_hashgrid_peer(backend, snap, q, reps) -> dict:
    """Warp's own wp.HashGrid on the same points: build time, and a query kernel counting the
    same neighbourhoods (the issue's alternative to our counting-sort grid)."""
    import warp as wp

    dev = backend.device
    pts = wp.array(snap.points[:, :3].copy(), dtype=wp.vec3, device=dev)
    qa = wp.array(q, dtype=wp.vec3, device=dev)
    counts = wp.zeros(len(q), dtype=int, device=dev)
    grid = wp.HashGrid(128, 128, 128, device=dev)

    @wp.kernel
    def count(grid: wp.uint64, pts: wp.array(dtype=wp.vec3), qs: wp.array(dtype=wp.vec3), r: float,
              out: wp.array(dtype=int)):
        i = wp.tid()
        x = qs[i]
        n = int(0)
        for j in wp.hash_grid_query(grid, x, r):
            if wp.length(pts[j] - x) <= r:
                n += 1
        out[i] = n

    def build():
        grid.build(pts, R3)
        wp.synchronize_device(dev)

    def query():
        wp.launch(count, dim=len(q), inputs=[grid.id, pts, qa, R3, counts], device=dev)
        wp.synchronize_device(dev)

    build()
    query()
    tb, tq = _time(build, reps), _time(query, reps)
    return {"warp_hashgrid_build_ms_4cam_p50": round(pct(tb, 50), 3),
            "warp_hashgrid_query_ms_4cam_p50": round(pct(tq, 50), 3)}
