"""What one point contributes to a proxy step, on the Warp device, and the hash path's passes.

The same algorithm as kernels/proxy.py (the NumPy reference) and kernels/opencl/proxy.cl: step
1 (clearances, normal sum, smallest clearance), step 3 (the swept-sphere clip) and the push
away from the deepest points, for one point at a time; the working-set passes
(kernels/warp/working_set.py) and the hash passes below call them. Points are float4 (x, y, z
in the world frame, m; w the fixture radius, m) taken where the tick predicts them, p + v dt
(kernels/motion.py). The hash path scans the cells within ``span`` of the proxy in global
memory, each thread of the block taking every ``bd``-th point of a row: the cold path, for a
working set that does not fit in shared memory (each pass has one call site, in
kernels/warp/steps.py's hash loop, where it is inlined).
"""
from __future__ import annotations

import warp as wp

from .args import ProxyArgs
from .frames import GridArgs
from .primitives import div_fast, mul_rn, rsqrt_fast


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
    """The point's clearance radius, m: its own (fixture mode) or r1."""
    return wp.where(a.fixture != 0, p[3], a.r1)



@wp.func
def unit_len(v: wp.vec3):
    """(v / |v|, |v|), zero for v = 0."""
    l2 = wp.dot(v, v)
    inv = wp.where(l2 > 0.0, rsqrt_fast(l2), 0.0)
    return v * inv, l2 * inv


@wp.func
def eval_point_e(X: wp.vec3, q: wp.vec4, a: ProxyArgs, ns: wp.vec3, me: float):
    """Step 1 for one point: its share of the normal sum and of the smallest clearance, and
    its clearance."""
    dv = wp.vec3(X[0] - q[0], X[1] - q[1], X[2] - q[2])
    d2 = dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2]
    inv = wp.where(d2 > 0.0, rsqrt_fast(d2), 0.0)
    e = mul_rn(d2, inv) - clearance_radius(q, a)
    near = e < a.nreach
    me = wp.where(near, wp.min(me, e), me)
    ns = ns + dv * wp.where(near, inv, 0.0)   # (without a branch: + 0 leaves ns as it is)
    return ns, me, e


@wp.func
def eval_point(X: wp.vec3, q: wp.vec4, a: ProxyArgs, ns: wp.vec3, me: float):
    """Step 1 for one point: its share of the normal sum and of the smallest clearance."""
    ns, me, e = eval_point_e(X, q, a, ns, me)
    return ns, me


@wp.func
def clip_point(X: wp.vec3, u: wp.vec3, q: wp.vec4, a: ProxyArgs, off: float, tm: float) -> float:
    """Step 3 for one point (kernels/proxy.py); off = F + margin: a clear point stops the step
    where its clearance reaches off (swept sphere), a point at the limit (clearance below off)
    may not be approached at all."""
    dx = X[0] - q[0]
    dy = X[1] - q[1]
    dz = X[2] - q[2]
    d2 = dx * dx + dy * dy + dz * dz
    b = u[0] * dx + u[1] * dy + u[2] * dz
    rc = clearance_radius(q, a) + off
    c = d2 - rc * rc
    disc = b * b - c
    t = div_fast(c, -b + disc * rsqrt_fast(disc))   # (taken only where the sphere is hit)
    tm = wp.where(c >= 0.0 and b < 0.0 and disc > 0.0, wp.min(tm, t), tm)
    return wp.where(c < 0.0 and b < 0.0, 0.0, tm)


@wp.func
def away_point(X: wp.vec3, q: wp.vec4, a: ProxyArgs, off: float, ns: wp.vec3) -> wp.vec3:
    """This point's share of sum (X - P)/|X - P| over the points at the limit (clearance below off)."""
    dv = wp.vec3(X[0] - q[0], X[1] - q[1], X[2] - q[2])
    d2 = dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2]
    rc = clearance_radius(q, a) + off
    return ns + dv * wp.where(d2 - rc * rc < 0.0 and d2 > 0.0, rsqrt_fast(d2), 0.0)


@wp.func
def results_out(p: int, X: wp.vec3, nrm: wp.vec3, min_e: float, st: int, steps: int, conv: int,
                pos: wp.array(dtype=wp.vec3), nrm_out: wp.array(dtype=wp.vec3), near_out: wp.array(dtype=float),
                state_out: wp.array(dtype=wp.int32), steps_out: wp.array(dtype=wp.int32),
                conv_out: wp.array(dtype=wp.bool)):
    """Proxy p's tick results into the batch's arrays (one thread)."""
    pos[p] = X
    nrm_out[p] = nrm
    near_out[p] = min_e
    state_out[p] = st
    steps_out[p] = steps
    conv_out[p] = conv != 0


