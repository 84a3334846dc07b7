"""6-DOF teleoperation reaching real-robot interfaces (issue 22): through the whole service, a
turning, grasping master drives a Raven II over ITP (the receiver integrates the rotation
increments and the grasp exactly as the Raven's ``teleopIntoDS1`` does) and a CRTK arm over ROS 2
(the full pose on ``servo_cp``, the jaw on ``jaw/servo_jp``, its angle from ``jaw/measured_js``)."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service.masters import ScriptedMaster
from pointfence.service.replay import simulate
from pointfence.service.robot.base import RobotMode
from pointfence.service.teleop import quat_angle

from service_cases import balloon_config, needs_opencl
from test_robot_raven_itp import RavenReceiver, make, quat_mat
from test_teleop_orientation import qaxis

DT = 1e-3


def quat_of(R):
    """Unit quaternion (w, x, y, z; w >= 0) of rotation matrix ``R``."""
    from pointfence.service.teleop import quat_of_rotation

    return quat_of_rotation(R)


def turning_grasping_master(t_end=0.9):
    t = np.arange(0.0, t_end + DT / 2, DT)
    ang = 0.8 * np.clip(t - 0.1, 0.0, None)
    q = np.array([qaxis([0.3, -0.2, 1.0], a) for a in ang])
    g = np.interp(t, [0.0, 0.1, 0.5, t_end], [0.0, 0.0, 0.5, 0.2])
    return ScriptedMaster(t, np.zeros((t.size, 3)), orientations=q, grasps=g)


@needs_opencl
def test_the_raven_over_itp_receives_the_rotation_increments_and_the_grasp(tmp_path):
    rx = RavenReceiver()
    cfg = balloon_config(tmp_path, arch="III", robot='model = "point-mass"\nx0 = [0.0, 0.0, 0.167]')
    robot = make(rx.port, x0=np.array([0.0, 0.0, 0.167]), workspace_min=[-0.3, -0.3, -0.3],
                 workspace_max=[0.3, 0.3, 0.3])
    try:
        ticks = []
        grab = {k: (lambda s: ticks.append(s.out.copy())) for k in range(1, 900)}
        svc, loop, sources = simulate(cfg, [turning_grasping_master()], 0.9, robots=[robot], events=grab)
        for s in sources:
            s.close()
        last = svc.out
        assert last.coupled[0] and svc.status()["hold"] == []
        rx.wait(robot.sent, timeout=3.0)
        assert rx.problems == [] and rx.counts["malformed"] == 0 and rx.counts["checksum"] == 0
        # the Raven's integrated orientation: the one at engage (identity here) turned by the increments
        R_raven = rx.R
        q_raven = quat_of(R_raven)
        turned = quat_angle(last.orientation[0], ticks[0].orientation[0])
        assert turned > 0.5                                          # 0.64 rad in 0.8 s
        assert quat_angle(q_raven, last.orientation[0]) < 1e-9       # every increment arrived, exactly
        # the grasp: the jaw command in whole milliradians, as the Raven integrates it
        assert rx.grasp == round(1000 * last.jaw[0]) and rx.grasp > 150
        np.testing.assert_allclose(robot.measured_cp()[:3, :3], quat_mat(*q_raven[[1, 2, 3, 0]]), atol=1e-9)
    finally:
        robot.close()
        rx.close()


# --- CRTK over ROS 2 ---------------------------------------------------------------------------------

def _until(robot, cond, seconds=10.0):
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        robot.step(1e-3)
        if cond():
            return True
        time.sleep(0.002)
    return False


@pytest.fixture(scope="module")
def sim_arm(ros2_env):
    from test_ros2_crtk import start_sim_arm, stop

    proc = start_sim_arm(ros2_env, "PSMJ")
    yield proc
    stop(proc)


def test_a_crtk_arm_gets_the_full_pose_and_the_jaw(sim_arm):
    """servo_cp carries the commanded orientation; with ``jaw = true`` the jaw's setpoint goes out on
    jaw/servo_jp (JointState, one position) while the arm is ENABLED, only once the arm has said
    where its jaw is (jaw/measured_js), and never outside the jaw's range."""
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import JointState

    from pointfence.service.ros2 import crtk_wire as wire
    from pointfence.service.ros2.node import RosNode
    from test_ros2_crtk import crtk

    node = RosNode("pf_test_jaw").start()
    got_jaw, got_cp = [], []
    node.node.create_subscription(JointState, "/PSMJ/jaw/servo_jp", lambda m: got_jaw.append(list(m.position)),
                                  wire.qos_reliable(100))
    node.node.create_subscription(PoseStamped, "/PSMJ/servo_cp", lambda m: got_cp.append(m.pose.orientation),
                                  wire.qos_reliable(100))
    jaw_pub = node.node.create_publisher(JointState, "/PSMJ/jaw/measured_js", wire.qos_reliable(10))
    arm = crtk("PSMJ", jaw=True, jaw_min=0.0, jaw_max=1.2)
    try:
        assert arm.state == RobotMode.ENABLED, arm.fault_reason
        assert arm.jaw_limits == (0.0, 1.2) and math.isnan(arm.measured_jaw())
        T = arm.measured_cp()
        T[:3, :3] = quat_mat(*qaxis([0, 0, 1], 0.3)[[1, 2, 3, 0]]) @ T[:3, :3]

        def publish_jaw():
            m = JointState()
            m.name, m.position = ["jaw"], [0.4]
            jaw_pub.publish(m)
            return arm.measured_jaw() == 0.4

        assert _until(arm, publish_jaw)
        with pytest.raises(InputError, match="jaw_min"):
            arm.servo_jaw(1.3)
        with pytest.raises(InputError):
            arm.servo_jaw(math.nan)
        assert _until(arm, lambda: (arm.servo_cp(T), arm.servo_jaw(0.7))[1] and bool(got_jaw) and bool(got_cp))
        assert _until(arm, lambda: any(j == [0.7] for j in got_jaw))
        o = got_cp[-1]
        want = quat_of(T[:3, :3])
        assert quat_angle([o.w, o.x, o.y, o.z], want) < 1e-9
        arm.hold()                                                  # held: the jaw is not streamed
        _until(arm, lambda: False, 0.1)                             # (what was sent before arrives)
        n = len(got_jaw)
        _until(arm, lambda: False, 0.3)
        assert len(got_jaw) == n and not arm.servo_jaw(0.5)
    finally:
        arm.close()
        node.close()


