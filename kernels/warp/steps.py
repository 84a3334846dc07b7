"""One tick's steps of a proxy (dissertation 2.2.4), as a block of threads runs them on Warp.

The same algorithm as kernels/proxy.py (the NumPy reference) and kernels/opencl/proxy.cl. Each
step evaluates the clearances (normal sum and smallest clearance: a block-wide reduction),
chooses the direction and length by the contact rules, clips the step against the swept
spheres (a block-wide minimum; up to three tries with one clip pass in the code: the push-out
along the normal, the contact rule's direction, away from the deepest points) and moves. Every
thread takes the same decision from the reduced values, so the step loop stays uniform across
the block. A proxy reads its working set in shared memory (kernels/warp/working_set.py) or,
where none fits, the hash in global memory (kernels/warp/points.py), and gathers again when it
has wandered further than its skin.

Two loops run these steps. ``run_steps``, the hot one, knows only the working set: its code is
small enough to stay in the instruction cache (the profiles ranked instruction fetch among the
step's first stalls when the hash path, the away pass and their call sites sat in the loop).
Where no working set fits (the first gather or a regather gave -1), it hands the proxy, from
that step on, to ``run_steps_any``, a function of its own that also scans the hash. Both are
one source (``make_loop``; ``wp.static`` leaves the hash path out of the hot loop's code), so
the results do not depend on which loop ran a step.
"""
from __future__ import annotations

import warp as wp

from .args import ProxyArgs
from .frames import GridArgs
from .points import cell_box, hash_away, hash_clip, hash_eval, unit_len
from .primitives import block_min, block_reduce4


@wp.func
def plan(X: wp.vec3, H: wp.vec3, rd: wp.vec4, a: ProxyArgs):
    """Step 2 from the reduced clearances ``rd`` (normal sum, smallest clearance, m): (state,
    unit normal, whether there is one, the contact rule's direction and length u2, L2, the
    push-out length Lp, off = limit F + margin, whether buried, whether the first clip pushes
    out along the normal)."""
    nsum = wp.vec3(rd[0], rd[1], rd[2])
    min_e = rd[3]
    st = int(0)
    if min_e < 0.0:
        st = 2
    elif min_e < a.band:
        st = 1
    nrm, nn = unit_len(nsum)
    v = H - X
    vn = wp.dot(v, nrm)
    vp = v - vn * nrm
    has_n = nn > 0.0
    # contact rules (3/4): along v with the HIP outside or no normal, else along vp
    w = vp
    if st == 0 or vn > 0.0 or not has_n:
        w = v
    u2, L2 = unit_len(w)
    L2 = wp.min(L2, a.step)
    Lp = wp.min(0.5 * a.band - min_e, a.step)
    # limit F: mid-band for a free step, -slack otherwise, min e where buried (the deepest
    # penetration never grows); off = F + margin
    buried = st == 2 and min_e < -a.slack - a.margin
    lim = -a.slack
    if st == 0:
        lim = 0.5 * a.band
    elif buried:
        lim = min_e
    push = st == 2 and has_n
    return st, nrm, u2, L2, Lp, lim + a.margin, buried, push


@wp.func
def turned_back(u: wp.vec3, uprev: wp.vec3, a: ProxyArgs) -> bool:
    """Whether a slide along u turns back against the previous one (rocking in a crease)."""
    return u[0] * uprev[0] + u[1] * uprev[1] + u[2] * uprev[2] < a.turn_back


