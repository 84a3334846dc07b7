"""The Warp backend's GPU-shaped paths against the NumPy reference: the neighbour query (a block
a query, buffers kept from call to call) and the proxy tick's working-set passes.

They run on Warp's CPU device here (one thread a block) and on CUDA where there is one (the
device machine runs this file too); they skip where warp is not installed.
"""
import numpy as np
import pytest

wp = pytest.importorskip("warp", reason="warp-lang is not installed: pip install 'pointfence[warp]'")

from pointfence.kernels import get_backend  # noqa: E402
from pointfence.kernels.errors import InputError  # noqa: E402
from pointfence.kernels.reference.neighbors import neighbors as reference_neighbors  # noqa: E402
from pointfence.kernels.warp.tuning import WarpTuning  # noqa: E402

from kernel_cases import params_for, random_rig  # noqa: E402


def assert_same(nb, ref):
    """Every field equal to the reference's, bit for bit: the hits in scan order, the nearest
    (ties to the earlier point) and its float32 distance."""
    np.testing.assert_array_equal(nb.count, ref.count)
    np.testing.assert_array_equal(nb.index, ref.index)
    np.testing.assert_array_equal(nb.nearest, ref.nearest)
    np.testing.assert_array_equal(nb.nearest_dist, ref.nearest_dist)
    for a in (nb.count, nb.index, nb.nearest):
        assert a.dtype == np.int32
    assert nb.nearest_dist.dtype == np.float32


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(31)
    cams, frames = random_rig(rng, n_cams=2)
    pipe = get_backend("warp").pipeline(cams, params_for("mask", cell=0.02))
    pipe.ingest(frames)
    snap = pipe.host_snapshot()
    idx = rng.integers(0, snap.n_points, 48)
    q = (snap.points[idx, :3] + rng.normal(0, 0.006, (48, 3))).astype(np.float32)
    q[0] = snap.points[3, :3]          # exactly on a point
    q[1] = [5.0, 5.0, 5.0]             # far outside the grid
    q[2] = snap.points[idx[2], :3] + [0.0, 0.0, 0.021]   # one cell above a point
    return pipe, snap, q


@pytest.mark.parametrize("radius", [0.003, 0.01, 0.02, 0.045])   # below, at and above the 2 cm cells
@pytest.mark.parametrize("protected_only", [False, True])
def test_neighbors_equal_the_reference_bit_for_bit(scene, radius, protected_only):
    pipe, snap, q = scene
    nb = pipe.neighbors(q, radius, max_neighbors=5000, protected_only=protected_only)
    ref = reference_neighbors(snap, q, radius, 5000, protected_only)
    assert_same(nb, ref)
    assert ref.count.sum() > 0 and (radius < 0.01 or (ref.count > 0).sum() > 10)


def test_truncated_rows_hold_the_first_hits_in_scan_order(scene):
    """K below the counts: each row holds the first K hits of the reference's scan (a wrong
    rank across the warps or rows of a block shows up as another subset or order)."""
    pipe, snap, q = scene
    for K in (1, 7, 33, 300):
        nb = pipe.neighbors(q, 0.03, max_neighbors=K)
        ref = reference_neighbors(snap, q, 0.03, K)
        assert nb.truncated.any() or K == 300
        assert_same(nb, ref)


def test_buffers_are_reused_and_results_are_the_callers_own(scene):
    """Calls that grow and shrink B and K reuse the query buffers; a result stays as it was
    after later calls (they write the same buffers)."""
    pipe, snap, q = scene
    first = pipe.neighbors(q[:5], 0.01, max_neighbors=16)
    keep = [a.copy() for a in (first.count, first.index, first.nearest, first.nearest_dist)]
    for B, K in ((48, 4000), (3, 2), (48, 64), (1, 1), (20, 9000)):
        assert_same(pipe.neighbors(q[:B], 0.012, max_neighbors=K), reference_neighbors(snap, q[:B], 0.012, K))
    for a, b in zip((first.count, first.index, first.nearest, first.nearest_dist), keep):
        np.testing.assert_array_equal(a, b)
    again = pipe.neighbors(q[:5], 0.01, max_neighbors=16)
    assert_same(again, reference_neighbors(snap, q[:5], 0.01, 16))


def test_no_queries_give_empty_results(scene):
    pipe, snap, q = scene
    nb = pipe.neighbors(np.zeros((0, 3), np.float32), 0.01, max_neighbors=5)
    assert nb.count.shape == (0,) and nb.index.shape == (0, 5) and nb.nearest_dist.shape == (0,)


def test_bad_queries_raise_before_anything_runs(scene):
    pipe, snap, q = scene
    bad = q.copy()
    bad[4, 1] = np.nan
    with pytest.raises(InputError, match="query 4"):
        pipe.neighbors(bad, 0.01)
    with pytest.raises(InputError, match="radius"):
        pipe.neighbors(q, -0.01)
    # the buffers still serve the next call
    assert_same(pipe.neighbors(q, 0.01, max_neighbors=64), reference_neighbors(snap, q, 0.01, 64))


