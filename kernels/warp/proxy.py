"""Warp proxy batch: one launch per haptic tick for all proxies, one thread block per proxy.

Same algorithm as kernels/proxy.py (the NumPy reference and kernels/opencl/proxy.cl). On a
GPU a proxy's neighbourhood (about 1500 points within R3 on a close-range frame) is spread over
the ``block_dim`` threads of its block: each thread takes every block_dim-th candidate of the
cells within reach, and the normal sum, the smallest clearance and the swept-sphere step limit
are block-wide reductions (``wp.tile_sum`` / ``wp.tile_min``). Every thread then takes the same
decision from the reduced values, so the step loop stays uniform across the block.

On CUDA the tick (HIP upload from pinned memory, the launch, the result download) is captured
once per snapshot slot into a CUDA graph and replayed each tick; nothing is allocated per tick.
Candidates are read from the snapshot's cell-sorted copy of the points: the lanes of a block
read consecutive points (one coalesced load each) instead of an index and then a point.
"""
from __future__ import annotations

import os

import numpy as np
import warp as wp

from ..errors import KernelError
from ..motion import extra_span
from ..neighbors import search_span
from ..proxy import ProxyBatch
from .frames import GridArgs

vec8 = wp.types.vector(length=8, dtype=wp.float32)

#: threads per proxy on CUDA (one block each) by batch size: (largest batch, threads). A small
#: batch spreads each proxy over many threads (latency); a large one over fewer, so that more
#: blocks run at once (throughput). H100 sweep, apc frame 49 (bench/RESULTS.md): 1 proxy fastest
#: with 256, 1,024 with 128, 65,536 with 32 (12 M proxies/s against 6.4 M with 256).
BLOCK_DIMS = ((64, 256), (4096, 128), (1 << 62, 32))
#: one size for every batch instead (POINTFENCE_WARP_BLOCK_DIM); Warp's CPU device runs one
#: thread per block
BLOCK_DIM = int(os.environ["POINTFENCE_WARP_BLOCK_DIM"]) if os.environ.get("POINTFENCE_WARP_BLOCK_DIM") else None


def block_dim_for(n: int) -> int:
    """Threads per proxy for a batch of ``n`` proxies on CUDA."""
    if BLOCK_DIM:
        return BLOCK_DIM
    return next(bd for most, bd in BLOCK_DIMS if n <= most)


@wp.struct
class ProxyArgs:
    r1: float
    band: float  # r2 - r1
    nreach: float  # r3 - r1
    step: float
    tol: float
    slack: float
    margin: float
    turn_back: float  # turn_back_cos
    fixture: int
    max_steps: int
    span: int  # cells searched on each side (reach, without motion)


@wp.struct
class TickArgs:
    """Per-tick values, copied to the device with the HIPs (inside the CUDA graph)."""

    dt: float  # prediction time: points are taken at p + v dt (kernels/motion.py)
    span: int  # cells searched on each side: reach plus the motion's extra reach


@wp.func
def point_at(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), i: int, dt: float) -> wp.vec4:
    """Sorted point i where the tick predicts it: p + v dt (dt = 0: untouched)."""
    q = spts[i]
    if dt > 0.0:
        v = svel[i]
        q = wp.vec4(q[0] + v[0] * dt, q[1] + v[1] * dt, q[2] + v[2] * dt, q[3])
    return q


@wp.func
def clearance_radius(p: wp.vec4, a: ProxyArgs) -> float:
    if a.fixture != 0:
        return p[3]
    return a.r1


@wp.func
def clip_partial(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float, order: wp.array(dtype=int), start: wp.array(dtype=int), g: GridArgs,
                 a: ProxyArgs, X: wp.vec3, u: wp.vec3, off: float, x0: int, x1: int, y0: int, y1: int,
                 z0: int, z1: int, lane: int, bd: int) -> float:
    """This thread's share of the step limit along u (kernels/proxy.py, step 3); off = F + margin:
    a clear point stops the step where its clearance reaches off (swept sphere), a point at the
    limit (clearance below off) may not be approached at all."""
    tm = float(wp.inf)
    if x0 <= x1:
        for iz in range(z0, z1 + 1):
            for iy in range(y0, y1 + 1):
                base = (iz * g.ny + iy) * g.nx
                for i in range(start[base + x0] + lane, start[base + x1 + 1], bd):
                    if a.fixture != 0 and order[i] >= 0:
                        continue
                    q = point_at(spts, svel, i, dt)
                    dx = X[0] - q[0]
                    dy = X[1] - q[1]
                    dz = X[2] - q[2]
                    d2 = dx * dx + dy * dy + dz * dz
                    b = u[0] * dx + u[1] * dy + u[2] * dz
                    rc = clearance_radius(q, a) + off
                    c = d2 - rc * rc
                    disc = b * b - c
                    if c >= 0.0 and b < 0.0 and disc > 0.0:
                        tm = wp.min(tm, c / (-b + wp.sqrt(disc)))
                    elif c < 0.0 and b < 0.0:
                        tm = 0.0
    return tm


