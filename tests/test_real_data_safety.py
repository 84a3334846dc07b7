"""Held-out real data (issue 18, failure 1; SAFETY.md S5): a real Kinect frame of PCL's grabber
sequence, one camera whose frame is the world frame (z points away from the camera), a
point-mass robot, a 1 cm fixture around every point, and a master pushed 3 cm past the fixture.

With the embedded defaults the point mass has no tool model, so nothing is filtered out of the
frame (the status says why). Before the fix it was given an assumed shaft along +z of its tip
frame: the capsule lay across the surface in front of the tool and the self-filter cut a hole
there (proxy 3.9 mm and robot 3.5 mm inside the region in architecture III here)."""
import tomllib

import numpy as np
import pytest

from pointfence.kernels import get_backend
from pointfence.service import config as config_mod
from pointfence.service.masters import ScriptedMaster
from pointfence.service.measures import SnapshotRegion
from pointfence.service.replay import simulate
from pointfence.service.sources import open_source

from service_cases import needs_opencl

pytestmark = needs_opencl
FRAME = "frame_20121214T142255.814212"


@pytest.fixture
def kinect(shared_data, tmp_path):
    """A folder with the sequence's first depth frame (and its camera xml): one static frame."""
    seq = shared_data / "pcl_kinect_grabber_seq"
    d = tmp_path / "kinect1"
    d.mkdir()
    (d / f"{FRAME}_depth.tiff").symlink_to(seq / "tiff" / f"{FRAME}_depth.tiff")
    (d / f"{FRAME}.xml").symlink_to(seq / "pclzf" / f"{FRAME}.xml")
    return d


def push_run(folder, arch, extra=""):
    """The run of failure 1: returns (proxy, robot) penetration of the true region (m), status."""
    src = open_source(f"recorded:{folder}", loop=False)
    frame, cam = src.read(), src.camera
    src.close()
    u, v = 320, 240
    z = frame.depth[v, u] * cam.depth_scale
    P = np.array([(u - cam.cx) * z / cam.fx, (v - cam.cy) * z / cam.fy, z])   # the surface under the tool
    start = P - [0.0, 0.0, 0.03]                                                # 3 cm in front of it
    text = f'''
[workspace]
min = [{P[0] - 0.2}, {P[1] - 0.2}, {P[2] - 0.2}]
max = [{P[0] + 0.2}, {P[1] + 0.2}, {P[2] + 0.1}]
[fixture]
radius = 0.01
select = {{ kind = "all" }}
[[camera]]
name = "kinect"
source = "recorded:{folder}"
[teleop]
architecture = "{arch}"
scale = 1.0
[robot]
model = "point-mass"
x0 = [{start[0]}, {start[1]}, {start[2]}]
workspace_max = [1.5, 1.5, 1.5]
{extra}
'''
    cfg = config_mod.parse(tomllib.loads(text), "kinect push")
    push = 0.03 - 0.01 + 0.03      # to the fixture's edge, then 3 cm past it
    master = ScriptedMaster([0, 0.2, 1.5, 3.0], [[0, 0, 0], [0, 0, 0], [0, 0, push], [0, 0, push]])
    svc, loop, sources = simulate(cfg, [master], 3.0)
    for s in sources:
        s.close()
    truth = get_backend("numpy").pipeline([cam], cfg.pipeline)   # the unfiltered frame: the true region
    truth.ingest([frame])
    region = SnapshotRegion(truth.host_snapshot())
    rec = svc.recorder
    proxy, robot = rec.ticks()[:, 7:10], rec.robots[: rec.count, 0, :3]
    return max(0.0, -region(proxy).min()), max(0.0, -region(robot).min()), svc.status()


def test_default_configuration_keeps_the_robot_out_of_a_real_surface(kinect):
    proxy_pen, robot_pen, status = push_run(kinect, "III")
    assert proxy_pen <= 0.0005 and robot_pen <= 0.001, (proxy_pen, robot_pen)
    assert status["self_filter"]["on"] is False and "tool model" in status["self_filter"]["why"]


def test_architecture_i_still_lets_it_in(kinect):
    proxy_pen, robot_pen, _ = push_run(kinect, "I")
    assert robot_pen > 0.009             # the soft fixture lets the robot through the 1 cm region


def test_an_explicit_self_filter_without_a_tool_is_an_error(kinect):
    from pointfence.kernels.errors import InputError

    with pytest.raises(InputError, match=r"\[robot.tool\] parts"):
        push_run(kinect, "III", extra="[service]\nself_filter = true")