@pytest.mark.parametrize("value", [48, 0, 2048, True, 256.0])
def test_query_block_dim_is_checked(value):
    with pytest.raises(InputError, match="query_block_dim"):
        WarpTuning(query_block_dim=value)


@pytest.mark.parametrize("bd", [32, 128, 1024])
def test_every_query_block_size_gives_the_same_results(scene, bd):
    """(On CUDA: 1, 4 and 32 warps a query, so rows split into pieces of every size; on the
    CPU device the block is one thread whatever the tuning says.)"""
    pipe0, snap, q = scene
    backend = get_backend("warp")
    from pointfence.kernels.warp.backend import WarpBackend

    b = WarpBackend(backend.device.alias, tuning=WarpTuning(query_block_dim=bd))
    rng = np.random.default_rng(31)
    cams, frames = random_rig(rng, n_cams=2)
    pipe = b.pipeline(cams, params_for("mask", cell=0.02))
    pipe.ingest(frames)
    assert_same(pipe.neighbors(q, 0.02, max_neighbors=200), reference_neighbors(snap, q, 0.02, 200))


def _run_ticks(pipe, start, hips, p, tuning):
    batch = pipe.proxies(start, p, tuning=tuning)
    out = []
    for h in hips:
        batch.step(h)
        out.append((batch.positions.copy(), batch.states.copy(), batch.steps.copy(), batch.nearest.copy()))
    batch.close()
    return out


@pytest.mark.parametrize("mode", ["rendering", "fixture"])
def test_near_points_as_masks_or_lists_move_proxies_alike(mode):
    """The clip passes take the near points from a thread's bit mask (a working set of at most
    31 points a thread: every CUDA block, and here sets of up to 31 points) or from the warps'
    lists (the CPU device's larger sets): the same step lengths either way. On the CPU device,
    where both sum in one order, the trajectories agree bit for bit. (CUDA blocks always take the
    mask path; tests/test_warp_proxy.py checks it against the reference there.) The sparse rig
    keeps many sets under 31 points, so the mask path is taken."""
    from pointfence.kernels.haptics import HapticParams
    from pointfence.kernels.warp.tuning import ANY

    if get_backend("warp").device.is_cuda:
        pytest.skip("CUDA blocks always take the mask path: tests/test_warp_proxy.py checks it against the reference")
    rng = np.random.default_rng(41)
    cams, frames = random_rig(rng, n_cams=1, w=80, h=60)
    pipe = get_backend("warp").pipeline(cams, params_for("mask", adaptive=True, cell=0.02))
    pipe.ingest(frames)
    snap = pipe.host_snapshot()
    p = HapticParams(mode=mode, max_steps=40)
    B = 12
    surf = snap.points[rng.integers(0, snap.n_points, B), :3].astype(np.float64)
    start = surf + rng.normal(0, 0.004, (B, 3)) + [0, 0, -0.012]
    hips = start[None] + np.cumsum(rng.normal(0, 0.0015, (25, B, 3)) + [0, 0, 0.0009], axis=0)
    counts = pipe.neighbors(start, p.reach() + 0.0015, max_neighbors=1).count
    assert np.any((counts > 0) & (counts <= 31))
    masks = _run_ticks(pipe, start, hips, p, WarpTuning(ws_caps=((ANY, 31),), gather_skin=0.0015))
    lists = _run_ticks(pipe, start, hips, p, WarpTuning(ws_caps=((ANY, 4096),), gather_skin=0.0015))
    moved = 0
    for (xa, sa, na, ea), (xb, sb, nb, eb) in zip(masks, lists):
        np.testing.assert_array_equal(xa, xb)
        np.testing.assert_array_equal(sa, sb)
        np.testing.assert_array_equal(na, nb)
        np.testing.assert_array_equal(ea, eb)
        moved += int(na.sum())
    assert moved > 100


