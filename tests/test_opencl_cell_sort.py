"""The OpenCL cell sort's two shapes (kernels/opencl/cell_sort.py) against the NumPy reference,
entry for entry: cell starts, pixels in pixel order within each cell, protected bits, and the
snapshot's points and velocities, on random rigs, real recordings and scenes built to break the
GPU shape (one cell holding the whole rig, runs cut at every RUN_MAX block, cells alternating
pixel by pixel, no point at all), over repeated builds; how the shape is chosen; and the pinned
upload array (`depth_staging`) that GPU devices ingest from.

On PoCL (a CPU device) the GPU shape is forced (``kernel_shape="gpu"``); PoCL's worker threads
hand out the atomics' ranges in a different order from build to build, which the GPU shape must
undo. ``POINTFENCE_OPENCL_DEVICE=nvidia`` runs the same tests on an NVIDIA GPU.
"""
import dataclasses
import subprocess
import sys
import textwrap
import zlib

import numpy as np
import pytest

from pointfence.kernels import Camera, DepthFrame, InputError, PipelineParams, Workspace, get_backend
from pointfence.kernels.motion import MotionModel
from pointfence.kernels.opencl.cell_sort import RUN_MAX
from pointfence.kernels.opencl.kernel_shape import ENVIRONMENT

from kernel_cases import SHARED, params_for, random_rig, read_png16

SHAPES = ("cpu", "gpu")


def pipelines(cams, params, shape):
    """The reference's pipeline and the OpenCL one of ``shape`` on the same cameras."""
    dev = get_backend("opencl", kernel_shape=shape).pipeline(cams, params)
    assert dev.cell_sort.shape == shape
    return get_backend("numpy").pipeline(cams, params), dev


def assert_same_snapshot(dev, ref, what=""):
    """Every array of the two snapshots equal, in the same order: cell starts, pixels, cameras
    and protected bits exactly; positions, radii and sigmas to rounding (OpenCL's sqrt may
    differ from NumPy's in the last bit)."""
    a, b = ref.host_snapshot(), dev.host_snapshot()
    assert b.n_points == a.n_points, f"{what}: {b.n_points} points vs the reference's {a.n_points}"
    np.testing.assert_array_equal(b.cell_start, a.cell_start, err_msg=f"{what} cell_start")
    np.testing.assert_array_equal(b.pixel, a.pixel, err_msg=f"{what} pixel order")
    np.testing.assert_array_equal(b.camera, a.camera, err_msg=f"{what} camera")
    np.testing.assert_array_equal(b.protected, a.protected, err_msg=f"{what} protected")
    np.testing.assert_allclose(b.points, a.points, rtol=1e-6, atol=1e-7, err_msg=f"{what} points")
    np.testing.assert_allclose(b.sigma, a.sigma, rtol=1e-6, atol=1e-9, err_msg=f"{what} sigma")
    cell = b.cell_of()
    same = cell[1:] == cell[:-1]
    assert np.all(b.pixel[1:][same] > b.pixel[:-1][same]), f"{what}: a cell out of pixel order"
    return b


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("selection,cell", [("mask", 0.02), ("color", 0.01), ("box", 0.05), ("all", 0.2)])
def test_random_rigs_equal_the_reference(shape, selection, cell):
    """Three small cameras (one distorted), invalid and out-of-range pixels, protected bits from
    every selection, cells from 1 cm (a few pixels a cell) to 20 cm (whole images)."""
    rng = np.random.default_rng(zlib.crc32(f"{shape}{selection}{cell}".encode()))
    cams, frames = random_rig(rng, n_cams=3)
    ref, dev = pipelines(cams, params_for(selection, cell=cell), shape)
    for k in range(3):   # the second slot too, and a changed frame
        fr = [dataclasses.replace(f, depth=(f.depth + 7 * k * (f.depth > 0)).astype(np.uint16)) for f in frames]
        ref.ingest(fr)
        dev.ingest(fr)
        snap = assert_same_snapshot(dev, ref, f"{shape} {selection} {cell} build {k}")
    assert snap.n_points > 10000 and snap.protected.any()
    assert snap.protected.all() == (selection == "all"), "a selection that protects everything tests no bit"


def wall_camera(name, w=200, h=150, z=0.5):
    return Camera(name, w, h, 180.0, 180.0, w / 2, h / 2, depth_scale=0.001, T_world_cam=np.eye(4),
                  z_min=0.1, z_max=3.0)


@pytest.mark.parametrize("shape", SHAPES)
def test_one_cell_holding_every_point(shape):
    """A cell larger than the workspace: every pixel of both cameras in cell 0, so the GPU shape's
    runs are cut only at RUN_MAX blocks (hundreds of runs in one cell, crossing the cameras' seam)."""
    cams = [wall_camera("a"), wall_camera("b")]
    params = PipelineParams(workspace=Workspace((-2, -2, 0.0), (2, 2, 2.0)), cell_size=5.0)
    d = np.full((150, 200), 600, np.uint16)
    frames = [DepthFrame("a", d, 0.0), DepthFrame("b", d + 50, 0.0)]
    ref, dev = pipelines(cams, params, shape)
    ref.ingest(frames)
    dev.ingest(frames)
    snap = assert_same_snapshot(dev, ref, f"{shape} one cell")
    assert snap.n_points == 2 * 150 * 200 and snap.n_points > 100 * RUN_MAX
    np.testing.assert_array_equal(snap.pixel, np.arange(snap.n_points))


