"""Shared set-ups of the service tests: a small synthetic scene (160x120 camera) on PoCL,
scripted masters, and offline runs on the simulated clock."""
from __future__ import annotations

import textwrap

import numpy as np
import pytest

from pointfence.service import config
from pointfence.service.masters import ScriptedMaster

BALLOON = """
backend = "opencl"
[workspace]
min = [-0.25, -0.25, -0.02]
max = [0.25, 0.25, 0.25]
[fixture]
mode = "fixture"
radius = 0.02
select = {{ kind = "color", lo = [150, 0, 0], hi = [255, 90, 90] }}
[[camera]]
name = "overhead"
source = "{source}"
fx = 143.95
fy = 143.95
cx = 79.5
cy = 59.5
width = 160
height = 120
T_world_cam = [1, 0, 0, 0,  0, -1, 0, 0,  0, 0, -1, 0.6,  0, 0, 0, 1]
options = {{ color = true{options} }}
[teleop]
architecture = "{arch}"
scale = 0.5
max_robot_speed = 0.05
[robot]
{robot}
[service]
max_frame_age_s = 0.3
recover_s = 0.05
force_ramp_s = 0.02
"""
RAVEN = 'model = "raven2"\nmount_tool_down = [0.0, 0.0, 0.25]'
POINT_MASS = 'model = "point-mass"\nx0 = [0.0, 0.0, 0.167]'
#: top of the balloon (radius 6 cm on the table) plus the 2 cm fixture
REGION_TOP = 0.14
START_Z = 0.167


def have_pocl():
    try:
        from pointfence.kernels import get_backend

        get_backend("opencl")
        return True
    except Exception:
        return False


needs_opencl = pytest.mark.skipif(not have_pocl(), reason="the service tests run on the OpenCL backend (PoCL)")


def balloon_config(tmp_path, arch="III", robot=RAVEN, source="synthetic:sphere", options="", extra=""):
    p = tmp_path / "scene.toml"
    p.write_text(textwrap.dedent(BALLOON.format(arch=arch, robot=robot, source=source, options=options)) + extra)
    return config.load(p)


def push(depth_master=0.12, t_start=0.1, t_end=1.1, hold=0.3, clutch=None):
    """A master pushing straight down by ``depth_master`` (master frame; the robot moves half)."""
    t = [0.0, t_start, t_end, t_end + hold]
    p = [[0, 0, 0], [0, 0, 0], [0, 0, -depth_master], [0, 0, -depth_master]]
    return ScriptedMaster(np.array(t), np.array(p, float), clutch)


def steps(a):
    """Per-tick increments' lengths of an (N, 3) series."""
    return np.linalg.norm(np.diff(np.asarray(a), axis=0), axis=1)
