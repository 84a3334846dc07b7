"""The Warp proxy kernel (one block per proxy, block reductions) against the NumPy reference."""
import numpy as np
import pytest

wp = pytest.importorskip("warp", reason="warp-lang is not installed: pip install 'pointfence[warp]'")

from pointfence.kernels import get_backend
from pointfence.kernels.haptics import CONTACT, ENTRENCHED, FREE, HapticParams
from pointfence.kernels.reference.proxy import NumpyProxies

from kernel_cases import params_for, random_rig


def brute_normals(snap, X, p):
    """Eq. 2.1 over every point with clearance below r3 - r1 (float64, all points)."""
    pts = snap.points.astype(np.float64)
    if p.mode == "fixture":
        keep = snap.protected != 0
        pts, rho = pts[keep], pts[keep, 3]
    else:
        rho = np.full(len(pts), p.r1)
    out = np.zeros_like(X, dtype=np.float64)
    for i, x in enumerate(X.astype(np.float64)):
        d = x - pts[:, :3]
        n = np.linalg.norm(d, axis=1)
        sel = (n - rho < p.r3 - p.r1) & (n > 0)
        s = (d[sel] / n[sel, None]).sum(axis=0)
        out[i] = s / np.linalg.norm(s) if np.linalg.norm(s) > 0 else 0
    return out


PATHS = ["working-set", "launched", "hash", "copies", "params-skin", "skin-fallback"]


@pytest.fixture(params=PATHS)
def kernel_path(request):
    """Which way the kernel runs, and the ``WarpTuning`` that makes it: working sets in shared
    memory (the default; on CUDA a batch this small runs on the resident kernel), on CUDA the
    same launched each tick as a graph ("launched"), the hash scanned from global memory
    (working sets that do not fit: capacity 16 points), on CUDA the graph with copies instead
    of zero-copy host memory (large batches), working sets gathered with HapticParams.skin
    instead of the wider GPU skin, and sets too large with a 10 mm skin for a 24-point buffer
    (most of this sparse rig's), gathered again with HapticParams.skin."""
    from pointfence.kernels.warp.tuning import ANY, WarpTuning

    tuning = {
        "working-set": WarpTuning(),
        "hash": WarpTuning(ws_caps=((ANY, 16),)),
        "params-skin": WarpTuning(gather_skin=0.0),
        "skin-fallback": WarpTuning(gather_skin=0.01, ws_caps=((ANY, 24),)),
        "copies": WarpTuning(zero_copy_max=0, resident_max=0),
        "launched": WarpTuning(resident_max=0),
    }[request.param]
    if request.param == "copies" and not get_backend("warp").device.is_cuda:
        pytest.skip("the copying path exists on CUDA only")
    if request.param == "launched" and not get_backend("warp").device.is_cuda:
        pytest.skip("the resident kernel exists on CUDA only: every tick is launched on the CPU device")
    return request.param, tuning


@pytest.mark.parametrize("mode", ["rendering", "fixture"])
def test_warp_proxies_agree_with_reference(mode, kernel_path):
    """Same snapshot, same HIPs, one tick at a time from the same positions: positions within
    1e-5 m. The block reduction sums in another order than the reference, and the algorithm is
    discontinuous (a point entering the normal band turns the normal), so two long trajectories
    may part; each tick therefore starts the reference from the Warp proxies' positions."""
    kernel_path, tuning = kernel_path
    rng = np.random.default_rng(17 if mode == "rendering" else 23)
    cams, frames = random_rig(rng, n_cams=2)
    pipe = get_backend("warp").pipeline(cams, params_for("mask", adaptive=True, cell=0.02))
    pipe.ingest(frames)
    snap = pipe.host_snapshot()
    p = HapticParams(mode=mode, max_steps=40)
    B = 16
    surf = snap.points[rng.integers(0, snap.n_points, B), :3].astype(np.float64)
    start = surf + rng.normal(0, 0.01, (B, 3)) + [0, 0, -0.015]
    dev = pipe.proxies(start, p, tuning=tuning)
    if kernel_path == "copies":
        assert not dev.zero_copy()
    assert dev.resident() == (kernel_path in ("working-set", "hash", "params-skin", "skin-fallback")
                              and pipe.device.is_cuda)
    ref = NumpyProxies(pipe, start, p, snapshot=snap)
    h = start.copy()
    states = np.zeros(3, int)
    parted = 0
    for _ in range(40):
        h = h + rng.normal(0, 0.0015, h.shape) + [0, 0, 0.0008]
        same = _tick_pair(dev, ref, h, 1e-5)
        # Clearances near the clipping limit are decided with a margin (kernels/proxy.py), but a
        # step may still end within rounding of a state threshold (e = 0) by chance; then the
        # two may part within a tick (about one proxy-tick in 10^4).
        parted += np.count_nonzero(~same)
        np.testing.assert_allclose(dev.nearest[same], ref.nearest[same], atol=1e-5, rtol=0)
        # The normal is discontinuous in the position (a point entering the R3 band adds 1/N), so
        # check it against eq. 2.1 evaluated by brute force at the Warp proxy's own position.
        np.testing.assert_allclose(dev.normals, brute_normals(snap, dev.positions, p), atol=2e-4, rtol=0)
        states += np.bincount(dev.states, minlength=3)
    assert parted <= 0.01 * 40 * B
    assert states[CONTACT] + states[ENTRENCHED] > 30 and states[FREE] > 30


