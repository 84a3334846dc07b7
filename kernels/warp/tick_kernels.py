"""The Warp proxy tick kernels: one thread block a proxy, all proxies in one launch.

``proxy_tick`` is the launched tick (a CUDA graph replayed each tick, or a plain launch on
Warp's CPU device): a block reads its proxy's inputs (on CUDA's zero-copy path from device
memory, where the tick's first blocks copy every block's: kernels/warp/tick_inputs.py), takes
its working set from the device memory cache where it still holds (kernels/warp/proxy.py keeps
it for batches of up to ``WarpTuning.ws_cache_max`` proxies) or gathers it
(kernels/warp/working_set.py), runs the tick's steps (kernels/warp/steps.py) and writes its
results. ``proxy_resident`` is its resident form (CUDA only; the protocol in
kernels/warp/resident_protocol.py, the host's driver in kernels/warp/resident.py): the blocks
stay on their SMs and run a tick each time the host posts one. The working-set capacity, the
register cap and the block size are constants of a kernel's code: ``tick_kernel`` makes and
keeps one pair of kernels per triple.
"""
from __future__ import annotations

import warp as wp

from .args import ProxyArgs, TickArgs
from .frames import GridArgs
from .points import results_out, set_holds
from .primitives import bits_float, block_sync, float_bits, shared4, sharedi4
from .resident_protocol import (IN_HEAD, MB_ALIVE, bits_vec3, command_put, command_wait, mailbox_set,
                                positions_in, staged4, tick_done, tick_in)
from .steps import make_run_steps
from .tick_inputs import stage_inputs, staged3, staged_tick, tick_end
from .working_set import make_working_set

_KERNELS: dict = {}


def tick_kernel(cap: int, maxreg: int = 0, bd: int = 1, resident: bool = False):
    """The tick kernel with a shared working set of ``cap`` points, a register cap (0: none) and
    ``bd`` threads a block (1 on Warp's CPU device), made on first use; ``resident``: its
    resident form, CUDA only."""
    key = (cap, maxreg, bd)
    pair = _KERNELS.get(key) or _KERNELS.setdefault(key, _make_tick_kernels(cap, maxreg, bd))
    return pair[1] if resident else pair[0]


