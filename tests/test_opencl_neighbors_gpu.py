"""The GPU-shaped OpenCL neighbour query (neighbors_gpu.cl: a work-group a query) against the NumPy
reference and the CPU-shaped kernel (neighbors.cl), bit for bit: counts, the first K hits in scan
order, the nearest with ties to the earlier point and its distance, protected_only, empty results,
on random and real data, at several work-group sizes; the host side's buffers reused across calls;
and how the kernel is chosen.

On PoCL (a CPU device) the GPU shape is forced; PoCL compiles it once per work-group size (a few
seconds, then from its cache). ``POINTFENCE_OPENCL_DEVICE=nvidia`` runs the same tests on a GPU.
"""
import dataclasses
import threading
import zlib

import numpy as np
import pytest

from pointfence.kernels import DepthFrame, InputError, PipelineParams, RadiusModel, Selection, Workspace, get_backend
from pointfence.kernels.opencl.kernel_shape import ENVIRONMENT, NEIGHBOR_GROUPS, neighbor_group_size
from pointfence.kernels.opencl.neighbor_query import NeighborQuery
from pointfence.kernels.reference.neighbors import brute_force
from pointfence.kernels.reference.neighbors import neighbors as reference_neighbors

from kernel_cases import SHARED, kitchen_rig, params_for, random_rig

# 1: every batch of rows a loop of its own; 7: not a power of two (the reduction's odd tail); 32 to 1,024
GROUPS = (1, 7, 32, 256, 1024)
FIELDS = ("count", "index", "nearest", "nearest_dist")


def assert_same(got, want, what=""):
    for f in FIELDS:
        a, b = getattr(got, f), getattr(want, f)
        assert a.dtype == b.dtype and a.shape == b.shape, f"{what} {f}: {a.dtype}{a.shape} vs {b.dtype}{b.shape}"
        # bits, not values: -1/inf padding and the distance's last bit included
        np.testing.assert_array_equal(a.view(np.int32), b.view(np.int32), err_msg=f"{what} {f}")


def fits(pipe, w):
    """Whether the device runs the GPU-shaped kernel at ``w`` work-items (NVIDIA's OpenCL allows
    this kernel 256; PoCL 1,024): a size it cannot run is refused with an InputError that says so."""
    try:
        NeighborQuery(pipe, kernel_shape="gpu", group_size=w)(np.zeros((1, 3), np.float32), 0.01, 1, False)
    except InputError as e:
        if "choose one in that range" not in str(e):
            raise
        return False
    return True


def gpu_query(pipe, w, **options):
    """The GPU-shaped query at ``w`` work-items; the test is skipped where the device cannot run them."""
    if not fits(pipe, w):
        pytest.skip(f"{pipe.backend.device_name} runs the GPU-shaped neighbour kernel at fewer than {w} work-items")
    return NeighborQuery(pipe, kernel_shape="gpu", group_size=w, **options)


def shapes(pipe, group_size):
    """The CPU- and GPU-shaped queries on ``pipe``'s snapshots."""
    return NeighborQuery(pipe, kernel_shape="cpu"), gpu_query(pipe, group_size)


def check_all(pipe, snap, q, radius, K, protected_only, group_size):
    """GPU shape == CPU shape == reference, to the bit; returns the reference."""
    cpu, gpu = shapes(pipe, group_size)
    want = reference_neighbors(snap, q, radius, K, protected_only)
    assert_same(cpu(q, radius, K, protected_only), want, "cpu")
    assert_same(gpu(q, radius, K, protected_only), want, f"gpu w={group_size}")
    return want


def surface_queries(rng, snap, n, spread):
    idx = rng.integers(0, snap.n_points, n)
    return (snap.points[idx, :3] + rng.normal(0, spread, (n, 3))).astype(np.float32)


@pytest.fixture(scope="module")
def random_pipe():
    rng = np.random.default_rng(11)
    cams, frames = random_rig(rng)
    pipe = get_backend("opencl").pipeline(cams, params_for("mask"))
    pipe.ingest(frames)
    return pipe, pipe.host_snapshot()


