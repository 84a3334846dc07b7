"""Robot self-filter (kernels/selffilter.py): the tool's own points are removed before fixtures,
the rest of the scene stays."""
import numpy as np
import pytest

from pointfence.service.dynamic_scenes import self_filter_ratio
from pointfence.kernels import DepthFrame, InputError
from pointfence.kernels.selffilter import Capsule, SelfFilter, segment_distance
from pointfence.service.robot import make_robot
from pointfence.service.robot.raven2 import Raven2
from pointfence.service.robot.tool import ToolModel, tool_capsules, tool_model_for
from pointfence.service.sources import SyntheticSource, default_camera
from pointfence.service.sources.scenes import make_scene
from pointfence.service.sources.toolscene import ToolInScene


def test_filter_removes_exactly_the_tool_pixels():
    """Every pixel that sees the tool (true geometry, with depth noise) is dropped, and only
    pixels within the margin of the tool are: the table around and under it stays."""
    cam = default_camera("cam0", eye=(0.2, 0.1, 0.5), width=160, height=120)
    robot = make_robot("raven2", T_world_base=Raven2.mount_tool_down((0.0, 0.0, 0.12)))
    caps = tool_capsules(robot)
    scene = ToolInScene(base=make_scene("plane"), capsules=caps)
    src = SyntheticSource(scene, cam, quantize=False, dropout=0.0, shadows=False)
    depth, _, _ = src.render(0.0, np.random.default_rng(0))
    frame = DepthFrame("cam0", depth, 0.0)
    f = SelfFilter([cam], margin=0.003)
    [out] = f.apply([frame], caps)
    z_true = src.true_depth(0.0).reshape(-1)
    pts = src._origin + z_true[:, None] * src._dirs
    on_tool = scene.tool_distance(pts) < 1e-6
    dropped = (depth.reshape(-1) != 0) & (out.depth.reshape(-1) == 0)
    assert on_tool.sum() > 100  # the tool is in view
    assert not np.any((out.depth.reshape(-1) != 0) & on_tool)  # no tool pixel survives
    assert f.removed == dropped.sum() == np.count_nonzero(dropped & on_tool) + np.count_nonzero(dropped & ~on_tool)
    near = scene.tool_distance(pts) < 0.003 + 0.004  # margin + a few sigma of depth noise
    assert np.all(near[dropped])  # nothing far from the tool is dropped
    assert frame.depth is depth and np.array_equal(frame.depth, depth)  # the input frame is untouched


def test_robot_never_fences_itself_and_the_table_stays_protected():
    """Selection box over the whole work area: without the filter the instrument's own points are
    protected (false fixtures) and a fixture proxy at the tip is buried in them; with the filter
    none are left, no table point is lost, and the tip moves freely."""
    r = self_filter_ratio()
    print(f"\nself-filter: {r}")
    assert r["false_fixture_points_without"] > 50 and r["tips_fenced_without"] == 3
    assert r["false_fixture_points_with"] == 0 and r["self_filter_false_fixture_ratio"] == 0.0
    assert r["tips_fenced_with"] == 0
    assert r["table_points_lost_fraction"] < 0.01


def test_capsules_of_both_robot_models():
    robot = make_robot("raven2", T_world_base=Raven2.mount_tool_down((0.0, 0.0, 0.15)))
    shaft, wrist = tool_capsules(robot)
    tip = robot.measured_cp()[:3, 3]
    assert segment_distance(tip[None], wrist.a, wrist.b)[0] < 1e-9
    assert segment_distance(np.zeros((1, 3)) + [0, 0, 0.15], shaft.a, shaft.b)[0] < 1e-9  # through the RCM
    pm = make_robot("point-mass")
    assert tool_capsules(pm, model=ToolModel(shaft_length=0.1)) == []     # S5: no assumed shaft axis
    [c] = tool_capsules(pm, model=ToolModel(parts=(((0, 0, 0), (0, 0, 0.1), 0.004),)))
    assert np.allclose(np.subtract(c.b, c.a), [0, 0, 0.1]) and c.radius == 0.004
    with pytest.raises(InputError, match="radius"):
        Capsule((0, 0, 0), (0, 0, 1), float("nan"))
    with pytest.raises(InputError, match="unknown camera"):
        SelfFilter([default_camera("a", width=16, height=12)]).mask(
            DepthFrame("b", np.zeros((12, 16), np.uint16), 0.0), [c])