def test_queries_from_several_threads_each_get_their_own_results(scene):
    """The query buffers are shared by the pipeline's calls: callers on other threads wait for
    one another instead of reading each other's results."""
    import threading

    pipe, snap, q = scene
    cases = [(q[i::4], 0.004 + 0.004 * i, 50 + 100 * i) for i in range(4)]
    expect = [reference_neighbors(snap, qq, r, K) for qq, r, K in cases]
    errors = []

    def worker(j):
        try:
            for _ in range(15):
                qq, r, K = cases[j]
                assert_same(pipe.neighbors(qq, r, max_neighbors=K), expect[j])
        except Exception as e:  # collected: a failure on a thread would not fail the test
            errors.append(e)

    threads = [threading.Thread(target=worker, args=(j,)) for j in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors[0]


def test_each_snapshot_slots_query_follows_grown_buffers():
    """A query on one snapshot slot after the buffers grew for a query on the other slot reads
    the new buffers (each slot's launch is recorded once; a stale query buffer would give the
    earlier call's queries' results)."""
    rng = np.random.default_rng(8)
    cams, frames = random_rig(rng, n_cams=1)
    pipe = get_backend("warp").pipeline(cams, params_for("all"))
    for round_ in range(3):
        pipe.ingest(frames)   # the slots alternate
        snap = pipe.host_snapshot()
        B = (5, 150, 5)[round_]
        q = (snap.points[rng.integers(0, snap.n_points, B), :3] + rng.normal(0, 0.003, (B, 3))).astype(np.float32)
        K = (8, 1, 8)[round_]   # (the results fit the first buffer: only the queries grow)
        assert_same(pipe.neighbors(q, 0.01, max_neighbors=K), reference_neighbors(snap, q, 0.01, K))


def _cuda_rig(rng, n_cams):
    """(pipeline on CUDA, its snapshot) of a random rig, all points protected, 2 cm cells; skips
    where Warp has no CUDA device (the staged inputs are CUDA's zero-copy path)."""
    if not get_backend("warp").device.is_cuda:
        pytest.skip("the staged inputs are CUDA's zero-copy path")
    cams, frames = random_rig(rng, n_cams=n_cams)
    pipe = get_backend("warp").pipeline(cams, params_for("all", cell=0.02))
    pipe.ingest(frames)
    return pipe, pipe.host_snapshot()


def test_inputs_staged_by_the_first_blocks_move_proxies_as_the_copies_do():
    """On CUDA's zero-copy path the first blocks to start copy every proxy's position and HIP
    and the tick's arguments from host memory into device memory for the others
    (kernels/warp/tick_inputs.py); the copying path's graph copies them instead. Both run the
    same step code on the same inputs, so every tick's results agree bit for bit: across batch
    sizes whose copy takes one block or several and whose 3 n floats leave a tail (n = 7, 300,
    1,030) or are nothing but a tail (n = 1), positions the host resets between ticks (the staged
    copy must be this tick's), and sizes changing back and forth (the protocol's words at rest
    between ticks)."""
    from pointfence.kernels.haptics import HapticParams

    rng = np.random.default_rng(53)
    pipe, snap = _cuda_rig(rng, n_cams=2)
    p = HapticParams(max_steps=40)
    staged = pipe.proxies(np.zeros((1, 3)), p, tuning=WarpTuning(resident_max=0, stage_min=1))
    copies = pipe.proxies(np.zeros((1, 3)), p, tuning=WarpTuning(resident_max=0, zero_copy_max=0))
    assert staged.staged(1) and staged.staged(1030) and not copies.zero_copy(7) and not copies.staged(7)
    moved = 0
    for B in (300, 1, 7, 1030, 2, 300):
        surf = snap.points[rng.integers(0, snap.n_points, B), :3].astype(np.float64)
        start = surf + rng.normal(0, 0.01, (B, 3)) + [0, 0, -0.015]
        staged.reset(start)
        copies.reset(start)
        h = start.copy()
        for k in range(12):
            if k == 6:   # the host moves every proxy between two ticks
                jump = staged.positions + rng.normal(0, 0.003, (B, 3))
                staged.reset(jump)
                copies.reset(jump)
            h = h + rng.normal(0, 0.0015, h.shape) + [0, 0, 0.0008]
            staged.step(h)
            copies.step(h)
            for name in ("positions", "normals", "nearest", "states", "steps", "converged"):
                np.testing.assert_array_equal(getattr(staged, name), getattr(copies, name), err_msg=f"{name}, B={B}")
            moved += int(staged.steps.sum())
    staged.close()
    copies.close()
    assert moved > 1000


def test_a_copy_needing_more_blocks_than_fit_at_once_still_finishes():
    """The bodies that copy a staged tick's inputs are at most the device's SM count, each taking
    more chunks where the copy is larger: every one of them is on the GPU before any body can
    finish waiting. A zero-copy batch of 65,536 proxies at 32 threads a proxy needs 3,072 bodies
    of 32 chunks, more than an H100 or H200 holds at once (13 blocks an SM); with a body a slice,
    every resident body would wait for a copier that cannot start, and the tick would never end.
    Its results are the copying path's, bit for bit."""
    from pointfence.kernels.haptics import HapticParams
    from pointfence.kernels.warp.tuning import ANY

    rng = np.random.default_rng(59)
    pipe, snap = _cuda_rig(rng, n_cams=1)
    B = 65536
    assert -(-2 * (3 * B // 4) // 32) > 16 * pipe.device.sm_count   # (more bodies than fit at once)
    p = HapticParams(max_steps=20)
    start = snap.points[rng.integers(0, snap.n_points, B), :3].astype(np.float64) + [0.0, 0.0, -0.012]
    tuned = dict(resident_max=0, block_dims=((ANY, 32),), ws_caps=((ANY, 256),))
    staged = pipe.proxies(start, p, tuning=WarpTuning(zero_copy_max=B, **tuned))
    copies = pipe.proxies(start, p, tuning=WarpTuning(zero_copy_max=0, **tuned))
    assert staged.staged() and not copies.zero_copy()
    h = start.copy()
    for _ in range(3):
        h = h + rng.normal(0, 0.001, h.shape) + [0, 0, 0.0008]
        staged.step(h)
        copies.step(h)
        np.testing.assert_array_equal(staged.positions, copies.positions)
        np.testing.assert_array_equal(staged.steps, copies.steps)
    assert staged.steps.sum() > B // 2