@pytest.mark.parametrize("group_size", GROUPS)
@pytest.mark.parametrize("radius,K", [
    (0.004, 4096),    # below the 2 cm cell: one cell of reach each side, nothing truncated
    (0.0123, 16),     # truncated rows: the first 16 hits in scan order
    (0.035, 64),      # 2 cells each side: 25 rows, several batches of rows at small work-groups
    (0.1, 3),         # 5 cells each side: 121 rows
])
def test_gpu_shape_equals_reference_and_cpu_shape_random(random_pipe, radius, K, group_size):
    pipe, snap = random_pipe
    rng = np.random.default_rng(zlib.crc32(repr((radius, K, group_size)).encode()))
    q = surface_queries(rng, snap, 33, 0.01)
    q[0] = [5.0, 5.0, 5.0]            # far outside the workspace: no cells at all
    q[1] = snap.points[0, :3]         # exactly on a point: distance 0
    q[2] = [-0.605, 0.0, 0.8]         # just outside the workspace's -x face
    want = check_all(pipe, snap, q, radius, K, False, group_size)
    assert want.count[0] == 0 and want.count.sum() > 0
    if K < 4096:
        assert want.truncated.any()
    prot = check_all(pipe, snap, q, radius, K, True, group_size)
    assert prot.count.sum() < want.count.sum() and (radius < 0.01 or prot.count.sum() > 0)
    assert np.all(snap.protected[prot.index[prot.index >= 0]] != 0)


def test_hits_beyond_k_are_the_reference_scan_order_not_any_subset(random_pipe):
    """With K below the count every work-item's hits land past K except the first few: the row
    must be the first K hits in scan order (ascending snapshot index), for every split."""
    pipe, snap = random_pipe
    rng = np.random.default_rng(3)
    q = surface_queries(rng, snap, 12, 0.002)
    for w in [w for w in GROUPS if fits(pipe, w)]:
        nb = NeighborQuery(pipe, kernel_shape="gpu", group_size=w)(q, 0.03, 5, False)
        bf = brute_force(snap.points, q, 0.03)
        for i in range(len(q)):
            assert nb.count[i] == bf[i].size > 5
            np.testing.assert_array_equal(nb.index[i], bf[i][:5])   # brute force lists ascending index


@pytest.mark.parametrize("group_size", GROUPS)
def test_every_candidate_a_hit(random_pipe, group_size):
    """A 2 m radius reaches every cell of the grid (thousands of rows, many batches of rows) and
    every point is a hit: each work-item's run, long or short, is written whole, the first 64
    candidates from the count's bits and the rest tested again, in scan order."""
    pipe, snap = random_pipe
    q = np.array([[0.0, 0.0, 0.8], [0.55, -0.45, 1.15], [5.0, 5.0, 5.0]], np.float32)
    want = check_all(pipe, snap, q, 2.0, snap.n_points, False, group_size)
    assert want.count[0] == want.count[1] == snap.n_points and want.count[2] == 0
    np.testing.assert_array_equal(want.index[0], np.arange(snap.n_points))
    check_all(pipe, snap, q, 2.0, 1000, True, group_size)


def test_empty_results_and_no_queries(random_pipe):
    pipe, snap = random_pipe
    q = np.array([[5.0, 5.0, 5.0], [-5.0, 0.0, 0.8], [0.0, 0.0, 0.31]], np.float32)
    for w in GROUPS[1:3]:
        gpu = NeighborQuery(pipe, kernel_shape="gpu", group_size=w)
        nb = gpu(q, 0.001, 8, False)
        assert_same(nb, reference_neighbors(snap, q, 0.001, 8))
        assert np.all(nb.count == 0) and np.all(nb.index == -1) and np.all(nb.nearest == -1)
        assert np.all(np.isinf(nb.nearest_dist))
        none = gpu(np.zeros((0, 3), np.float32), 0.01, 8, False)
        assert none.count.shape == (0,) and none.index.shape == (0, 8)
    cams, _ = random_rig(np.random.default_rng(1), n_cams=1)
    none = get_backend("opencl", kernel_shape="gpu").pipeline(cams, params_for("all"))
    # (no snapshot ingested yet: every cell empty)
    assert_same(none.neighbors(q, 0.05, max_neighbors=4),
                reference_neighbors(none.host_snapshot(), q, 0.05, 4))


