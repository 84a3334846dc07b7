"""The Cartesian point-mass robot: PD tracking, force and velocity saturation, workspace."""
import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service.robot import PointMass, RobotMode, make_robot

DT = 1e-3


def test_tracks_a_5cm_per_s_line_and_settles():
    r = make_robot("point-mass", x0=[0.0, 0.0, 0.1])
    assert isinstance(r, PointMass)
    p0 = r.setpoint_cp()[:3, 3].copy()
    d = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    during = []
    for k in range(1, 401):
        assert r.servo_cp(p0 + d * 0.05 * k * DT)
        r.step(DT)
        during.append(np.linalg.norm(r.measured_cp()[:3, 3] - r.setpoint_cp()[:3, 3]))
    during = np.array(during)
    lag = (r.kd + r.damping) / r.kp * 0.05          # PD lag of a ramp: (Kd + c) / Kp * v
    # sampled after the tick's semi-implicit update: one tick (v dt) less than the continuous lag
    np.testing.assert_allclose(during[100:], lag - 0.05 * DT, rtol=0.01)
    assert 0.3e-3 < lag < 1.2e-3
    after = []
    for _ in range(100):
        r.step(DT)
        after.append(np.linalg.norm(r.measured_cp()[:3, 3] - r.setpoint_cp()[:3, 3]))
    assert max(after[50:]) < 20e-6


def test_force_and_velocity_saturate_on_their_norms():
    r = make_robot("point-mass", max_force=5.0, max_velocity=0.2, fault_error=0.0)
    target = r.setpoint_cp()[:3, 3] + [0.03, -0.04, 0.0]     # 5 cm away
    assert r.servo_cp(target)
    forces, speeds = [], []
    for _ in range(1000):
        r.step(DT)
        js = r.measured_js()
        forces.append(np.linalg.norm(js.effort))
        speeds.append(np.linalg.norm(js.velocity))
    assert max(forces) == pytest.approx(5.0, rel=1e-9)        # saturated, never beyond
    assert max(speeds) <= 0.2 + 1e-12
    assert max(speeds) == pytest.approx(0.2, rel=1e-9)
    np.testing.assert_allclose(r.measured_cp()[:3, 3], target, atol=1e-5)
    # the saturated force keeps the direction of the PD force
    r2 = make_robot("point-mass", max_force=5.0, fault_error=0.0)
    r2.servo_cp(r2.setpoint_cp()[:3, 3] + [0.03, -0.04, 0.0])
    r2.step(DT)
    f = r2.measured_js().effort
    np.testing.assert_allclose(f / np.linalg.norm(f), [0.6, -0.8, 0.0], atol=1e-12)


def test_workspace_is_the_joint_range():
    r = make_robot("point-mass", workspace_min=[-0.1, -0.1, 0.0], workspace_max=[0.1, 0.1, 0.2])
    lo, hi = r.joint_limits
    np.testing.assert_array_equal(lo, [-0.1, -0.1, 0.0])
    np.testing.assert_array_equal(hi, [0.1, 0.1, 0.2])
    np.testing.assert_allclose(r.measured_cp()[:3, 3], [0.0, 0.0, 0.1])
    with pytest.raises(InputError, match="axis z"):
        r.servo_cp([0.0, 0.0, 0.25])
    with pytest.raises(InputError, match="'y' = -0.3"):
        r.servo_jp([0.0, -0.3, 0.1])
    np.testing.assert_allclose(r.setpoint_cp()[:3, 3], [0.0, 0.0, 0.1])


def test_following_error_fault():
    r = make_robot("point-mass")                    # fault_error 5 cm by default
    assert r.servo_cp(r.setpoint_cp()[:3, 3] + [0.08, 0.0, 0.0])
    r.step(DT)
    assert r.state is RobotMode.FAULT and "'x'" in r.fault_reason


def test_bad_options_raise():
    for kw in ({"mass": 0.0}, {"mass": -1.0}, {"max_force": float("nan")}, {"damping": True},
               {"workspace_min": [0, 0, 0], "workspace_max": [1, 1, 0]}, {"x0": [2.0, 0.0, 0.0]}):
        with pytest.raises(InputError):
            make_robot("point-mass", **kw)