@wp.func
def set_holds(key: wp.vec4i, X0: wp.vec3, skin: float, build: int, dtb: int, span: int, X: wp.vec3) -> bool:
    """Whether a working set gathered around X0 with ``skin`` for ``key`` (build, dt bits, span)
    still serves a proxy at X in a tick of (build, dtb, span): the conditions under which
    ``run_steps`` keeps a set."""
    dx = X[0] - X0[0]
    dy = X[1] - X0[1]
    dz = X[2] - X0[2]
    return key[0] == build and key[1] == dtb and key[2] == span and dx * dx + dy * dy + dz * dz <= skin * skin


@wp.func
def cell_of(X: wp.vec3, g: GridArgs) -> wp.vec3i:
    """Cell of X, clamped to one cell outside the grid (a cell range's end)."""
    cx = int(wp.clamp(wp.floor((X[0] - g.origin[0]) * g.inv_h), -1.0, float(g.nx)))
    cy = int(wp.clamp(wp.floor((X[1] - g.origin[1]) * g.inv_h), -1.0, float(g.ny)))
    cz = int(wp.clamp(wp.floor((X[2] - g.origin[2]) * g.inv_h), -1.0, float(g.nz)))
    return wp.vec3i(cx, cy, cz)


@wp.func
def cell_box(X: wp.vec3, g: GridArgs, span: int) -> wp.vec3i:
    """Cell of X, clamped to span + 1 cells outside the grid (the reference's clamp)."""
    cx = int(wp.clamp(wp.floor((X[0] - g.origin[0]) * g.inv_h), float(-span - 1), float(g.nx + span)))
    cy = int(wp.clamp(wp.floor((X[1] - g.origin[1]) * g.inv_h), float(-span - 1), float(g.ny + span)))
    cz = int(wp.clamp(wp.floor((X[2] - g.origin[2]) * g.inv_h), float(-span - 1), float(g.nz + span)))
    return wp.vec3i(cx, cy, cz)


# --- the hash path: a thread's share of each pass over the cells within reach ---------------

@wp.func
def hash_eval(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float, order: wp.array(dtype=int),
              start: wp.array(dtype=int), g: GridArgs, a: ProxyArgs, X: wp.vec3, c: wp.vec3i, span: int,
              lane: int, bd: int):
    ns = wp.vec3(0.0)
    me = float(wp.inf)
    x0 = wp.max(c[0] - span, 0)
    x1 = wp.min(c[0] + span, g.nx - 1)
    if x0 <= x1:
        for iz in range(wp.max(c[2] - span, 0), wp.min(c[2] + span, g.nz - 1) + 1):
            for iy in range(wp.max(c[1] - span, 0), wp.min(c[1] + span, g.ny - 1) + 1):
                base = (iz * g.ny + iy) * g.nx
                for i in range(start[base + x0] + lane, start[base + x1 + 1], bd):
                    if a.fixture != 0 and order[i] >= 0:
                        continue
                    ns, me = eval_point(X, point_at(spts, svel, i, dt), a, ns, me)
    return ns, me


@wp.func
def hash_clip(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float, order: wp.array(dtype=int),
              start: wp.array(dtype=int), g: GridArgs, a: ProxyArgs, X: wp.vec3, u: wp.vec3, off: float,
              c: wp.vec3i, span: int, lane: int, bd: int) -> float:
    tm = float(wp.inf)
    x0 = wp.max(c[0] - span, 0)
    x1 = wp.min(c[0] + span, g.nx - 1)
    if x0 <= x1:
        for iz in range(wp.max(c[2] - span, 0), wp.min(c[2] + span, g.nz - 1) + 1):
            for iy in range(wp.max(c[1] - span, 0), wp.min(c[1] + span, g.ny - 1) + 1):
                base = (iz * g.ny + iy) * g.nx
                for i in range(start[base + x0] + lane, start[base + x1 + 1], bd):
                    if a.fixture != 0 and order[i] >= 0:
                        continue
                    tm = clip_point(X, u, point_at(spts, svel, i, dt), a, off, tm)
    return tm


@wp.func
def hash_away(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float, order: wp.array(dtype=int),
              start: wp.array(dtype=int), g: GridArgs, a: ProxyArgs, X: wp.vec3, off: float, c: wp.vec3i,
              span: int, lane: int, bd: int) -> wp.vec3:
    ns = wp.vec3(0.0)
    x0 = wp.max(c[0] - span, 0)
    x1 = wp.min(c[0] + span, g.nx - 1)
    if x0 <= x1:
        for iz in range(wp.max(c[2] - span, 0), wp.min(c[2] + span, g.nz - 1) + 1):
            for iy in range(wp.max(c[1] - span, 0), wp.min(c[1] + span, g.ny - 1) + 1):
                base = (iz * g.ny + iy) * g.nx
                for i in range(start[base + x0] + lane, start[base + x1 + 1], bd):
                    if a.fixture != 0 and order[i] >= 0:
                        continue
                    ns = away_point(X, point_at(spts, svel, i, dt), a, off, ns)
    return ns
