"""Simulated Raven II dynamics: PID tracking at 1 kHz, settling, joint limits, saturation, faults."""
import tracemalloc

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service.robot import JOINT_HOME, JOINT_LOWER, JOINT_UPPER, RobotMode, make_robot

DT = 1e-3


def _tip(r):
    return r.measured_cp()[:3, 3]


def _track_line(r, direction, speed=0.05, duration=0.4, settle=0.1):
    """Servo the tip along a straight line at ``speed``; tip error during and after the motion."""
    p0 = r.setpoint_cp()[:3, 3].copy()
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    during, after = [], []
    for k in range(1, int(round(duration / DT)) + 1):
        assert r.servo_cp(p0 + d * speed * k * DT)
        r.step(DT)
        during.append(np.linalg.norm(_tip(r) - r.setpoint_cp()[:3, 3]))
    for _ in range(int(round(settle / DT))):
        r.step(DT)
        after.append(np.linalg.norm(_tip(r) - r.setpoint_cp()[:3, 3]))
    return np.array(during), np.array(after)


@pytest.fixture
def raven():
    # mounted with the tool pointing down, RCM 15 cm above the world origin (as a demo would)
    r = make_robot("raven2", mount_tool_down=[0.0, 0.0, 0.15])
    for _ in range(200):
        r.step(DT)
    return r


def test_rests_at_home_under_gravity(raven):
    # gravity is on by default, 90 % compensated; the integral removes the residual
    for _ in range(300):
        raven.step(DT)
    assert np.linalg.norm(_tip(raven) - raven.setpoint_cp()[:3, 3]) < 1e-5
    np.testing.assert_allclose(raven.measured_js().position, JOINT_HOME, atol=1e-4)
    assert np.linalg.norm(raven.gravity_torque()[:3]) > 0.0


@pytest.mark.parametrize("direction", [(1, 0, 0), (0, 1, 0), (0, 0, -1), (1, -1, 1)])
def test_tracks_a_5cm_per_s_line_with_a_realistic_error_and_settles(raven, direction):
    during, after = _track_line(raven, direction)
    steady = during[100:]                     # after the first 0.1 s
    # a real PID-servoed arm lags: a few tenths of a mm, never more than ~1 mm
    assert 0.1e-3 < steady.mean() < 1.0e-3
    assert during.max() < 1.2e-3
    # stop: within tens of ms the error falls below 50 um and stays there
    settled = np.nonzero(after > 50e-6)[0]
    settle_ticks = 0 if settled.size == 0 else settled[-1] + 1
    assert settle_ticks * DT < 0.06
    assert after[-1] < 10e-6


def test_hold_freezes_the_setpoint_while_moving(raven):
    p0 = raven.setpoint_cp()[:3, 3].copy()
    for k in range(1, 101):
        raven.servo_cp(p0 + [0.05 * k * DT, 0, 0])
        raven.step(DT)
    lagging = raven.setpoint_cp()[:3, 3].copy()
    at_hold = raven.measured_cp()[:3, 3].copy()
    assert np.linalg.norm(lagging - at_hold) > 1e-5           # moving at 5 cm/s: behind its command
    raven.hold()
    held = raven.setpoint_cp()
    assert raven.state is RobotMode.HOLDING
    # a stop where the arm is (SAFETY.md S3), not the end of the last command
    np.testing.assert_allclose(held[:3, 3], at_hold, atol=1e-9)
    for k in range(101, 301):                 # the loop keeps streaming: ignored
        assert raven.servo_cp(p0 + [0.05 * k * DT, 0, 0]) is False
        raven.step(DT)
    np.testing.assert_array_equal(raven.setpoint_cp(), held)
    assert np.linalg.norm(_tip(raven) - held[:3, 3]) < 20e-6      # settled on the frozen setpoint
    tip_before = _tip(raven).copy()
    raven.resume()                            # resuming moves nothing
    for _ in range(20):
        raven.step(DT)
    assert np.linalg.norm(_tip(raven) - tip_before) < 1e-6
    assert raven.servo_cp(held[:3, 3] + [0, 0, 1e-5])


