"""`pointfence bench floor`: the launch + copy floor of a device, the least a tick can cost.

Measured the way a proxy tick runs: a small upload (one HIP), one kernel launch, a small
download (one result) and the wait for it, as plain calls and (Warp on CUDA) as one replayed
CUDA graph; and (Warp on CUDA) a graph holding the kernel alone, which reads its input from and
writes its result to pinned host memory (``graph_zero_copy``: how a Warp proxy tick of up to
``ZERO_COPY_MAX`` proxies runs); and (Warp on CUDA) the resident tick's hand-over alone
(``resident_round_trip``: a resident kernel of one block takes a HIP from the inbox and writes
it back with the proxy kernel's own functions, kernels/warp/resident.py, no step in between).
Other figures are reported as distance from this floor.
"""
from __future__ import annotations

import time

import numpy as np

from pointfence.kernels import get_backend

from .stats import pct


def add_arguments(p):
    pass


def _time_us(fn, n):
    for _ in range(50):
        fn()
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t0) * 1e6)
    return ts


def _warp(backend, n):
    import warp as wp

    @wp.kernel
    def touch(a: wp.array(dtype=wp.vec3), b: wp.array(dtype=wp.vec3)):
        i = wp.tid()
        b[i] = a[i]

    dev = backend.device
    pinned = dev.is_cuda
    h_in = wp.zeros(1, dtype=wp.vec3, device="cpu", pinned=pinned)
    h_out = wp.zeros(1, dtype=wp.vec3, device="cpu", pinned=pinned)
    d_in = wp.zeros(1, dtype=wp.vec3, device=dev)
    d_out = wp.zeros(1, dtype=wp.vec3, device=dev)
    stream = wp.Stream(dev) if dev.is_cuda else None

    def record():
        wp.copy(d_in, h_in)
        wp.launch(touch, dim=1, inputs=[d_in, d_out], device=dev)
        wp.copy(h_out, d_out)

    def plain():
        record()
        wp.synchronize_device(dev)

    out = {"launch_copy_us_p50": None}
    t = _time_us(plain, n)
    out.update(launch_copy_us_p50=round(pct(t, 50), 2), launch_copy_us_p99=round(pct(t, 99), 2))
    if dev.is_cuda:
        def graph_us(record_fn):
            """(p50, p99) us of replaying a graph of ``record_fn`` and waiting for it."""
            with wp.ScopedStream(stream):
                wp.capture_begin(device=dev, stream=stream)
                record_fn()
                graph = wp.capture_end(device=dev, stream=stream)

            def replay():
                wp.capture_launch(graph, stream=stream)
                wp.synchronize_stream(stream)

            t = _time_us(replay, n)
            return round(pct(t, 50), 2), round(pct(t, 99), 2)

        out["graph_us_p50"], out["graph_us_p99"] = graph_us(record)
        # zero-copy: device views of the pinned host arrays, the graph is the kernel alone
        v_in = wp.array(ptr=h_in.ptr, dtype=wp.vec3, shape=1, device=dev)
        v_out = wp.array(ptr=h_out.ptr, dtype=wp.vec3, shape=1, device=dev)
        out["graph_zero_copy_us_p50"], out["graph_zero_copy_us_p99"] = graph_us(
            lambda: wp.launch(touch, dim=1, inputs=[v_in, v_out], device=dev))
        out["resident_round_trip_us_p50"], out["resident_round_trip_us_p99"] = _resident_round_trip(dev, n)
    return out