def duplicated_rig(rng):
    """One camera twice (same pose, same frame): every point twice, at the same place, so
    every nearest is a tie between two snapshot indices."""
    cams, frames = random_rig(rng, n_cams=1)
    twin = dataclasses.replace(cams[0], name="twin")
    f = frames[0]
    return [cams[0], twin], [f, DepthFrame("twin", f.depth.copy(), f.timestamp, color=f.color, mask=f.mask)]


@pytest.mark.parametrize("group_size", GROUPS)
def test_nearest_ties_go_to_the_earlier_point(group_size):
    rng = np.random.default_rng(8)
    cams, frames = duplicated_rig(rng)
    pipe = get_backend("opencl").pipeline(cams, params_for("mask"))
    pipe.ingest(frames)
    snap = pipe.host_snapshot()
    pos = snap.points[:, :3]
    q = np.concatenate([pos[rng.integers(0, snap.n_points, 16)],           # on a point (twice over)
                        surface_queries(rng, snap, 16, 0.004)]).astype(np.float32)
    want = check_all(pipe, snap, q, 0.015, 32, False, group_size)
    check_all(pipe, snap, q, 0.015, 32, True, group_size)
    # each nearest has a twin at the same distance, and the reported one is the earlier
    ties = 0
    for i in range(len(q)):
        j = want.nearest[i]
        same = np.flatnonzero(np.all(pos == pos[j], axis=1))
        assert same.size >= 2 and j == same.min()
        ties += 1
    assert ties == len(q)


@pytest.mark.parametrize("staged", [True, False])
def test_buffers_reused_across_growing_and_shrinking_calls(random_pipe, staged):
    """Query counts and K up and down on one query object (its staging grows, never shrinks; each
    slot's kernel keeps its arguments and sets only what changed), the result read through the
    pinned staging or straight into the returned arrays: every call equal to the reference, and
    arrays returned earlier untouched by later calls."""
    pipe, snap = random_pipe
    rng = np.random.default_rng(21)
    gpu = NeighborQuery(pipe, kernel_shape="gpu", group_size=32, staged=staged)
    cpu = NeighborQuery(pipe, kernel_shape="cpu", staged=staged)
    kept = []
    for B, K, r, prot in [(3, 4, 0.01, False), (40, 64, 0.02, False), (5, 300, 0.02, True), (70, 2, 0.006, False),
                          (1, 1, 0.03, True), (70, 2, 0.006, False), (17, 1000, 0.012, False)]:
        q = surface_queries(rng, snap, B, 0.008)
        want = reference_neighbors(snap, q, r, K, prot)
        got = gpu(q, r, K, prot)
        assert_same(got, want, f"gpu B={B} K={K}")
        assert_same(cpu(q, r, K, prot), want, f"cpu B={B} K={K}")
        kept.append((got, want))
    for got, want in kept:
        assert_same(got, want, "kept")


def test_new_snapshots_are_queried_not_the_first(random_pipe):
    """Each slot has its own kernel instance: after the next ingest (the other slot) a query sees
    the new snapshot."""
    rng = np.random.default_rng(4)
    cams, frames = random_rig(rng, n_cams=1)
    pipe = get_backend("opencl", kernel_shape="gpu").pipeline(cams, params_for("all"))
    pipe.neighbor_query.group_size = 32
    for shift in (0, 7, 13):
        for f in frames:
            f.depth = np.roll(f.depth, shift, axis=1)
        pipe.ingest(frames)
        snap = pipe.host_snapshot()
        q = surface_queries(rng, snap, 9, 0.005)
        assert_same(pipe.neighbors(q, 0.015, max_neighbors=40), reference_neighbors(snap, q, 0.015, 40))