def test_joint_limits_are_respected():
    r = make_robot("raven2", gravity=False)
    lo, hi = r.joint_limits
    np.testing.assert_array_equal(lo, JOINT_LOWER)
    np.testing.assert_array_equal(hi, JOINT_UPPER)
    # walk the shoulder onto its upper limit at full speed: it stops there, never beyond
    q = r.measured_js().position
    target = q.copy()
    target[0] = hi[0]
    seen = []
    for k in range(1, 2001):
        cmd = q + (target - q) * min(1.0, k / 500)
        r.servo_jp(cmd)
        r.step(DT)
        seen.append(r.measured_js().position)
    seen = np.array(seen)
    assert np.all(seen >= lo - 1e-12) and np.all(seen <= hi + 1e-12)
    assert seen[-1, 0] == pytest.approx(hi[0], abs=1e-5)
    # one step past the limit is refused and changes nothing
    beyond = target.copy()
    beyond[0] = hi[0] + 1e-3
    with pytest.raises(InputError, match="'shoulder'"):
        r.servo_jp(beyond)
    np.testing.assert_array_equal(r.setpoint_js().position, target)


def test_torque_and_velocity_saturate():
    r = make_robot("raven2", gravity=False)
    q = r.measured_js().position
    jump = q + [0.25, -0.25, 0.04, 0.8, 0.8, 0.8]       # big, but inside the fault thresholds
    assert r.servo_jp(jump)
    tau_max, v_max = r.max_torque, r.max_velocity
    for _ in range(1500):
        r.step(DT)
        js = r.measured_js()
        assert np.all(np.abs(js.effort) <= tau_max + 1e-12)
        assert np.all(np.abs(js.velocity) <= v_max + 1e-12)
    assert r.state is RobotMode.ENABLED
    np.testing.assert_allclose(r.measured_js().position, jump, atol=1e-4)


def test_following_error_faults_and_enable_does_not_jump():
    r = make_robot("raven2", gravity=False)
    q = r.measured_js().position
    assert r.servo_jp(q + [0.0, 0.0, 0.0, 0.0, 0.0, 1.2])   # 1.2 rad jump: more than fault_error 1.0
    r.step(DT)
    assert r.state is RobotMode.FAULT
    assert "grasper_yaw" in r.fault_reason
    before = r.measured_js().position
    assert r.servo_cp(r.measured_cp()) is False              # ignored while faulted
    for _ in range(10):
        r.step(DT)
    np.testing.assert_array_equal(r.measured_js().position, before)   # brakes on
    r.enable()
    assert r.state is RobotMode.ENABLED and r.fault_reason is None
    np.testing.assert_array_equal(r.setpoint_js().position, before)   # re-seated: no jump
    for _ in range(50):
        r.step(DT)
    np.testing.assert_allclose(r.measured_js().position, before, atol=1e-6)


def test_long_dt_runs_several_control_periods():
    a = make_robot("raven2")
    b = make_robot("raven2")
    for r in (a, b):
        r.servo_cp(r.setpoint_cp()[:3, 3] + [0.0005, 0, 0])
    for _ in range(10):
        a.step(DT)
    b.step(10 * DT)
    np.testing.assert_allclose(a.measured_js().position, b.measured_js().position, atol=1e-12)
    assert a.t == pytest.approx(b.t)
    for bad in (0.0, -1e-3, float("nan"), float("inf")):
        with pytest.raises(InputError, match="dt"):
            a.step(bad)


def test_step_allocates_nothing_per_tick():
    """The tick works on preallocated state: memory does not grow over many steps."""
    r = make_robot("raven2")
    r.servo_cp(r.setpoint_cp()[:3, 3] + [0.0002, 0, 0])
    for _ in range(10):
        r.step(DT)
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    for _ in range(2000):
        r.step(DT)
    grown = tracemalloc.get_traced_memory()[0] - base
    tracemalloc.stop()
    assert grown < 512