def test_warp_empty_snapshot_is_free_motion():
    rng = np.random.default_rng(1)
    cams, frames = random_rig(rng, n_cams=1)
    pipe = get_backend("warp").pipeline(cams, params_for("all"))
    prox = pipe.proxies(np.zeros((3, 3)) + [0, 0, 0.8], HapticParams(max_steps=20))
    prox.step(np.zeros((3, 3)) + [0, 0.005, 0.8])
    np.testing.assert_allclose(prox.positions[:, 1], 0.005, atol=1e-6)
    assert np.all(prox.states == FREE) and np.all(prox.converged) and np.all(np.isinf(prox.nearest))


def _rig(rng, B):
    """A 2-camera random rig's pipeline (all points protected, 2 cm cells) with one snapshot, and
    B proxy starts near its surface points: (pipe, frames, snap, surface points, starts)."""
    cams, frames = random_rig(rng, n_cams=2)
    pipe = get_backend("warp").pipeline(cams, params_for("all", cell=0.02))
    pipe.ingest(frames)
    snap = pipe.host_snapshot()
    surf = snap.points[rng.integers(0, snap.n_points, B), :3].astype(np.float64)
    return pipe, frames, snap, surf, surf + rng.normal(0, 0.01, (B, 3)) + [0, 0, -0.015]


def _cuda_pipe_and_batch(rng, B=8, **batch_options):
    if not get_backend("warp").device.is_cuda:
        pytest.skip("the resident kernel exists on CUDA only")
    pipe, frames, snap, surf, start = _rig(rng, B)
    p = HapticParams(max_steps=40)
    return pipe, frames, snap, start, p, pipe.proxies(start, p, **batch_options)


def _tick_pair(dev, other, h, tol):
    """One tick of ``dev`` and of ``other`` from dev's positions towards the HIPs ``h``: the
    proxies that end within ``tol`` m of each other, whose states must then agree."""
    other.reset(dev.positions.copy())
    dev.step(h)
    other.step(h)
    same = np.abs(dev.positions - other.positions).max(axis=1) <= tol
    np.testing.assert_array_equal(dev.states[same], other.states[same])
    return same


def _agree(dev, ref, h):
    same = _tick_pair(dev, ref, h, 1e-5)
    assert same.mean() >= 0.8, (dev.positions, ref.positions)