def test_concurrent_callers_take_turns(random_pipe):
    pipe, snap = random_pipe
    gpu = NeighborQuery(pipe, kernel_shape="gpu", group_size=32)
    rng = np.random.default_rng(6)
    cases = [(surface_queries(rng, snap, 5 + 7 * i, 0.01), 8 + 5 * i) for i in range(4)]
    errors = []

    def run(q, K):
        try:
            for _ in range(5):
                assert_same(gpu(q, 0.015, K, False), reference_neighbors(snap, q, 0.015, K))
        except AssertionError as e:
            errors.append(e)

    threads = [threading.Thread(target=run, args=c) for c in cases]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert not errors, errors[0]


def kitchen_pipe(selection):
    cams, frames = kitchen_rig()
    params = PipelineParams(workspace=Workspace((-3, -3, -3), (3, 3, 3)), cell_size=0.03, selection=selection,
                            radius=RadiusModel(r_base=0.01, adaptive=True, r_max=0.03))
    pipe = get_backend("opencl").pipeline(cams, params)
    pipe.ingest(frames)
    return pipe, pipe.host_snapshot()


@pytest.mark.parametrize("group_size", (32, 1024))
def test_real_rig_equals_reference_and_cpu_shape(group_size):
    """Two 7-Scenes kitchen frames: dense surfaces, hundreds of hits a query, truncated rows; a box
    of the scene protected."""
    if not SHARED.is_dir():
        pytest.skip("../shared/data not found: real-data tests need the shared folder beside the project")
    _, whole = kitchen_pipe(Selection())
    mid = np.median(whole.points[:, :3], axis=0)
    pipe, snap = kitchen_pipe(Selection("box", box_min=tuple(mid - 0.4), box_max=tuple(mid + 0.4)))
    rng = np.random.default_rng(5)
    q = surface_queries(rng, snap, 30, 0.005)
    full = check_all(pipe, snap, q, 0.01, 100000, False, group_size)
    assert full.count.sum() > 30 * 20
    cut = check_all(pipe, snap, q, 0.02, 50, False, group_size)
    assert cut.truncated.sum() >= 10
    prot = check_all(pipe, snap, q, 0.02, 50, True, group_size)
    assert 0 < prot.count.sum() < cut.count.sum()


def test_kernel_shape_picks_the_neighbour_kernel(monkeypatch):
    cams, frames = random_rig(np.random.default_rng(2), n_cams=1)
    p = params_for("all")
    gpu_device = bool(get_backend("opencl").device.type & get_backend("opencl").cl.device_type.GPU)
    assert get_backend("opencl").pipeline(cams, p).neighbor_query.shape == ("gpu" if gpu_device else "cpu")
    assert get_backend("opencl", kernel_shape="gpu").pipeline(cams, p).neighbor_query.shape == "gpu"
    assert get_backend("opencl", kernel_shape="cpu").pipeline(cams, p).neighbor_query.shape == "cpu"
    monkeypatch.setenv(ENVIRONMENT, "gpu")
    pipe = get_backend("opencl").pipeline(cams, p)
    assert pipe.neighbor_query.shape == "gpu"
    pipe.neighbor_query.group_size = 100000
    pipe.ingest(frames)
    with pytest.raises(InputError, match="group_size = 100000"):
        pipe.neighbors([[0.0, 0.0, 0.8]], 0.01)
    with pytest.raises(InputError, match="kernel_shape = 'fast'"):
        NeighborQuery(pipe, kernel_shape="fast")


def test_group_size_table():
    assert neighbor_group_size(64, 1024) == NEIGHBOR_GROUPS[0][1]
    assert neighbor_group_size(10 ** 6, 1024) == NEIGHBOR_GROUPS[-1][1]
    assert neighbor_group_size(64, 48) == 48      # the device's limit for the kernel