@wp.func
def away_partial(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float, order: wp.array(dtype=int), start: wp.array(dtype=int), g: GridArgs,
                 a: ProxyArgs, X: wp.vec3, off: float, x0: int, x1: int, y0: int, y1: int, z0: int, z1: int,
                 lane: int, bd: int) -> wp.vec3:
    """This thread's share of sum (X - P)/|X - P| over the points at the limit (clearance below off)."""
    ns = wp.vec3(0.0)
    if x0 <= x1:
        for iz in range(z0, z1 + 1):
            for iy in range(y0, y1 + 1):
                base = (iz * g.ny + iy) * g.nx
                for i in range(start[base + x0] + lane, start[base + x1 + 1], bd):
                    if a.fixture != 0 and order[i] >= 0:
                        continue
                    q = point_at(spts, svel, i, dt)
                    dv = wp.vec3(X[0] - q[0], X[1] - q[1], X[2] - q[2])
                    d2 = dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2]
                    d = wp.sqrt(d2)
                    rc = clearance_radius(q, a) + off
                    if d2 - rc * rc < 0.0 and d > 0.0:
                        ns = ns + dv / d
    return ns


@wp.kernel
def proxy_tick(spts: wp.array(dtype=wp.vec4), order: wp.array(dtype=int), start: wp.array(dtype=int), g: GridArgs,
               a: ProxyArgs, pos: wp.array(dtype=wp.vec3), hips: wp.array(dtype=wp.vec3), bd: int,
               out: wp.array(dtype=vec8), svel: wp.array(dtype=wp.vec4), tick: wp.array(dtype=TickArgs)):
    p, lane = wp.tid()
    dt = tick[0].dt
    span = tick[0].span
    X = pos[p]
    H = hips[p]
    steps = int(0)
    conv = int(0)
    st = int(0)
    nrm = wp.vec3(0.0)
    min_e = float(wp.inf)
    uprev = wp.vec3(0.0)  # direction of the last sliding or free step
    for it in range(a.max_steps + 1):
        # cells within reach of X
        cx = int(wp.clamp(wp.floor((X[0] - g.origin[0]) * g.inv_h), float(-span - 1), float(g.nx + span)))
        cy = int(wp.clamp(wp.floor((X[1] - g.origin[1]) * g.inv_h), float(-span - 1), float(g.ny + span)))
        cz = int(wp.clamp(wp.floor((X[2] - g.origin[2]) * g.inv_h), float(-span - 1), float(g.nz + span)))
        x0 = wp.max(cx - span, 0)
        x1 = wp.min(cx + span, g.nx - 1)
        y0 = wp.max(cy - span, 0)
        y1 = wp.min(cy + span, g.ny - 1)
        z0 = wp.max(cz - span, 0)
        z1 = wp.min(cz + span, g.nz - 1)

        # 1. clearances, normal sum, smallest clearance within the normal band
        ns = wp.vec3(0.0)
        me = float(wp.inf)
        if x0 <= x1:
            for iz in range(z0, z1 + 1):
                for iy in range(y0, y1 + 1):
                    base = (iz * g.ny + iy) * g.nx
                    for i in range(start[base + x0] + lane, start[base + x1 + 1], bd):
                        if a.fixture != 0 and order[i] >= 0:
                            continue
                        q = point_at(spts, svel, i, dt)
                        dv = wp.vec3(X[0] - q[0], X[1] - q[1], X[2] - q[2])
                        d = wp.sqrt(dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2])
                        e = d - clearance_radius(q, a)
                        if e < a.nreach:
                            me = wp.min(me, e)
                            if d > 0.0:
                                ns = ns + dv / d
        nt = wp.tile_sum(wp.tile(ns), axis=1)  # wp.tile of a vec3 is a (3, block_dim) tile
        nsum = wp.vec3(nt[0], nt[1], nt[2])
        min_e = wp.tile_min(wp.tile(me))[0]
        st = 0
        if min_e < 0.0:
            st = 2
        elif min_e < a.band:
            st = 1
        nn = wp.length(nsum)
        nrm = wp.vec3(0.0)
        if nn > 0.0:
            nrm = nsum / nn
        if it == a.max_steps:
            break

        # 2. direction and length (dissertation 2.2.4)
        v = H - X
        vl = wp.length(v)
        vn = wp.dot(v, nrm)
        vp = v - vn * nrm
        vpl = wp.length(vp)
        has_n = nn > 0.0
        # contact rules (3/4): along v with the HIP outside or no normal, else along vp
        u2 = wp.vec3(0.0)
        L2 = float(0.0)
        if st == 0 or vn > 0.0 or not has_n:
            if vl > 0.0:
                u2 = v / vl
                L2 = vl
        elif vpl > 0.0:
            u2 = vp / vpl
            L2 = vpl
        L2 = wp.min(L2, a.step)
        u = u2
        L = L2
        Lp = wp.min(0.5 * a.band - min_e, a.step)
        # limit F: mid-band for a free step, -slack otherwise, min e where buried (the deepest
        # penetration never grows); off = F + margin
        buried = st == 2 and min_e < -a.slack - a.margin
        lim = -a.slack
        if st == 0:
            lim = 0.5 * a.band
        elif buried:
            lim = min_e
        off = lim + a.margin

        # 3. clipping (block-wide minimum)
        push = st == 2 and has_n
        if push:
            u = nrm
            L = Lp
        tm = clip_partial(spts, svel, dt, order, start, g, a, X, u, off, x0, x1, y0, y1, z0, z1, lane, bd)
        t = wp.tile_min(wp.tile(tm))[0]
        s = wp.max(wp.min(L, t), 0.0)
        along_n = push
        if push and s < a.tol:  # push-out blocked: the contact rule's direction instead
            along_n = False
            u = u2
            tm = clip_partial(spts, svel, dt, order, start, g, a, X, u, off, x0, x1, y0, y1, z0, z1, lane, bd)
            t = wp.tile_min(wp.tile(tm))[0]
            s = wp.max(wp.min(L2, t), 0.0)
            if buried and s < a.tol:  # both blocked: away from the deepest points
                along_n = True
                av = away_partial(spts, svel, dt, order, start, g, a, X, off, x0, x1, y0, y1, z0, z1, lane, bd)
                at = wp.tile_sum(wp.tile(av), axis=1)
                asum = wp.vec3(at[0], at[1], at[2])
                al = wp.length(asum)
                s = 0.0
                if al > 0.0:
                    u = asum / al
                    tm = clip_partial(spts, svel, dt, order, start, g, a, X, u, off, x0, x1, y0, y1, z0, z1, lane, bd)
                    t = wp.tile_min(wp.tile(tm))[0]
                    s = wp.max(wp.min(Lp, t), 0.0)
        if s < a.tol:
            conv = 1
            break
        if not along_n:  # a slide turning back against the previous one: rocking in a crease
            if u[0] * uprev[0] + u[1] * uprev[1] + u[2] * uprev[2] < a.turn_back:
                conv = 1
                break
            uprev = u
        X = X + s * u
        steps += 1

    if lane == 0:
        pos[p] = X
        out[p] = vec8(X[0], X[1], X[2], min_e, nrm[0], nrm[1], nrm[2], float(st + 4 * conv + 8 * steps))