def test_a_hosted_arm_takes_the_jaw_across_the_robot_process():
    """The robot process (robot/hosted.py): the jaw setpoint crosses the shared block to the
    child's arm (here a Raven II over ITP: the receiver integrates the grasp) and the child's jaw
    comes back as ``measured_jaw``; out of range it is refused on this side, nothing sent."""
    from pointfence.service.robot.hosted import RobotHost

    rx = RavenReceiver()
    host = RobotHost([{"model": "raven2-itp", "address": f"127.0.0.1:{rx.port}", "sync_packets": 3,
                       "x0": [0.0, 0.0, 0.1], "workspace_min": [-0.3, -0.3, -0.3], "workspace_max": [0.3, 0.3, 0.3]}])
    arm = host.robots[0]
    try:
        assert arm.jaw_limits is not None and arm.jaw_limits[0] < 0.3 < arm.jaw_limits[1]
        arm.resume()
        T = arm.measured_cp()

        def go():
            arm.servo_cp(T)
            arm.servo_jaw(0.3)
            return rx.grasp == 300 and arm.measured_jaw() == pytest.approx(0.3)

        assert _until(arm, go, 10.0), (rx.grasp, arm.measured_jaw())
        with pytest.raises(InputError, match="servo_jaw"):
            arm.servo_jaw(5.0)
        assert rx.problems == []
    finally:
        host.close()
        rx.close()
