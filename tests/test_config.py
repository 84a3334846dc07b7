"""The scene configuration file."""
import textwrap

import numpy as np
import pytest

from pointfence.kernels import InputError
from pointfence.service import config

from kernel_cases import SHARED

GOOD = """
backend = "numpy"
[workspace]
min = [-0.3, -0.3, -0.05]
max = [0.3, 0.3, 0.3]
[fixture]
mode = "fixture"
radius = 0.015
adaptive = true
k_sigma = 2.5
select = { kind = "box", min = [-0.1, -0.1, 0.0], max = [0.1, 0.1, 0.2] }
[[camera]]
name = "left"
source = "synthetic:plane"
fx = 500.0
fy = 501.0
cx = 159.5
cy = 119.5
width = 320
height = 240
depth_scale = 0.001
T_world_cam = [1, 0, 0, 0,  0, -1, 0, 0,  0, 0, -1, 0.6,  0, 0, 0, 1]
noise = { a = 0.0005, b = 0.002 }
[[camera]]
name = "right"
source = "synthetic:plane"
"""


def write(tmp_path, text):
    p = tmp_path / "scene.toml"
    p.write_text(textwrap.dedent(text))
    return p


def test_good_config_parses_every_key(tmp_path):
    c = config.load(write(tmp_path, GOOD))
    assert c.backend == "numpy" and c.mode == "fixture"
    left, right = c.cameras[0].camera, c.cameras[1].camera
    assert (left.fx, left.fy, left.width, left.height) == (500.0, 501.0, 320, 240)
    assert left.noise.a == 0.0005 and left.noise.b == 0.002
    np.testing.assert_allclose(left.T_world_cam[2], [0, 0, -1, 0.6])
    assert right.width == 640  # synthetic default camera
    p = c.pipeline
    assert p.selection.kind == "box" and p.selection.box_max == (0.1, 0.1, 0.2)
    assert p.radius.adaptive and p.radius.k_sigma == 2.5 and p.radius.r_base == 0.015
    assert p.cell_size >= p.radius.r_max + 0.010


def test_defaults_load_and_run_one_frame():
    from pointfence.kernels import get_backend

    c = config.load(None)
    pipe = get_backend(c.backend, c.device).pipeline([x.camera for x in c.cameras], c.pipeline)
    src = c.open_sources()
    info = pipe.ingest([s.read() for s in src])
    snap = pipe.host_snapshot()
    assert info.n_points > 10000
    assert 0 < snap.protected.sum() < snap.n_points  # the red balloon only


@pytest.mark.parametrize("edit, message", [
    (("radius = 0.015", "radious = 0.015"), "unknown key 'radious'; did you mean 'radius'?"),
    (("[workspace]", "[workspaces]"), "unknown key 'workspaces'; did you mean 'workspace'?"),
    (("fx = 500.0", "fx = -500.0"), "fx = -500.0; expected a number > 0"),
    (("fx = 500.0\n", ""), "intrinsics incomplete, missing fx"),
    (("T_world_cam = [1, 0, 0, 0,", "T_world_cam = [2, 0, 0, 0,"), "not a rotation"),
    (("T_world_cam = [1, 0, 0, 0,  0, -1, 0, 0,", "T_world_cam = [1, 0, 0, 0,"), "expected a list of 16 numbers"),
    (('mode = "fixture"', 'mode = "fence"'), "mode = 'fence'; expected one of 'fixture', 'rendering'"),
    (('source = "synthetic:plane"\nfx', 'source = "webcam"\nfx'), "expected 'synthetic:<scene>', 'recorded:<path>', 'openni2:<uri or file.oni>', 'depthai:<device id>' or 'realsense:<serial or file.db3>'"),
    (("noise = { a = 0.0005, b = 0.002 }", "noise = { a = 0.0005, c = 0.002 }"), "unknown key 'c'"),
    (('kind = "box"', 'kind = "sphere"'), "expected one of 'all', 'box', 'color', 'mask'"),
])
def test_config_errors_name_the_value(tmp_path, edit, message):
    old, new = edit
    assert old in GOOD
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)").replace("?", r"\?")):
        config.load(write(tmp_path, GOOD.replace(old, new, 1)))


def test_missing_file_and_bad_toml(tmp_path):
    with pytest.raises(InputError, match="not found"):
        config.load(tmp_path / "nope.toml")
    with pytest.raises(InputError, match="not valid TOML"):
        config.load(write(tmp_path, "backend = \n"))