class WarpProxies(ProxyBatch):
    """Proxies on a ``WarpPipeline``; create with ``pipeline.proxies(positions, params)``."""

    def __init__(self, pipeline, positions, params=None, block_dim: int | None = None):
        """``block_dim``: threads per proxy on CUDA (None: by batch size, ``block_dim_for``)."""
        self.dev = pipeline.device
        self.cuda = self.dev.is_cuda
        self._block_dim_request = block_dim
        self.stream = pipeline.query_stream
        self._graphs = {}
        super().__init__(pipeline, positions, params)
        p = self.params
        a = self.args = ProxyArgs()
        a.r1, a.band, a.nreach, a.step = p.r1, p.band, p.r3 - p.r1, p.step
        a.tol, a.slack, a.fixture, a.max_steps = p.tolerance, p.slack, int(p.mode == "fixture"), p.max_steps
        a.margin = p.margin
        a.turn_back = p.turn_back_cos
        a.span = search_span(self.reach, pipeline.grid.h)
        self._tick = wp.zeros(1, dtype=TickArgs, device=self.dev)
        self._tick_host = wp.zeros(1, dtype=TickArgs, device="cpu", pinned=self.cuda)
        self._tick_np = self._tick_host.numpy()
        self._tick_np[0]["span"] = a.span

    def _grow(self, cap: int):
        dev = self.dev
        self._pos = wp.zeros(cap, dtype=wp.vec3, device=dev)
        self._hips = wp.zeros(cap, dtype=wp.vec3, device=dev)
        self._out = wp.zeros(cap, dtype=vec8, device=dev)
        self._hips_host = wp.zeros(cap, dtype=wp.vec3, device="cpu", pinned=self.cuda)
        self._out_host = wp.zeros(cap, dtype=vec8, device="cpu", pinned=self.cuda)
        self._hips_np = self._hips_host.numpy()
        self._out_np = self._out_host.numpy()
        self._graphs.clear()

    def _upload_positions(self):
        n = self.n
        wp.copy(self._pos, wp.array(self._positions[:n], dtype=wp.vec3, device="cpu"), count=n)
        self._graphs.clear()

    def block_dim(self, n: int | None = None) -> int:
        """Threads per proxy of a launch for ``n`` proxies (default: the batch's size)."""
        if not self.cuda:
            return 1
        return self._block_dim_request or block_dim_for(self.n if n is None else n)

    def _record(self, slot, n):
        bd = self.block_dim(n)
        wp.copy(self._hips, self._hips_host, count=n)
        wp.copy(self._tick, self._tick_host)
        wp.launch_tiled(proxy_tick, dim=[n], inputs=[slot.sorted_pts, slot.order, slot.start, self.pipeline.grid_args,
                        self.args, self._pos, self._hips, bd, self._out, slot.sorted_vel, self._tick],
                        block_dim=bd, device=self.dev)
        wp.copy(self._out_host, self._out, count=n)

    def _capture(self, slot, n):
        """The tick's CUDA graph for snapshot slot ``slot`` and ``n`` proxies (captured once)."""
        with wp.ScopedStream(self.stream):
            wp.capture_begin(device=self.dev, stream=self.stream)
            try:
                self._record(slot, n)
            finally:
                graph = wp.capture_end(device=self.dev, stream=self.stream)
        self._graphs[(id(slot), n)] = graph
        return graph

    def _step(self, hips):
        n = self.n
        if n == 0:
            return
        self._hips_np[:n] = hips
        try:
            with self.pipeline.buffers.read() as slot:
                dt = self._tick_dt(min(slot.timestamps) if slot.timestamps else 0.0, slot.vmax)
                tk = self._tick_np[0]
                tk["dt"] = dt
                tk["span"] = search_span(self.reach + extra_span(slot.vmax, dt), self.pipeline.grid.h)
                if not self.cuda:
                    self._record(slot, n)
                else:
                    graph = self._graphs.get((id(slot), n))
                    if graph is None:
                        graph = self._capture(slot, n)
                    wp.capture_launch(graph, stream=self.stream)
                    wp.synchronize_stream(self.stream)
        except Exception as e:  # Warp reports CUDA failures as RuntimeError
            raise KernelError(f"Warp proxy kernel failed on {self.pipeline.backend.device_name}: {e}") from e
        out = self._out_np
        np.copyto(self._positions[:n], out[:n, :3])
        np.copyto(self._nearest[:n], out[:n, 3])
        np.copyto(self._normals[:n], out[:n, 4:7])
        info = self._info[:n]
        np.copyto(info, out[:n, 7], casting="unsafe")   # st + 4 conv + 8 steps, exact in float32
        np.bitwise_and(info, 3, out=self._states[:n])
        np.right_shift(info, 3, out=self._steps[:n])
        np.bitwise_and(info, 4, out=info)
        np.not_equal(info, 0, out=self._converged[:n])

    def _alloc(self, n: int):
        grew = n > self._cap
        super()._alloc(n)
        if grew:
            self._info = np.zeros(self._cap, np.int32)
