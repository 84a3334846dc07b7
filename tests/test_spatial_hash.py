"""The spatial hash's neighbour primitive: equal to brute force, exactly, on every backend."""
import threading

import numpy as np
import pytest

from pointfence.kernels import get_backend
from pointfence.kernels.reference.neighbors import brute_force

from kernel_cases import device_backends, SHARED, kitchen_params, kitchen_rig, params_for, random_rig

BACKENDS = ["numpy"] + device_backends()


def check_against_brute_force(pipe, queries, radius, K=100000, protected_only=False):
    snap = pipe.host_snapshot()
    nb = pipe.neighbors(queries, radius, max_neighbors=K, protected_only=protected_only)
    bf = brute_force(snap.points, queries, radius, snap.protected if protected_only else None)
    total = 0
    for i, expect in enumerate(bf):
        assert nb.count[i] == expect.size
        got = nb.index[i, : nb.count[i]]
        np.testing.assert_array_equal(np.sort(got), expect)
        assert np.all(nb.index[i, nb.count[i]:] == -1)
        if expect.size:
            d = np.linalg.norm(snap.points[expect, :3].astype(np.float64) - queries[i], axis=1)
            assert abs(nb.nearest_dist[i] - d.min()) < 1e-6
            assert nb.nearest[i] in expect
        else:
            assert nb.nearest[i] == -1
        total += expect.size
    return total


def surface_queries(rng, snap, n, spread):
    idx = rng.integers(0, snap.n_points, n)
    return (snap.points[idx, :3] + rng.normal(0, spread, (n, 3))).astype(np.float32)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("radius", [0.004, 0.0123, 0.02, 0.035])  # below, at and above the 2 cm cell size
def test_neighbors_equal_brute_force_random(backend, radius):
    rng = np.random.default_rng(11)
    cams, frames = random_rig(rng)
    pipe = get_backend(backend).pipeline(cams, params_for("mask"))
    pipe.ingest(frames)
    snap = pipe.host_snapshot()
    q = surface_queries(rng, snap, 40, 0.01)
    q[0] = [5.0, 5.0, 5.0]  # far outside the workspace
    q[1] = snap.points[0, :3]  # exactly on a point
    q[2] = [-0.605, 0.0, 0.8]  # just outside the workspace's -x face
    assert check_against_brute_force(pipe, q, radius) > 0
    check_against_brute_force(pipe, q, radius, protected_only=True)


@pytest.mark.parametrize("backend", BACKENDS)
def test_truncation_keeps_count_and_a_subset(backend):
    rng = np.random.default_rng(2)
    cams, frames = random_rig(rng, n_cams=2)
    pipe = get_backend(backend).pipeline(cams, params_for("all"))
    pipe.ingest(frames)
    snap = pipe.host_snapshot()
    q = surface_queries(rng, snap, 8, 0.002)
    nb = pipe.neighbors(q, 0.02, max_neighbors=8)
    bf = brute_force(snap.points, q, 0.02)
    for i in range(len(q)):
        assert nb.count[i] == bf[i].size > 8
        assert nb.truncated[i]
        assert set(nb.index[i]).issubset(set(bf[i]))


@pytest.mark.parametrize("backend", device_backends())
def test_real_rig_neighbors_equal_brute_force(backend):
    if not SHARED.is_dir():
        pytest.skip("../shared/data not found: real-data tests need the shared folder beside the project")
    rng = np.random.default_rng(5)
    cams, frames = kitchen_rig()
    pipe = get_backend(backend).pipeline(cams, kitchen_params(cams))
    pipe.ingest(frames)
    snap = pipe.host_snapshot()
    q = surface_queries(rng, snap, 30, 0.005)
    assert check_against_brute_force(pipe, q, 0.01) > 30 * 20


@pytest.mark.parametrize("backend", BACKENDS)
def test_readers_always_see_a_complete_snapshot(backend):
    """A reader holding the front snapshot is never overwritten; the builder waits for it."""
    rng = np.random.default_rng(4)
    cams, frames = random_rig(rng, n_cams=1, distort=False)
    pipe = get_backend(backend).pipeline(cams, params_for("all"))
    pipe.ingest(frames)
    first = pipe.host_snapshot()
    done = threading.Event()

    def build_twice():
        for f in frames:
            f.depth = np.roll(f.depth, 5, axis=0)
        pipe.ingest(frames)  # fills the other slot: no wait
        pipe.ingest(frames)  # wants the held slot: waits for the reader
        done.set()

    with pipe.buffers.read():
        t = threading.Thread(target=build_twice)
        t.start()
        assert not done.wait(0.5), "the builder overwrote a snapshot a reader still held"
        held = pipe.buffers.slots[pipe.buffers.front_index ^ 1]
    t.join(30)
    assert done.is_set()
    assert pipe.seq == 3
    del held, first