def test_recorded_camera_takes_intrinsics_from_the_recording(tmp_path):
    if not SHARED.is_dir():
        pytest.skip("../shared/data not found: real-data tests need the shared folder beside the project")
    text = f"""
    [workspace]
    min = [-3, -3, -3]
    max = [3, 3, 3]
    [[camera]]
    name = "kitchen"
    source = "recorded:{SHARED / '7scenes_kitchen_50f'}"
    """
    c = config.load(write(tmp_path, text))
    cam = c.cameras[0].camera
    assert (cam.fx, cam.cx, cam.width) == (585.0, 320.0, 640)
    frame = c.open_sources()[0].read()
    assert frame.depth.shape == (480, 640) and frame.T_world_cam is not None


def test_openni2_camera_takes_intrinsics_from_the_recording(tmp_path):
    pytest.importorskip("openni", reason="OpenNI2 Python bindings missing: pip install openni (and apt-get install libopenni2-0)")
    if not SHARED.is_dir():
        pytest.skip("../shared/data not found: real-data tests need the shared folder beside the project")
    from pointfence.service.sources.openni2 import OpenNI2Unavailable

    text = f"""
    [[camera]]
    name = "primesense"
    source = "openni2:{SHARED / 'oni_3dj' / 'test.oni'}"
    """
    try:
        c = config.load(write(tmp_path, text))
    except OpenNI2Unavailable as e:
        pytest.skip(f"OpenNI2 runtime missing: {e}")
    cam = c.cameras[0].camera
    assert cam.name == "primesense" and (cam.width, cam.height) == (640, 480)
    assert abs(cam.fx - 575.8157) < 0.01 and (cam.cx, cam.cy) == (320.0, 240.0)


@pytest.mark.parametrize("line, message", [
    ("rt_priority = 120", "[service] rt_priority = 120; expected an integer 0-99"),
    ("rt_priority = 1.5", "[service] rt_priority = 1.5; expected an integer 0-99"),
    ("build_nice = -5", "[service] build_nice = -5; expected an integer 0-19"),
    ("frames_rt_priority = 100", "[service] frames_rt_priority = 100; expected an integer 0-99"),
    ("frames_rt_priority = 80", "[service] frames_rt_priority = 80 is not below rt_priority = 80"),
    ("build_idle = 1", "[service] build_idle = 1; expected true or false"),
])
def test_service_priorities(tmp_path, line, message):
    d = config.load(None).service
    assert (d.rt_priority, d.frames_rt_priority, d.build_nice, d.build_idle) == (80, 50, 10, True)
    text = GOOD + "\n[service]\n" + line + "\n" if "[service]" not in GOOD else GOOD.replace("[service]", "[service]\n" + line, 1)
    with pytest.raises(InputError, match=message.replace("[", r"\[").replace("]", r"\]")):
        config.load(write(tmp_path, text))
    ok = config.load(write(tmp_path, text.replace(line, "rt_priority = 0\nbuild_nice = 19")))
    assert (ok.service.rt_priority, ok.service.build_nice) == (0, 19)


def test_near_reading_and_depth_step_reach_the_camera(tmp_path):
    """``near_reading`` and ``depth_step_inv`` of a ``[[camera]]`` reach its Camera (full
    intrinsics and a synthetic source's defaults alike); off by default; a negative step is
    refused with the key named."""
    text = GOOD.replace('noise = { a = 0.0005, b = 0.002 }', 'noise = { a = 0.0005, b = 0.002 }\nnear_reading = true\n'
                        'depth_step_inv = 0.0029')
    text = text.replace('name = "right"\nsource = "synthetic:plane"', 'name = "right"\nsource = "synthetic:plane"\n'
                        'near_reading = true')
    c = config.load(write(tmp_path, text))
    left, right = c.cameras[0].camera, c.cameras[1].camera
    assert left.near_reading and left.depth_step_inv == 0.0029 and left.near_bias == (0.0005, 0.00145)
    assert right.near_reading and right.depth_step_inv == 0.0 and right.near_bias == (0.0005, 0.0)
    plain = config.load(write(tmp_path, GOOD))
    assert not plain.cameras[0].camera.near_reading and plain.cameras[0].camera.near_bias == (0.0, 0.0)
    with pytest.raises(InputError, match="depth_step_inv"):
        config.load(write(tmp_path, GOOD.replace('noise = { a = 0.0005, b = 0.002 }', 'depth_step_inv = -0.01')))
