"""``FramePipeline.ingest_steps``: a build in two parts (submitted, then finished), as a replay
runs it beside its ticks (service/recorded_frames.py). Nothing is published before the second
part, queries keep the front snapshot meanwhile, and the result is bit for bit the snapshot of
a plain ``ingest``; a build abandoned between its parts publishes nothing and leaves the
pipeline usable. On real frames (the 7-Scenes kitchen, a moving camera), motion on and off."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from pointfence.kernels import Camera, Workspace, get_backend
from pointfence.kernels.backend import run_steps

from kernel_cases import device_backends
from test_snapshot_determinism import assert_bit_identical, kitchen_params, kitchen_sequence, snapshot_arrays

def _quarter(cam, frames):
    """The camera at a quarter of its resolution (every 4th pixel)."""
    small = Camera(cam.name, cam.width // 4, cam.height // 4, cam.fx / 4, cam.fy / 4, cam.cx / 4, cam.cy / 4,
                   T_world_cam=np.eye(4))
    return small, [replace(f, depth=np.ascontiguousarray(f.depth[::4, ::4])) for f in frames]


def _query(pipe, at):
    nb = pipe.neighbors(at, 0.05, 32)
    return np.asarray(nb.count).copy(), np.asarray(nb.index).copy()


@pytest.mark.parametrize("motion", [False, True])
@pytest.mark.parametrize("backend", ["numpy"] + device_backends())
def test_a_build_in_two_parts_publishes_only_at_its_end_and_equals_a_plain_ingest(backend, motion):
    cam, frames = kitchen_sequence(3)
    params = kitchen_params(motion=motion)
    if motion:    # (the motion grid's tables cover the workspace: the kitchen's corner of it only)
        cam, frames = _quarter(cam, frames)
        params = replace(params, workspace=Workspace((-2.8, -1.7, 1.0), (-0.9, 0.7, 3.2)))
    plain = get_backend(backend).pipeline([cam], params)
    want = []
    for f in frames:
        plain.ingest([f])
        want.append(snapshot_arrays(plain.host_snapshot()))
    pipe = get_backend(backend).pipeline([cam], params)
    info = pipe.ingest([frames[0]])
    before = snapshot_arrays(pipe.host_snapshot())
    at = before["points"][:: max(1, len(before["points"]) // 7), :3].astype(np.float64)   # on the kitchen's surfaces
    q0 = _query(pipe, at)
    assert (q0[0] > 0).all()
    for i in (1, 2):
        steps = pipe.ingest_steps([frames[i]])
        assert next(steps) is None                 # submitted: the device builds into the back slot
        assert pipe.host_snapshot().seq == info.seq
        assert_bit_identical(before, snapshot_arrays(pipe.host_snapshot()), f"{backend}: front during build {i}")
        qi = _query(pipe, at)
        np.testing.assert_array_equal(qi[0], q0[0])
        np.testing.assert_array_equal(qi[1], q0[1])
        info = run_steps(steps)
        assert info.seq == i + 1 and pipe.host_snapshot().seq == i + 1
        before = snapshot_arrays(pipe.host_snapshot())
        assert_bit_identical(want[i], before, f"{backend} motion={motion}: build {i} in two parts")
        q0 = _query(pipe, at)


@pytest.mark.parametrize("backend", ["numpy"] + device_backends())
def test_a_build_abandoned_between_its_parts_publishes_nothing(backend):
    cam, frames = kitchen_sequence(3)
    params = kitchen_params()
    pipe = get_backend(backend).pipeline([cam], params)
    pipe.ingest([frames[0]])
    front = snapshot_arrays(pipe.host_snapshot())
    steps = pipe.ingest_steps([frames[1]])
    next(steps)
    steps.close()                                   # (waits for the submitted device work)
    assert pipe.host_snapshot().seq == 1
    assert_bit_identical(front, snapshot_arrays(pipe.host_snapshot()), f"{backend}: after the abandoned build")
    assert pipe.ingest([frames[2]]).seq == 2
    other = get_backend(backend).pipeline([cam], params)
    other.ingest([frames[2]])
    a, b = snapshot_arrays(pipe.host_snapshot()), snapshot_arrays(other.host_snapshot())
    assert_bit_identical(b, a, f"{backend}: the next build after an abandoned one")
