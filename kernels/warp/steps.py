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

Two loops run these steps, and the tick kernel calls no function that is not inlined. A call
that the compiler cannot inline makes it keep, around the call, every value live across it and
the callee's own registers on top: the gather, the hash loop and the away pass called that way
put the kernel at about 240 registers a thread (two blocks of 128 threads an SM); inlined, about
200, and the loop over a working set runs without a spill under a cap of 168 (three blocks an
SM; ``WarpTuning.maxregs``). So ``run_steps`` is a small driver: it gathers (the one
call site of ``gather`` in the kernel), runs ``run_steps_ws`` (the hot loop: the working set
only) or, where no set fits, ``run_steps_hash`` (the hash in global memory), and gathers again
where a loop returns the step at which the proxy wandered further than its skin. Both loops are
one source (``make_loop``; ``wp.static`` picks each one's passes), so the results do not depend
on which loop ran a step, and a register cap (``WarpTuning.maxreg_for``) spills only in the cold
code around them (bench/HISTORY.md, stop 43).
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

    def make_away(HASH: bool):
        """The push away from the deepest points (the third clip try) over the working set
        (HASH False) or over the hash."""

        def away(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float,
                 order: wp.array(dtype=int), start: wp.array(dtype=int), g: GridArgs, a: ProxyArgs, X: wp.vec3,
                 off: float, n_ws: int, c: wp.vec3i, span: int, lane: int, par: int):
            """The direction away from the deepest points (unit, its length before normalising)
            and the next reduction's ``par``."""
            av = wp.vec3(0.0)
            if wp.static(HASH):
                av = hash_away(spts, svel, dt, order, start, g, a, X, off, c, span, lane, BD)
            else:
                av = ws_away(X, a, off, n_ws, lane, BD)
            ra = block_reduce4(wp.vec4(av[0], av[1], av[2], 0.0), 0, par, BD)
            au, al = unit_len(wp.vec3(ra[0], ra[1], ra[2]))
            return au, al, 1 - par

        away.__name__ = away.__qualname__ = "away_hash" if HASH else "away_ws"
        return wp.func(away)

    def make_loop(HASH: bool):
        """The step loop from step ``it0`` on (``steps`` taken, ``uprev`` the last slide) over the
        working set (HASH False: ``run_steps_ws``, the hot loop) or over the hash where no set fits
        (HASH True: ``run_steps_hash``, the cold one). Neither calls a function that is not
        inlined, nor gathers: where the proxy has wandered further than its skin a loop returns
        that step's number (nothing of it done) and ``run_steps`` gathers there and goes on with
        the loop the new set asks for. One source for both (``wp.static`` picks the passes), so
        the results do not depend on which loop ran a step."""
        away_dir = make_away(HASH)

        def loop(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float,
                 order: wp.array(dtype=int), start: wp.array(dtype=int), g: GridArgs, a: ProxyArgs,
                 X: wp.vec3, H: wp.vec3, span: int, grad: float, lane: int, wbase: int, X0: wp.vec3,
                 n_ws: int, par: int, skin: float, it0: int, steps: int, uprev: wp.vec3):
            conv = int(0)
            st = int(0)
            nrm = wp.vec3(0.0)
            min_e = float(wp.inf)
            it_out = int(-1)
            for it in range(it0, a.max_steps + 1):
                if it > it0:
                    dx = X[0] - X0[0]
                    dy = X[1] - X0[1]
                    dz = X[2] - X0[2]
                    if dx * dx + dy * dy + dz * dz > skin * skin:  # wandered off its working set
                        it_out = it
                        break
                c = wp.vec3i(0)

                # 1. clearances, normal sum, smallest clearance within the normal band
                ns = wp.vec3(0.0)
                me = float(wp.inf)
                nnear = int(0)
                if wp.static(HASH):
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
                        au, al, par = away_dir(spts, svel, dt, order, start, g, a, X, off, n_ws, c, span, lane, par)
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
            return X, nrm, min_e, st, steps, conv, X0, n_ws, par, skin, it_out, uprev

        loop.__name__ = loop.__qualname__ = "run_steps_hash" if HASH else "run_steps_ws"
        return wp.func(loop)

    run_steps_hash = make_loop(True)
    run_steps_ws = make_loop(False)

    @wp.func
    def run_steps(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float, order: wp.array(dtype=int),
                  start: wp.array(dtype=int), g: GridArgs, a: ProxyArgs, X: wp.vec3, H: wp.vec3, span: int,
                  grad: float, lane: int, wbase: int, X0: wp.vec3, n_ws: int, par: int, skin: float):
        """One tick's steps of a proxy at X towards H over its working set (gathered around X0:
        ``n_ws`` points, -1 for the hash path, -2 for none yet: gathered around X first);
        returns (X, normal, nearest, state, steps, converged, and the working set's X0, n_ws,
        par, skin for the next tick)."""
        # A step's limit F is at most band / 2 (slack >= 0) and its length at most a.step, so a
        # point with clearance e >= band / 2 + margin + step cannot shorten it: the step reaches
        # that point's swept sphere (radius rho + F + margin) no sooner than e - F - margin >= step
        # >= L. ProxyArgs.rclip adds 1e-4 step and 1 um, which keep float32 rounding of e and of
        # the hit time out of the decision (as kernels/opencl/proxy.cl): the clip scans only each
        # thread's points below rclip (ws_eval) and gets the very same step length.
        it = int(0)
        steps = int(0)
        uprev = wp.vec3(0.0)
        nrm = wp.vec3(0.0)
        min_e = float(wp.inf)
        st = int(0)
        conv = int(0)
        while it >= 0:   # (a loop returns -1 when the tick's steps are done)
            if n_ws == -2 or it > 0:   # no set yet, or wandered off it at step it: gather around X
                X0 = X
                n_ws, par, skin = gather(spts, svel, dt, order, start, g, a, X0, grad, lane, BD, par)
            if n_ws >= 0:
                X, nrm, min_e, st, steps, conv, X0, n_ws, par, skin, it, uprev = run_steps_ws(
                    spts, svel, dt, order, start, g, a, X, H, span, grad, lane, wbase, X0, n_ws, par, skin, it,
                    steps, uprev)
            else:   # no working set fits here: the hash from this step on
                X, nrm, min_e, st, steps, conv, X0, n_ws, par, skin, it, uprev = run_steps_hash(
                    spts, svel, dt, order, start, g, a, X, H, span, grad, lane, wbase, X0, n_ws, par, skin, it,
                    steps, uprev)
        return X, nrm, min_e, st, steps, conv, X0, n_ws, par, skin

    return run_steps