def _make_tick_kernels(cap: int, maxreg: int, bd: int):
    BD = bd
    wset = make_working_set(cap, bd)
    ws, WL, NJ = wset.ws, wset.wl, wset.nj
    run_steps = make_run_steps(bd, wset.gather, wset.ws_eval, wset.ws_clip, wset.ws_away)
    opts = {"cuda_max_registers": maxreg} if maxreg else {}

    @wp.kernel(enable_backward=False, module="unique", **opts)
    def proxy_tick(spts: wp.array(dtype=wp.vec4), order: wp.array(dtype=int), start: wp.array(dtype=int),
                   g: GridArgs, a: ProxyArgs, pos: wp.array(dtype=wp.vec3), hips: wp.array(dtype=wp.vec3), bd: int,
                   svel: wp.array(dtype=wp.vec4), tick: wp.array(dtype=TickArgs), nrm_out: wp.array(dtype=wp.vec3),
                   near_out: wp.array(dtype=float), state_out: wp.array(dtype=wp.int32),
                   steps_out: wp.array(dtype=wp.int32), conv_out: wp.array(dtype=wp.bool), caching: int,
                   wsc: wp.array(dtype=wp.vec4), wsk: wp.array(dtype=wp.vec4), wsi: wp.array(dtype=wp.vec4i),
                   staged: int, n: int, kmax: int, tick4: wp.array(dtype=wp.vec4i), dpos: wp.array(dtype=wp.vec3),
                   dhips: wp.array(dtype=wp.vec3), dtick: wp.array(dtype=wp.vec4i), sync: wp.array(dtype=wp.int32)):
        """One tick of proxy p (a block of ``bd`` threads) of ``n``. ``caching``: whether the working
        sets persist from tick to tick in ``wsc`` (``cap`` points a proxy), with each proxy's
        (X0 m, skin m) in ``wsk`` and (build, dt bits, span, points or -1) in ``wsi``. ``staged``
        (CUDA, the zero-copy path): the inputs in host memory (``pos``, ``hips``, ``tick``, and
        ``tick4``: the same as four words) are copied by the first blocks into ``dpos``, ``dhips``
        and ``dtick`` and read from there (kernels/warp/tick_inputs.py; ``sync``: its words; ``kmax``:
        the most bodies that copy, the device's SM count)."""
        p, lane = wp.tid()
        if staged != 0:
            stage_inputs(pos, hips, tick4, dpos, dhips, dtick, sync, n, kmax, lane, BD)
        # one thread reads the proxy's inputs and shares them with the block
        if lane == 0:
            # the tick's arguments as four words (dt bits, span, grad bits, build), the position, the HIP
            tw = wp.vec4i(0)
            x = wp.vec3(0.0)
            hh = wp.vec3(0.0)
            if staged != 0:
                tw = staged_tick(dtick)
                x = staged3(dpos, p)
                hh = staged3(dhips, p)
            else:
                tk = tick[0]
                tw = wp.vec4i(float_bits(tk.dt), tk.span, float_bits(tk.grad), tk.build)
                x = pos[p]
                hh = hips[p]
            shared4(1, 0, wp.vec4(x[0], x[1], x[2], 0.0))
            shared4(1, 1, wp.vec4(hh[0], hh[1], hh[2], 0.0))
            shared4(1, 2, wp.vec4(bits_float(tw[0]), float(tw[1]), bits_float(tw[2]), 0.0))
            sharedi4(1, 0, wp.vec4i(tw[3], 0, 0, 0))
        block_sync()
        xv = shared4(0, 0, wp.vec4(0.0))
        hv = shared4(0, 1, wp.vec4(0.0))
        tv = shared4(0, 2, wp.vec4(0.0))
        X = wp.vec3(xv[0], xv[1], xv[2])
        H = wp.vec3(hv[0], hv[1], hv[2])
        dt = tv[0]
        span = int(tv[1])
        grad = tv[2]
        build = sharedi4(0, 0, wp.vec4i(0))[0]
        dtb = float_bits(dt)
        wbase = (lane // WL) * NJ
        # the working set of the proxy's last tick, from the cache in device memory, where it
        # still holds; else gathered anew
        X0 = X
        n_ws = int(-2)
        skin = a.skin
        par = int(0)
        hit = int(0)
        if caching != 0:
            ci = wsi[p]
            ck = wsk[p]
            if set_holds(ci, wp.vec3(ck[0], ck[1], ck[2]), ck[3], build, dtb, span, X):
                hit = 1
                X0 = wp.vec3(ck[0], ck[1], ck[2])
                skin = ck[3]
                n_ws = ci[3]
                for k in range(lane, n_ws, BD):
                    ws(1, k, wsc[p * cap + k])
                wset.pad(n_ws, lane)
                block_sync()
        # (where n_ws is still -2, run_steps gathers the set around X0 = X first)
        Xs = X0
        X, nrm, min_e, st, steps, conv, X0, n_ws, par, skin = run_steps(
            spts, svel, dt, order, start, g, a, X, H, span, grad, lane, wbase, X0, n_ws, par, skin)
        # (run_steps gathers again only at a position further than the skin from Xs)
        if caching != 0 and (hit == 0 or X0[0] != Xs[0] or X0[1] != Xs[1] or X0[2] != Xs[2]):
            for k in range(lane, n_ws, BD):
                wsc[p * cap + k] = ws(0, k, wp.vec4(0.0))
            if lane == 0:
                wsi[p] = wp.vec4i(build, dtb, span, n_ws)
                wsk[p] = wp.vec4(X0[0], X0[1], X0[2], skin)
        if lane == 0:
            results_out(p, X, nrm, min_e, st, steps, conv, pos, nrm_out, near_out, state_out, steps_out, conv_out)
            if staged != 0:
                tick_end(sync, n)

    @wp.kernel(enable_backward=False, module="unique", **opts)
    def proxy_resident(spts: wp.array(dtype=wp.vec4), order: wp.array(dtype=int), start: wp.array(dtype=int),
                       svel: wp.array(dtype=wp.vec4), g: GridArgs, a: ProxyArgs, inbox: wp.array(dtype=wp.int32),
                       mb: wp.array(dtype=wp.int32), cmd: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                       n: int, last0: int, idle_ns: int, pos: wp.array(dtype=wp.vec3),
                       nrm_out: wp.array(dtype=wp.vec3), near_out: wp.array(dtype=float),
                       state_out: wp.array(dtype=wp.int32), steps_out: wp.array(dtype=wp.int32),
                       conv_out: wp.array(dtype=wp.bool), stage: wp.array(dtype=wp.vec4i)):
        """The resident form of ``proxy_tick`` on one snapshot slot (kernels/warp/resident.py):
        the blocks stay on their SMs and run a tick each time the host posts one in the inbox; a
        proxy's working set stays in shared memory from tick to tick while it holds, and its
        position in a register while the kernel ran the batch's previous tick (tick numbers are
        consecutive then; after another kernel's tick or a reset block 0 stages the positions from
        the host). Host memory is read by block 0 alone (reads from many blocks at once queue on
        the bus): it passes the tick on to the others through device memory. Each block writes
        its results into the host arrays; the last to finish writes the tick's number into the
        mailbox. The slot's arrays are kernel parameters and the tick-to-tick bookkeeping lives in
        shared memory, so that the step loop has the registers of ``proxy_tick``'s."""
        p, lane = wp.tid()
        wbase = (lane // WL) * NJ
        par = int(0)
        X = wp.vec3(0.0)
        X0 = wp.vec3(0.0)
        n_ws = int(-2)      # no working set yet
        skin = float(0.0)
        if lane == 0:
            # (build, dt bits, span) the set was gathered for, and the last tick number seen;
            # the last tick this kernel ran (none yet)
            sharedi4(1, 2, wp.vec4i(-1, -1, -1, last0))
            sharedi4(1, 1, wp.vec4i(-1, 0, 0, 0))
        block_sync()
        while True:
            s = int(0)
            last = sharedi4(0, 2, wp.vec4i(0))[3]
            ran = sharedi4(0, 1, wp.vec4i(0))[0]
            if p == 0:   # block 0 alone polls the host and passes the tick on; the others follow
                if lane < 32:
                    tick_in(1, 0, inbox, mb, stage, n, last, idle_ns, lane)
                block_sync()
                s = tick_in(0, 0, inbox, mb, stage, n, last, idle_ns, lane)[0]
                if s > 0 and s != ran + 1:
                    positions_in(pos, stage, n, lane, BD)
                    block_sync()
                if n > 1 and lane == 0:
                    command_put(cmd, s)
            else:
                if lane == 0:
                    sharedi4(1, 0, wp.vec4i(command_wait(cmd, last), 0, 0, 0))
                block_sync()
                s = sharedi4(0, 0, wp.vec4i(0))[0]
            if s <= 0:
                break
            hd = wp.vec4i(0)
            hg = wp.vec4i(0)
            hh = wp.vec4i(0)
            if p == 0:
                hd = tick_in(0, 0, inbox, mb, stage, n, last, idle_ns, lane)
                hg = tick_in(0, 1, inbox, mb, stage, n, last, idle_ns, lane)
                hh = tick_in(0, 2, inbox, mb, stage, n, last, idle_ns, lane)
            else:
                hd = staged4(stage, 0)
                hg = staged4(stage, 1)
                hh = staged4(stage, IN_HEAD + p)
            if s != ran + 1:
                X = bits_vec3(staged4(stage, IN_HEAD + n + p))
            build = hd[1]
            dtb = hd[2]
            span = hd[3]
            dt = bits_float(dtb)
            grad = bits_float(hg[1])
            H = bits_vec3(hh)
            fresh = n_ws == -2 or not set_holds(sharedi4(0, 2, wp.vec4i(0)), X0, skin, build, dtb, span, X)
            block_sync()   # every thread has read the bookkeeping before lane 0 updates it
            if lane == 0:
                sharedi4(1, 2, wp.vec4i(build, dtb, span, s))
                sharedi4(1, 1, wp.vec4i(s, 0, 0, 0))
            # (block 0 takes the next tick only after the host has seen this one done, and a
            # block counts itself done after reductions that every one of its threads reached
            # with its inputs read)
            if fresh:   # run_steps gathers the set around X first
                n_ws = -2
            X, nrm, min_e, st, steps, conv, X0, n_ws, par, skin = run_steps(
                spts, svel, dt, order, start, g, a, X, H, span, grad, lane, wbase, X0, n_ws, par, skin)
            if lane == 0:
                results_out(p, X, nrm, min_e, st, steps, conv, pos, nrm_out, near_out, state_out, steps_out, conv_out)
                tick_done(count, mb, n, s)
        if p == 0 and lane == 0:
            mailbox_set(mb, MB_ALIVE, 0)

    return proxy_tick, proxy_resident