def make_run_steps(bd: int, gather, ws_eval, ws_clip, ws_away):
    """``run_steps`` for blocks of ``bd`` threads over one working set's functions
    (``make_working_set(cap, bd)``)."""
    BD = bd

    @wp.func(inline=False)  # rare: both the push-out and the contact direction blocked, buried
    def away_dir(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float,
                 order: wp.array(dtype=int), start: wp.array(dtype=int), g: GridArgs, a: ProxyArgs, X: wp.vec3,
                 off: float, n_ws: int, c: wp.vec3i, span: int, lane: int, par: int):
        """The direction away from the deepest points (unit, its length before normalising) and
        the next reduction's ``par``."""
        av = wp.vec3(0.0)
        if n_ws >= 0:
            av = ws_away(X, a, off, n_ws, lane, BD)
        else:
            av = hash_away(spts, svel, dt, order, start, g, a, X, off, c, span, lane, BD)
        ra = block_reduce4(wp.vec4(av[0], av[1], av[2], 0.0), 0, par, BD)
        au, al = unit_len(wp.vec3(ra[0], ra[1], ra[2]))
        return au, al, 1 - par

    def make_loop(HASH: bool):
        """The step loop from step ``it0`` on (``steps`` taken, ``uprev`` the last slide): over
        the working set only (HASH False: ``run_steps``; where a gather finds no set that fits it
        hands the proxy on to the other loop from that step), or over the working set where one
        fits and the hash where none does (HASH True: ``run_steps_any``). One source for both:
        ``wp.static`` leaves the hash path out of the hot loop's code."""

        def loop(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float,
                 order: wp.array(dtype=int), start: wp.array(dtype=int), g: GridArgs, a: ProxyArgs,
                 X: wp.vec3, H: wp.vec3, span: int, grad: float, lane: int, wbase: int, X0: wp.vec3,
                 n_ws: int, par: int, skin: float, it0: int, steps: int, uprev: wp.vec3):
            conv = int(0)
            st = int(0)
            nrm = wp.vec3(0.0)
            min_e = float(wp.inf)
            it_any = int(-1)
            for it in range(it0, a.max_steps + 1):
                if it > it0:
                    dx = X[0] - X0[0]
                    dy = X[1] - X0[1]
                    dz = X[2] - X0[2]
                    if dx * dx + dy * dy + dz * dz > skin * skin:  # wandered off its working set
                        X0 = X
                        n_ws, par, skin = gather(spts, svel, dt, order, start, g, a, X0, grad, lane, BD, par)
                c = wp.vec3i(0)
                if wp.static(not HASH):
                    if n_ws < 0:   # no working set fits here: the hash path from this step on
                        it_any = it
                        break

                # 1. clearances, normal sum, smallest clearance within the normal band
                ns = wp.vec3(0.0)
                me = float(wp.inf)
                nnear = int(0)
                if wp.static(HASH):
                    if n_ws >= 0:
                        ns, me, nnear = ws_eval(X, a, n_ws, lane, wbase)
                    else:
                        c = cell_box(X, g, span)
                        ns, me = hash_eval(spts, svel, dt, order, start, g, a, X, c, span, lane, BD)
                else:
                    ns, me, nnear = ws_eval(X, a, n_ws, lane, wbase)
                rd = block_reduce4(wp.vec4(ns[0], ns[1], ns[2], me), 8, par, BD)
                par = 1 - par
                min_e = rd[3]
                # 2. direction and length (dissertation 2.2.4)
                st, nrm, u2, L2, Lp, off, buried, push = plan(X, H, rd, a)
                if it == a.max_steps:
                    break

                # 3. clipping (block-wide minimum). Up to three tries, one clip pass in the code for
                # all of them: the push-out along n, then (blocked) the contact rule's direction,
                # then (buried and blocked again) away from the deepest points.
                along_n = push
                u = u2
                Lc = L2
                if push:
                    u = nrm
                    Lc = Lp
                s = float(0.0)
                attempt = int(0)
                while attempt < 3:
                    tm = float(wp.inf)
                    if wp.static(HASH):
                        if n_ws >= 0:
                            tm = ws_clip(X, u, a, off, nnear, lane, wbase)
                        else:
                            tm = hash_clip(spts, svel, dt, order, start, g, a, X, u, off, c, span, lane, BD)
                    else:
                        tm = ws_clip(X, u, a, off, nnear, lane, wbase)
                    t = block_min(tm, par, BD)
                    par = 1 - par
                    s = wp.max(wp.min(Lc, t), 0.0)
                    if s >= a.tol:
                        break
                    if attempt == 0:
                        if not push:
                            break
                        along_n = False  # push-out blocked: the contact rule's direction instead
                        u = u2
                        Lc = L2
                    elif attempt == 1:
                        if not buried:
                            break
                        along_n = True  # both blocked: away from the deepest points
                        au, al, par = away_dir(spts, svel, dt, order, start, g, a, X, off, n_ws, c, span, lane,
                                               par)
                        s = 0.0
                        if not (al > 0.0):
                            break
                        u = au
                        Lc = Lp
                    attempt += 1
                if s < a.tol:
                    conv = 1
                    break
                if not along_n:  # a slide turning back against the previous one: rocking in a crease
                    if turned_back(u, uprev, a):
                        conv = 1
                        break
                    uprev = u
                X = X + s * u
                steps += 1
            if wp.static(not HASH):
                if it_any >= 0:
                    return run_steps_any(spts, svel, dt, order, start, g, a, X, H, span, grad, lane, wbase, X0,
                                         n_ws, par, skin, it_any, steps, uprev)
            return X, nrm, min_e, st, steps, conv, X0, n_ws, par, skin

        loop.__name__ = loop.__qualname__ = "run_steps_any" if HASH else "run_steps_ws"
        # the cold path (a proxy with no working set in shared memory) is a function of its own
        return wp.func(loop) if not HASH else wp.func(inline=False)(loop)

    run_steps_any = make_loop(True)
    run_steps_ws = make_loop(False)

    @wp.func
    def run_steps(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float, order: wp.array(dtype=int),
                  start: wp.array(dtype=int), g: GridArgs, a: ProxyArgs, X: wp.vec3, H: wp.vec3, span: int,
                  grad: float, lane: int, wbase: int, X0: wp.vec3, n_ws: int, par: int, skin: float):
        """One tick's steps of a proxy at X towards H over its working set (gathered around X0:
        ``n_ws`` points, -1 for the hash path); returns (X, normal, nearest, state, steps,
        converged, and the working set's X0, n_ws, par, skin for the next tick)."""
        # A step's limit F is at most band / 2 (slack >= 0) and its length at most a.step, so a
        # point with clearance e >= band / 2 + margin + step cannot shorten it: the step reaches
        # that point's swept sphere (radius rho + F + margin) no sooner than e - F - margin >= step
        # >= L. ProxyArgs.rclip adds 1e-4 step and 1 um, which keep float32 rounding of e and of
        # the hit time out of the decision (as kernels/opencl/proxy.cl): the clip scans only each
        # thread's points below rclip (ws_eval) and gets the very same step length.
        return run_steps_ws(spts, svel, dt, order, start, g, a, X, H, span, grad, lane, wbase, X0, n_ws, par, skin,
                            0, 0, wp.vec3(0.0))

    return run_steps