def test_a_robot_without_a_known_tool_gets_no_self_filter_and_says_why():
    """S5: the point mass has no tool until [robot.tool] parts gives one; the Raven II has its
    instrument. An explicit self_filter = true without a tool is a configuration error."""
    pm, rv = make_robot("point-mass"), make_robot("raven2")
    model, why = tool_model_for(pm, None)
    assert model is None and "[robot.tool] parts" in why
    model, _ = tool_model_for(pm, {"parts": [[0, 0, 0, 0, 0, 0.02, 0.004]]})
    assert model is not None and len(model.parts) == 1
    model, _ = tool_model_for(rv, None)
    assert model == ToolModel()
    for bad, msg in (({"parts": [[0, 0, 0, 0, 0, 0.02]]}, "parts\\[0\\]"), ({"parts": [[0, 0, 0, 0, 0, 0.02, 0.5]]}, "radius"),
                     ({"shaft_radius": float("nan")}, "shaft_radius"), ({"axis": "z"}, "unknown key")):
        with pytest.raises(InputError, match=msg):
            tool_model_for(pm, bad)


def _mask_every_pixel(cam, frame, capsules, margin):
    """The self-filter's test applied to every pixel (no image window): the reference."""
    xy = cam.ray_table().reshape(-1, 2).astype(np.float64)
    rays = np.column_stack([xy, np.ones(len(xy))])
    T = cam.T_world_cam
    R, t = T[:3, :3], T[:3, 3]
    z = frame.depth.reshape(-1).astype(np.float64) * cam.depth_scale
    p = rays * z[:, None]
    out = np.zeros(len(z), bool)
    for c in capsules:
        a, b = R.T @ (np.asarray(c.a) - t), R.T @ (np.asarray(c.b) - t)
        out |= (z > 0) & (segment_distance(p, a, b) <= c.radius + margin)
    return out.reshape(frame.depth.shape)


@pytest.mark.parametrize("dist", [(0.0,) * 5, (-0.28, 0.09, 0.001, -0.002, 0.0)])
def test_image_window_drops_exactly_what_a_test_of_every_pixel_drops(dist):
    """Random capsules (in view, at the image border, partly behind the camera, out of view) on a
    random depth image: the windowed filter's mask equals the every-pixel test's."""
    cam = default_camera("cam0", eye=(0.0, 0.0, 0.6), width=160, height=120, dist=dist)
    rng = np.random.default_rng(11)
    depth = rng.integers(300, 900, (120, 160)).astype(np.uint16)
    depth[rng.random((120, 160)) < 0.1] = 0
    frame = DepthFrame("cam0", depth, 0.0)
    f = SelfFilter([cam], margin=0.003)
    hits = 0
    for _ in range(60):
        a = rng.uniform([-0.4, -0.3, -0.2], [0.4, 0.3, 0.7])
        b = a + rng.normal(0.0, 0.08, 3)
        caps = [Capsule(tuple(a), tuple(b), float(rng.uniform(0.002, 0.05)))]
        got = f.mask(frame, caps)
        want = _mask_every_pixel(cam, frame, caps, 0.003)
        assert np.array_equal(got, want)
        hits += int(want.any())
    assert hits > 10   # the capsules did cut into the depth image


def test_compiled_pixel_test_drops_what_numpy_drops_on_a_real_frame(shared_data):
    """A real Kinect frame (7-Scenes kitchen, its recorded pose) and random capsules around a
    surface point it sees, some cutting into the surface, some in front of it: the compiled
    test's mask equals the every-pixel NumPy test's, pixel for pixel."""
    from pointfence.service import dynamic_real_rig as drr

    R = drr.rig(1, shared_data)
    frame = R.a.frame(0, 0.0)
    f = SelfFilter([R.a.camera], margin=0.003)
    rng = np.random.default_rng(5)
    hits = 0
    for _ in range(40):
        tip = R.site.point + R.site.view * rng.uniform(-0.02, 0.05) + rng.normal(0.0, 0.03, 3)
        axis = R.site.view + rng.normal(0.0, 0.3, 3)
        caps = [Capsule(tuple(tip), tuple(tip + 0.15 * axis / np.linalg.norm(axis)), float(rng.uniform(0.003, 0.02)))]
        got = f.mask(frame, caps)
        want = _mask_every_pixel(R.a.camera, frame, caps, 0.003)
        assert np.array_equal(got, want)
        hits += int(want.sum() > 20)
    assert hits > 10   # the capsules did cut into the real surface