@pytest.mark.parametrize("shape", SHAPES)
def test_cells_alternating_pixel_by_pixel(shape):
    """Depths alternating between two cells at every pixel, with holes: runs of one pixel, so
    every point of a cell is a run head of its own (the most runs a cell can hold)."""
    cams = [wall_camera("a"), wall_camera("b", w=160, h=90)]
    params = PipelineParams(workspace=Workspace((-2, -2, 0.0), (2, 2, 2.0)), cell_size=0.1)
    rng = np.random.default_rng(3)
    frames = []
    for cam in cams:
        v, u = np.mgrid[0:cam.height, 0:cam.width]
        d = np.where((u + v) % 2 == 0, 420, 780).astype(np.uint16)
        d[rng.random(d.shape) < 0.05] = 0
        frames.append(DepthFrame(cam.name, d, 0.0))
    ref, dev = pipelines(cams, params, shape)
    ref.ingest(frames)
    dev.ingest(frames)
    snap = assert_same_snapshot(dev, ref, f"{shape} alternating")
    cell = snap.cell_of()
    assert np.count_nonzero(np.diff(cell[np.argsort(snap.pixel, kind="stable")]) != 0) > snap.n_points // 2


@pytest.mark.parametrize("shape", SHAPES)
def test_no_point_then_points_then_none(shape):
    """Frames with no valid pixel give an empty snapshot (every cell empty), and a full one after
    it, then an empty one again: nothing of the last build survives into the next."""
    rng = np.random.default_rng(11)
    cams, frames = random_rig(rng, n_cams=2)
    ref, dev = pipelines(cams, params_for("mask"), shape)
    empty = [dataclasses.replace(f, depth=np.zeros_like(f.depth)) for f in frames]
    for fr, what in ((empty, "empty"), (frames, "full"), (empty, "empty again"), (frames, "full again")):
        ref.ingest(fr)
        dev.ingest(fr)
        snap = assert_same_snapshot(dev, ref, f"{shape} {what}")
        assert (snap.n_points == 0) == what.startswith("empty")


def apc_frames(n):
    root = SHARED / "apc_shelfbin_50f"
    if not root.is_dir():
        pytest.skip("../shared/data/apc_shelfbin_50f not found: real-data tests need the shared folder")
    K = np.loadtxt(root / "intrinsics.K.txt")
    cams, frames = [], []
    for k in range(n):   # the same camera placed twice (two poses of the recording): a 2-camera rig
        fid = 15 + 10 * k
        T = np.loadtxt(root / f"frame-{fid:06d}.pose.txt")
        U, _, Vt = np.linalg.svd(T[:3, :3])
        T[:3, :3] = U @ Vt
        cams.append(Camera(f"apc{k}", 640, 480, K[0, 0], K[1, 1], K[0, 2], K[1, 2], T_world_cam=T, z_min=0.2, z_max=1.5))
        frames.append(DepthFrame(f"apc{k}", read_png16(root / f"frame-{fid:06d}.depth.png"), 0.0))
    return cams, frames


@pytest.mark.parametrize("shape", SHAPES)
def test_real_shelf_bin_equals_the_reference_on_every_build(shape):
    """Two APC shelf-bin views (0.3-0.5 m: thousands of points in a 3 cm cell, dozens of runs of
    each cell a camera), ten builds: each equal to the reference, so the ranges PoCL's threads
    hand out in a new order on every build never show in the snapshot."""
    cams, frames = apc_frames(2)
    params = PipelineParams(workspace=Workspace((-0.5, -0.5, 0.0), (0.5, 0.5, 1.2)), cell_size=0.03)
    ref, dev = pipelines(cams, params, shape)
    ref.ingest(frames)
    first = None
    for k in range(10):
        dev.ingest([dataclasses.replace(f, seq=k) for f in frames])
        snap = assert_same_snapshot(dev, ref, f"{shape} shelf bin build {k}")
        first = first if first is not None else np.diff(snap.cell_start).max()
    assert snap.n_points > 200000 and first > 2000


def test_motion_velocities_equal_across_shapes():
    """With motion estimation on, the cell moments read the sorted order: both shapes give the
    same velocities, bit for bit, on a rig that moves between frames."""
    rng = np.random.default_rng(5)
    cams, frames = random_rig(rng, n_cams=2)
    params = dataclasses.replace(params_for("all", cell=0.03), motion=MotionModel(enabled=True))
    out = {}
    for shape in SHAPES:
        pipe = get_backend("opencl", kernel_shape=shape).pipeline(cams, params)
        vel = []
        for k in range(4):
            shifted = [dataclasses.replace(f, depth=(f.depth + 4 * k * (f.depth > 0)).astype(np.uint16),
                                           timestamp=f.timestamp + k / 30) for f in frames]
            pipe.ingest(shifted)
            s = pipe.host_snapshot()
            vel.append((s.pixel.copy(), None if s.velocity is None else s.velocity.copy()))
        out[shape] = vel
    assert any(v is not None for _, v in out["cpu"]), "no velocities estimated: the test compares none"
    for (pa, va), (pb, vb) in zip(out["cpu"], out["gpu"]):
        np.testing.assert_array_equal(pa, pb)
        assert (va is None) == (vb is None)
        if va is not None:
            np.testing.assert_array_equal(va, vb)