def _resident_round_trip(dev, n):
    """(p50, p99) us of a resident tick with no step: the host posts one HIP in the inbox and
    spins until the kernel has written it back and marked the tick done."""
    import warp as wp

    from pointfence.kernels.warp.primitives import block_sync
    from pointfence.kernels.warp.resident_protocol import (IN_HEAD, MB_ALIVE, MB_DONE, MB_STOP, MB_WORDS, Inbox,
                                                           bits_vec3, mailbox_set, pinned_words, tick_done, tick_in)
    from pointfence.kernels.warp.tuning import WarpTuning

    @wp.kernel(enable_backward=False)
    def relay(inbox: wp.array(dtype=wp.int32), mb: wp.array(dtype=wp.int32), stage: wp.array(dtype=wp.vec4i),
              count: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.vec3), idle_ns: int):
        p, lane = wp.tid()
        last = int(0)
        while True:
            if lane < 32:
                tick_in(1, 0, inbox, mb, stage, 1, last, idle_ns, lane)
            block_sync()
            s = tick_in(0, 0, inbox, mb, stage, 1, last, idle_ns, lane)[0]
            if s <= 0:
                break
            h = tick_in(0, 2, inbox, mb, stage, 1, last, idle_ns, lane)
            if lane == 0:
                out[0] = bits_vec3(h)
                tick_done(count, mb, 1, s)
            last = s
            block_sync()   # (every thread has read the tick before warp 0 takes the next)
        if lane == 0:
            mailbox_set(mb, MB_ALIVE, 0)

    inbox = Inbox(1, dev)
    mb, mbn, mb_dev = pinned_words(MB_WORDS, dev)
    res = wp.zeros(1, dtype=wp.vec3, device="cpu", pinned=True)
    resn = res.numpy()
    mbn[MB_ALIVE] = 1
    stream = wp.Stream(dev)
    wp.launch_tiled(relay, dim=[1], block_dim=WarpTuning().block_dim_for(1), device=dev, stream=stream,
                    inputs=[inbox.dev, mb_dev, wp.zeros(IN_HEAD + 2, dtype=wp.vec4i, device=dev),
                            wp.zeros(1, dtype=wp.int32, device=dev),
                            wp.array(ptr=res.ptr, dtype=wp.vec3, shape=1, device=dev), int(1e9)])
    seq = [0]
    h = np.array([[0.1, 0.2, 0.3]], np.float32)

    def tick():
        s = seq[0] = seq[0] + 1
        h[0, 0] = s
        inbox.post(h, s)
        t_end = time.perf_counter() + 1.0
        while mbn[MB_DONE] != s:
            if time.perf_counter() > t_end:
                raise RuntimeError(f"the resident round-trip kernel did not answer tick {s} within 1 s on {dev}")
        if resn[0, 0] != s:
            raise RuntimeError(f"the resident round-trip kernel wrote back {resn[0].tolist()} for tick {s}")

    try:
        t = _time_us(tick, n)
    finally:
        mbn[MB_STOP] = 1
        wp.synchronize_stream(stream)
    return round(pct(t, 50), 2), round(pct(t, 99), 2)


def _opencl(backend, n):
    import pyopencl as cl

    ctx = backend.context
    q = cl.CommandQueue(ctx)
    prg = cl.Program(ctx, "__kernel void touch(__global const float4 *a, __global float4 *b) { b[0] = a[0]; }").build()
    k = cl.Kernel(prg, "touch")
    h_in = np.zeros(4, np.float32)
    h_out = np.zeros(4, np.float32)
    mf = cl.mem_flags
    d_in = cl.Buffer(ctx, mf.READ_ONLY, 16)
    d_out = cl.Buffer(ctx, mf.WRITE_ONLY, 16)
    k.set_args(d_in, d_out)

    def plain():
        cl.enqueue_copy(q, d_in, h_in, is_blocking=False)
        cl.enqueue_nd_range_kernel(q, k, (1,), None)
        cl.enqueue_copy(q, h_out, d_out, is_blocking=True)

    t = _time_us(plain, n)
    return {"launch_copy_us_p50": round(pct(t, 50), 2), "launch_copy_us_p99": round(pct(t, 99), 2)}


def run(args) -> dict:
    n = args.repeat or 5000
    backend = get_backend(args.backend, args.device)
    out = {"backend": backend.name, "device": backend.device_name, "repeat": n}
    if backend.name == "warp":
        out.update(_warp(backend, n))
    elif backend.name == "opencl":
        out.update(_opencl(backend, n))
    else:
        out["note"] = "the numpy backend launches nothing: its floor is zero"
    return out