def test_resident_kernel_leaves_when_idle_stopped_or_resized_and_comes_back():
    """The resident kernels (CUDA, one per snapshot slot): ticks agree with the reference; after
    IDLE_S without a tick a kernel has left and the next tick launches it again; close() stops
    it, the batch still steps; a batch resized (reset with another B) gets a new one; a new
    snapshot (the other slot, then the first rebuilt) is used at once."""
    import time

    from pointfence.kernels.warp import resident
    from pointfence.kernels.warp.resident_protocol import MB_ALIVE

    rng = np.random.default_rng(5)
    pipe, frames, snap, start, p, dev = _cuda_pipe_and_batch(rng)
    assert dev.resident()
    ref = NumpyProxies(pipe, start, p, snapshot=snap)
    h = start.copy()
    for _ in range(10):
        h = h + rng.normal(0, 0.0015, h.shape) + [0, 0, 0.0008]
        _agree(dev, ref, h)
    r = dev._resident[pipe.buffers.front_index]   # one resident kernel per snapshot slot
    assert r.launches == 1 and r.running
    time.sleep(3 * resident.IDLE_S)
    assert r.mb_np[MB_ALIVE] == 0   # left by itself
    _agree(dev, ref, h + 0.001)
    assert r.launches == 2
    dev.close()
    assert r.mb_np[MB_ALIVE] == 0 and not r.running
    _agree(dev, ref, h)
    assert r.launches == 3
    # another batch size: another kernel (the old one stopped)
    dev.reset(start[:3])
    ref = NumpyProxies(pipe, start[:3], p, snapshot=snap)
    _agree(dev, ref, h[:3])
    r3 = dev._resident[pipe.buffers.front_index]
    assert r3 is not r and r.mb_np[MB_ALIVE] == 0 and r3.n == 3
    # a new snapshot (the other slot, then the first again): the working sets are gathered again
    for k in range(2):
        shifted = [type(f)(**{**f.__dict__, "depth": (f.depth.astype(np.int32) - 40 * (k + 1)).clip(0).astype(f.depth.dtype)})
                   for f in frames]
        pipe.ingest(shifted)
        snap2 = pipe.host_snapshot()
        ref = NumpyProxies(pipe, start[:3], p, snapshot=snap2)
        _agree(dev, ref, h[:3])
        assert dev._resident[pipe.buffers.front_index].slot is pipe.buffers.slots[pipe.buffers.front_index]
    assert all(r is not None and r.running for r in dev._resident)   # both slots' kernels ran
    dev.close()
    assert not any(r.running for r in dev._resident)


def test_resident_ticks_take_reset_positions_for_one_and_several_proxies():
    """A resident kernel keeps each proxy's position on the GPU between its own consecutive ticks
    and takes the batch's positions after a reset (one proxy: block 0 alone; several: staged
    for the other blocks): every tick after a reset starts where the reset put the proxies."""
    rng = np.random.default_rng(13)
    for B in (1, 5):
        pipe, frames, snap, start, p, dev = _cuda_pipe_and_batch(rng, B=B)
        assert dev.resident()
        ref = NumpyProxies(pipe, start, p, snapshot=snap)
        h = start.copy()
        for k in range(12):
            h = h + rng.normal(0, 0.0015, h.shape) + [0, 0, 0.0008]
            if k % 4 == 3:   # somewhere else; the reference starts the next tick from there too
                dev.reset(start + rng.normal(0, 0.004, start.shape))
            _agree(dev, ref, h)
        dev.close()


def test_resident_ticks_only_where_the_host_keeps_store_order(monkeypatch):
    """The inbox's tags rely on x86's store order: on another host (an Arm CPU such as Grace)
    no batch ticks resident, and a small CUDA batch ticks on the launched kernel instead."""
    from pointfence.kernels.warp import resident
    from pointfence.kernels.warp.tuning import WarpTuning

    tuning = WarpTuning(resident_max=7)
    monkeypatch.setattr(resident, "HOST_STORE_ORDER", True)
    assert resident.resident_max(tuning) == 7
    monkeypatch.setattr(resident, "HOST_STORE_ORDER", False)
    assert resident.resident_max(tuning) == 0
    if get_backend("warp").device.is_cuda:
        rng = np.random.default_rng(3)
        pipe, frames, snap, surf, start = _rig(rng, 4)
        p = HapticParams(max_steps=40)
        dev = pipe.proxies(start, p)
        assert not dev.resident() and dev._resident == [None, None]
        _agree(dev, NumpyProxies(pipe, start, p, snapshot=snap), start + [0, 0, 0.004])


def test_resident_tick_that_times_out_raises_kernel_error_and_recovers(monkeypatch):
    """A resident tick not done within TIMEOUT_S raises KernelError (the service holds the
    robot); the kernel is stopped after that tick, and the next tick runs normally again."""
    from pointfence.kernels.errors import KernelError
    from pointfence.kernels.warp import resident

    rng = np.random.default_rng(9)
    pipe, frames, snap, start, p, dev = _cuda_pipe_and_batch(rng, B=4)
    h = start + [0, 0, 0.004]
    dev.step(h)
    monkeypatch.setattr(resident, "TIMEOUT_S", 1e-9)
    with pytest.raises(KernelError, match="did not finish tick"):
        dev.step(h)
    monkeypatch.setattr(resident, "TIMEOUT_S", 0.25)
    ref = NumpyProxies(pipe, start, p, snapshot=snap)
    _agree(dev, ref, h + 0.001)
    dev.close()


