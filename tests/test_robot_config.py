"""make_robot and the [robot] table of the scene configuration."""
import numpy as np
import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from pointfence.kernels.errors import InputError
from pointfence.service.robot import PointMass, Raven2, make_robot, model_options, robot_from_config


def test_default_is_the_raven2():
    r = robot_from_config({})
    assert isinstance(r, Raven2) and r.arm == "right"
    assert isinstance(robot_from_config({"model": "point-mass"}), PointMass)


def test_a_full_toml_table():
    doc = tomllib.loads("""
[robot]
model = "raven2"
arm = "left"
q0 = [0.6, 1.4, 0.38, 0.1, 0.0, 0.0]
mount_tool_down = [0.0, 0.0, 0.15]
gravity = true
tool_mass = 0.25
gravity_compensation = 1.0
bandwidth = [100, 100, 120, 150, 150, 150]
max_velocity = [2, 2, 0.2, 8, 8, 8]
workspace_min = [-0.1, -0.1, -0.05]
workspace_max = [0.1, 0.1, 0.2]
""")
    r = robot_from_config(doc["robot"])
    assert isinstance(r, Raven2) and r.arm == "left"
    np.testing.assert_allclose(r.measured_js().position, [0.6, 1.4, 0.38, 0.1, 0.0, 0.0])
    np.testing.assert_allclose(r.T_world_base[:3, 3], [0.0, 0.0, 0.15])
    np.testing.assert_allclose(r.max_velocity, [2, 2, 0.2, 8, 8, 8])
    np.testing.assert_allclose(r.kp, r.inertia * np.array([100, 100, 120, 150, 150, 150.0]) ** 2)
    pm = robot_from_config(tomllib.loads("""
[robot]
model = "point-mass"
mass = 1
max_force = 4.0
x0 = [0.0, 0.0, 0.1]
T_world_base = [1,0,0,0.5, 0,1,0,0, 0,0,1,0, 0,0,0,1]
""")["robot"])
    np.testing.assert_allclose(pm.measured_cp()[:3, 3], [0.5, 0.0, 0.1])
    assert pm.max_force == 4.0 and pm.mass == 1.0


def test_mount_tool_down_points_the_shaft_down():
    r = make_robot("raven2", mount_tool_down=[0.02, -0.01, 0.2])
    tip = r.measured_cp()[:3, 3]
    wrist, _ = r.kin.wrist_point(r.measured_js().position)
    wrist_world = r.T_world_base @ np.r_[wrist, 1.0]
    np.testing.assert_allclose(tip[:2], [0.02, -0.01], atol=1e-9)   # straight below the RCM
    np.testing.assert_allclose(wrist_world[:2], [0.02, -0.01], atol=1e-9)
    assert tip[2] < wrist_world[2] < 0.2


@pytest.mark.parametrize("table, fragment", [
    ({"model": "raven2", "tool_mas": 1.0}, "unknown key 'tool_mas'; did you mean 'tool_mass'?"),
    ({"model": "raven2", "bandwith": [1] * 6}, "did you mean 'bandwidth'?"),
    ({"model": "point-mass", "arm": "left"}, "'arm' is an option of model 'raven2'"),
    ({"model": "point-mass", "max_forse": 3}, "did you mean 'max_force'?"),
    ({"model": "raven"}, "did you mean 'raven2'?"),
    ({"model": "pointmass"}, "did you mean 'point-mass'?"),
    ({"model": 3}, "model = 3"),
    ({"arm": "middle"}, "arm = 'middle'"),
    ({"gravity": "yes"}, "gravity = 'yes'"),
    ({"q0": [0, 0, 0, 0, 0, 0]}, "'elbow'"),
    ({"inertia": [1, 1, 1]}, "inertia has shape (3,)"),
    ({"T_world_base": [1, 0, 0]}, "T_world_base has 3 numbers"),
    ({"T_world_base": [2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}, "not orthonormal"),
    ({"mount_tool_down": [0, 0, 0.1], "T_world_base": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]},
     "not both"),
    ({"joint_upper": [3, 3, 3, 3, 3, 3]}, "exceed the Raven II"),
    ({"model": "point-mass", "mass": -2}, "mass = -2"),
])
def test_bad_tables_raise_with_a_clear_message(table, fragment):
    with pytest.raises(InputError) as info:
        robot_from_config(table)
    assert fragment in str(info.value)
    assert str(info.value).startswith("[robot]") or "model" in str(info.value)


def test_make_robot_rejects_unknown_options():
    with pytest.raises(InputError, match="did you mean 'max_velocity'"):
        make_robot("raven2", max_velocty=[1] * 6)
    assert "mount_tool_down" in model_options("raven2")
    assert "max_force" in model_options("point-mass")
    with pytest.raises(InputError):
        robot_from_config(["raven2"])
