"""PoCL's in-thread device for the haptic tick (kernels/opencl/context.inline_device): it exists
by default, shares the snapshot's host memory with the build pool, gives the pool's results to
the bit, and a batch moves between the two as it grows and shrinks without losing its state."""
import os

import numpy as np
import pytest

from pointfence.kernels import get_backend
from pointfence.kernels.haptics import HapticParams
from pointfence.kernels.opencl import proxy as ocl_proxy
from pointfence.kernels.opencl.context import lower_pool_priority, pool_threads

from kernel_cases import params_for, random_rig


def _scene(seed=5):
    rng = np.random.default_rng(seed)
    cams, frames = random_rig(rng, n_cams=2)
    pipe = get_backend("opencl").pipeline(cams, params_for("mask", adaptive=False, cell=0.02))
    pipe.ingest(frames)
    snap = pipe.host_snapshot()
    surf = snap.points[rng.integers(0, snap.n_points, 12), :3].astype(np.float64)
    return rng, cams, frames, pipe, surf + [0, 0, -0.012]


def test_in_thread_device_is_used_and_matches_the_pool_to_the_bit():
    rng, _, frames, pipe, start = _scene()
    assert pipe.inline_ctx is not None, "PoCL's basic device should be enabled (POCL_DEVICES)"
    p = HapticParams(mode="rendering", max_steps=40)
    a = pipe.proxies(start[:4], p)
    b = pipe.proxies(start[:4], p, inline=False)
    assert (a.device_kind, b.device_kind) == ("in-thread", "pool")
    h = start[:4].copy()
    for k in range(40):
        h = h + rng.normal(0, 0.001, h.shape) + [0, 0, 0.0006]
        if k == 20:
            pipe.ingest(frames)      # a new snapshot in the other slot: both see it
        a.step(h)
        b.step(h)
        assert np.array_equal(a.positions, b.positions)
        assert np.array_equal(a.normals, b.normals)
        assert np.array_equal(a.states, b.states) and np.array_equal(a.steps, b.steps)
    assert (a.states != 0).any()


def test_batch_moves_between_devices_as_it_grows_and_keeps_its_proxies():
    _, _, _, pipe, start = _scene(6)
    p = HapticParams(mode="rendering")
    small = ocl_proxy.INLINE_MAX
    many = np.concatenate([start] * (small // len(start) + 2))[: small + 3]
    batch = pipe.proxies(many[:2], p)
    assert batch.device_kind == "in-thread"
    batch.reset(many)
    assert batch.device_kind == "pool" and len(batch) == small + 3
    ref = pipe.proxies(many, p, inline=False)
    batch.step(many)
    ref.step(many)
    assert np.array_equal(batch.positions, ref.positions)


def test_inline_can_be_turned_off():
    be = get_backend("opencl")
    from pointfence.kernels.opencl.backend import OpenCLBackend

    off = OpenCLBackend(inline=False)
    assert off.inline_context is None and be.inline_context is not None


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="per-thread priorities are a Linux feature")
def test_pool_priority_is_lowered_for_the_workers_only():
    get_backend("opencl")
    tids = pool_threads()
    assert tids, "PoCL's worker threads were not found"
    main = os.getpriority(os.PRIO_PROCESS, 0)
    try:
        changed = lower_pool_priority(10)
        assert changed and all(os.getpriority(os.PRIO_PROCESS, t) == 10 for t in changed)
        assert os.getpriority(os.PRIO_PROCESS, 0) == main     # the calling thread keeps its priority
    finally:
        for t in tids:   # raising it back needs privilege; leave it lowered where refused
            try:
                os.setpriority(os.PRIO_PROCESS, t, main)
            except OSError:
                pass


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="SCHED_IDLE is a Linux feature")
def test_pool_can_run_sched_idle_and_the_caller_keeps_its_policy():
    get_backend("opencl")
    tids = pool_threads()
    policy = os.sched_getscheduler(0)
    try:
        changed = lower_pool_priority(10, idle=True)
        assert changed and all(os.sched_getscheduler(t) == os.SCHED_IDLE for t in changed)
        assert os.sched_getscheduler(0) == policy
    finally:
        for t in tids:
            try:
                os.sched_setscheduler(t, os.SCHED_OTHER, os.sched_param(0))
            except OSError:
                pass