def test_shape_follows_the_device_and_the_setting(monkeypatch):
    """"auto" sorts with the GPU shape on GPU devices only; the setting and its environment
    variable force either; a misspelt one is refused with the choices."""
    cams, _ = random_rig(np.random.default_rng(0), n_cams=1)
    backend = get_backend("opencl")
    is_gpu = bool(backend.device.type & backend.cl.device_type.GPU)
    assert backend.pipeline(cams, params_for()).cell_sort.shape == ("gpu" if is_gpu else "cpu")
    monkeypatch.setenv(ENVIRONMENT, "gpu")
    assert get_backend("opencl").pipeline(cams, params_for()).cell_sort.shape == "gpu"
    monkeypatch.setenv(ENVIRONMENT, "cpu")
    assert get_backend("opencl").pipeline(cams, params_for()).cell_sort.shape == "cpu"
    with pytest.raises(InputError, match="expected one of auto, cpu, gpu"):
        get_backend("opencl", kernel_shape="gpus")


@pytest.fixture(params=["device", "forced"])
def pinned(request, monkeypatch):
    """The pinned upload array as the device has it ("device": on GPUs only), or forced on
    ("forced": PoCL runs the same path over its host memory)."""
    if request.param == "forced":
        import pointfence.kernels.opencl.pipeline as ocl_pipeline

        monkeypatch.setattr(ocl_pipeline, "pinned_upload", lambda device, cl: True)
    return request.param


def test_frames_written_into_depth_staging_give_the_same_snapshot(pinned):
    """Frames from their own arrays, frames written in place into ``depth_staging`` and a mix of
    both give the reference's snapshot (the in-place frames were copied nowhere else: a missed
    upload would build from the last images); a camera not in the rig is refused by name; a
    frame from its own array is copied into its camera's view."""
    rng = np.random.default_rng(7)
    cams, frames = random_rig(rng, n_cams=3)
    ref = get_backend("numpy").pipeline(cams, params_for("mask"))
    dev = get_backend("opencl").pipeline(cams, params_for("mask"))
    views = [dev.depth_staging(c.name) for c in cams]
    backend = dev.backend
    if pinned == "device" and backend.device.type & backend.cl.device_type.CPU:
        assert views == [None, None, None], "a CPU device has no upload array: its buffers are host memory"
        return
    assert all(v.shape == (c.height, c.width) and v.dtype == np.uint16 for v, c in zip(views, cams))
    assert dev.depth_staging(1) is views[1]
    with pytest.raises(InputError, match="no camera 'nope' in the rig"):
        dev.depth_staging("nope")
    ref.ingest(frames)
    dev.ingest(frames)
    assert_same_snapshot(dev, ref, "own arrays")
    later = [dataclasses.replace(f, depth=np.roll(f.depth, 3 * (i + 1), axis=1)) for i, f in enumerate(frames)]
    for v, f in zip(views, later):
        np.copyto(v, f.depth)
    staged = [dataclasses.replace(f, depth=v) for f, v in zip(later, views)]
    ref.ingest(later)
    dev.ingest(staged)
    assert_same_snapshot(dev, ref, "written in place")
    mixed = [staged[0], frames[1], staged[2]]   # camera 1 from its own array again
    ref.ingest([later[0], frames[1], later[2]])
    dev.ingest(mixed)
    assert_same_snapshot(dev, ref, "mixed")
    np.testing.assert_array_equal(views[1], frames[1].depth)   # its own array was copied into the view


def test_a_real_rocking_run_builds_its_snapshots(shared_data):
    """apc rocking at 0.1 m/s (chapter 6 on real frames, issue 23): a grid of 16,359 cells. The
    per-cell sort once kept each cell's stretch list in private arrays (2 KB a work-item), which
    PoCL replicates for every work-item of a work-group: this run's first build crashed the
    process (SIGSEGV). Run in a process of its own, so that a crash fails this test only."""
    code = textwrap.dedent("""
        import math
        from pointfence.service import dynamic_real as dr
        res = dr.sweep(("apc_shelfbin_50f",), speeds=(0.1,), radii=(0.01,), cases=(("rocking", "push"),))
        (row,) = [r for r in res["rows"] if r["scene"].startswith("apc")]
        assert math.isfinite(row["proxy_mm_with"]) and math.isfinite(row["proxy_mm_without"]), row
        print("built", row["proxy_mm_with"])
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0 and "built" in proc.stdout, (proc.returncode, proc.stderr[-2000:])