def test_resident_mailbox_and_inbox_layout_matches_the_native_code():
    """The resident kernel's native code uses the mailbox's word numbers (STOP, DONE) and the
    inbox's header size as literals, and polls at most two inbox chunks a lane of one warp: the
    layout must stay this."""
    from pointfence.kernels.warp import resident_protocol as rp
    from pointfence.kernels.warp.tuning import WarpTuning

    assert (rp.MB_STOP, rp.MB_DONE, rp.MB_ALIVE) == (0, 1, 2) and rp.MB_WORDS >= 3
    assert rp.IN_HEAD == 2 and rp.IN_HEAD + rp.RESIDENT_CAP <= 64
    assert 0 <= WarpTuning().resident_max <= rp.RESIDENT_CAP


def test_launched_working_set_cache_moves_proxies_exactly_as_gathering_every_tick():
    """The launched tick keeps each proxy's working set in device memory from tick to tick
    (WS_CACHE_MAX). Each tick, from the same positions, a cached batch moves its proxies as one
    that gathers every tick, through sliding (sets kept, and gathered again past the skin), a
    position reset far away and a new snapshot (sets gathered again); every proxy's cache key
    names the snapshot it last ran on. A kept set, gathered around an older position, holds
    more points in another order, so sums may differ in the last bits."""
    from pointfence.kernels.warp.tuning import WarpTuning

    tuning = WarpTuning(resident_max=0)   # on CUDA too: the launched path
    rng = np.random.default_rng(31)
    B = 12
    pipe, frames, snap, surf, start = _rig(rng, B)
    p = HapticParams(max_steps=40)
    cached = pipe.proxies(start, p, tuning=tuning)
    fresh = pipe.proxies(start, p, ws_cache=False, tuning=tuning)
    cap = tuning.ws_capacity_for(B)

    parted = 0

    def tick(h):
        nonlocal parted
        # (a sum a bit off may still flip a decision, as against the reference)
        same = _tick_pair(cached, fresh, h, 1e-6)
        parted += np.count_nonzero(~same)
        # (the normal turns about 200/m with the position: against eq. 2.1 where each proxy is)
        np.testing.assert_allclose(cached.normals, brute_normals(snap, cached.positions, p), atol=2e-4, rtol=0)

    h = start.copy()
    for _ in range(30):
        h = h + rng.normal(0, 0.0005, h.shape) + [0, 0, 0.0008]
        tick(h)
    keys = cached._ws_cache[cap][3].numpy()[:B]
    assert np.all(keys[:, 0] == pipe.buffers.slots[pipe.buffers.front_index].seq) and np.all(keys[:, 3] >= 0)
    assert "off" not in cached._ws_cache and cap not in fresh._ws_cache
    # each proxy set 4 mm from another one's surface point, entrenched: the kept sets no longer hold
    jump = np.roll(surf, 1, axis=0) + [0.0, 0.0, -0.004]
    assert np.all(np.linalg.norm(jump - cached.positions, axis=1) > 0.003)
    cached.reset(jump)
    fresh.reset(jump)
    for _ in range(5):
        h = jump + rng.normal(0, 0.002, h.shape) + [0, 0, 0.004]
        tick(h)
    # a new snapshot: every set is gathered again on it
    shifted = [type(f)(**{**f.__dict__, "depth": (f.depth.astype(np.int32) - 60).clip(0).astype(f.depth.dtype)})
               for f in frames]
    pipe.ingest(shifted)
    snap = pipe.host_snapshot()
    for _ in range(5):
        h = h + rng.normal(0, 0.0005, h.shape)
        tick(h)
    keys = cached._ws_cache[cap][3].numpy()[:B]
    assert np.all(keys[:, 0] == pipe.buffers.slots[pipe.buffers.front_index].seq)
    assert parted <= 0.02 * 40 * B
    ref = NumpyProxies(pipe, cached.positions.copy(), p, snapshot=pipe.host_snapshot())
    _agree(cached, ref, h + 0.001)
