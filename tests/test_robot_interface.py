"""The CRTK-style robot contract, for every model: bad commands raise and move nothing, hold()
freezes, state structs are copies."""
import math

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service.robot import JointState, Robot, RobotMode, RobotState, make_robot

DT = 1e-3
MODELS = ["raven2", "point-mass"]


@pytest.fixture(params=MODELS)
def robot(request):
    r = make_robot(request.param)
    for _ in range(100):
        r.step(DT)
    return r


def _rot(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _snapshot(r):
    return r.setpoint_cp(), r.setpoint_js().position, r.measured_js().position


def _bad_commands(r):
    """(description, command, method, expected fragment of the message)"""
    T = r.setpoint_cp()
    p = T[:3, 3]
    nan_p = p.copy()
    nan_p[1] = np.nan
    nan_T = T.copy()
    nan_T[0, 0] = np.nan
    inf_T = T.copy()
    inf_T[2, 3] = np.inf
    scaled = T.copy()
    scaled[:3, :3] *= 1.01
    sheared = T.copy()
    sheared[0, 1] += 0.05
    mirrored = T.copy()
    mirrored[:3, 0] *= -1.0
    bottom = T.copy()
    bottom[3] = (0.0, 0.0, 0.1, 1.0)
    far = p + [2.0, 0.0, 0.0]
    far_T = T.copy()
    far_T[:3, 3] = far
    q = r.setpoint_js().position
    q_nan = q.copy()
    q_nan[0] = np.nan
    lo, hi = r.joint_limits
    q_out = q.copy()
    q_out[-1] = hi[-1] + 0.01
    return [
        ("NaN position", nan_p, "servo_cp", "not finite"),
        ("NaN in pose", nan_T, "servo_cp", "not finite"),
        ("inf in pose", inf_T, "servo_cp", "not finite"),
        ("scaled rotation", scaled, "servo_cp", "not orthonormal"),
        ("sheared rotation", sheared, "servo_cp", "not orthonormal"),
        ("reflection", mirrored, "servo_cp", "determinant"),
        ("bad last row", bottom, "servo_cp", "last row"),
        ("wrong shape", np.zeros(5), "servo_cp", "shape"),
        ("not numbers", "home", "servo_cp", "home"),
        ("out of reach position", far, "servo_cp", "outside"),
        ("out of reach pose", far_T, "servo_cp", "outside"),
        ("NaN joints", q_nan, "servo_jp", "not finite"),
        ("joints beyond limits", q_out, "servo_jp", "outside its limits"),
        ("too few joints", q[:2], "servo_jp", "shape"),
    ]


def test_bad_commands_raise_and_never_move_the_robot(robot):
    # move a little first so the robot has a non-trivial setpoint and is in motion
    p0 = robot.setpoint_cp()[:3, 3]
    robot.servo_cp(p0 + [0.0, 0.0, 0.0005])
    for _ in range(5):
        robot.step(DT)
    reference = make_robot(robot.model)            # twin that receives only the good commands
    reference.reset(robot.measured_js().position)
    reference._dq[:] = robot._dq
    reference._q_d[:] = robot._q_d
    reference._T_d[...] = robot._T_d
    if hasattr(robot, "_int"):
        reference._int[:] = robot._int
        reference._qd_prev[:] = robot._qd_prev
    for desc, cmd, method, fragment in _bad_commands(robot):
        before = _snapshot(robot)
        with pytest.raises(InputError) as info:
            getattr(robot, method)(cmd)
        assert fragment in str(info.value), (desc, str(info.value))
        after = _snapshot(robot)
        for a, b in zip(before, after):
            np.testing.assert_array_equal(a, b, err_msg=desc)
        robot.step(DT)
        reference.step(DT)
        # the robot moved exactly as if the bad command had never been sent
        np.testing.assert_allclose(robot.measured_js().position, reference.measured_js().position, atol=1e-15,
                                   err_msg=desc)
    assert robot.rejected_commands == len(_bad_commands(robot))
    assert robot.state is RobotMode.ENABLED
    assert robot.last_error


def test_messages_name_the_value(robot):
    p = robot.setpoint_cp()[:3, 3].copy()
    p[2] = np.nan
    with pytest.raises(InputError, match=r"nan"):
        robot.servo_cp(p)
    q = robot.setpoint_js().position
    q[0] = 7.5
    with pytest.raises(InputError, match=rf"{robot.joint_names[0]!r} = 7.5"):
        robot.servo_jp(q)


def test_hold_freezes_and_resume_continues(robot):
    T = robot.setpoint_cp()
    robot.hold()
    held = robot.setpoint_cp()                       # where the arm is (at rest: on its setpoint)
    np.testing.assert_allclose(held[:3, 3], robot.measured_cp()[:3, 3], atol=1e-9)
    np.testing.assert_allclose(held[:3, 3], T[:3, 3], atol=2e-5)
    robot.hold()                                     # idempotent
    assert robot.state is RobotMode.HOLDING
    assert robot.servo_cp(T[:3, 3] + [0.001, 0, 0]) is False
    assert robot.servo_jp(robot.setpoint_js().position) is False
    assert robot.ignored_commands == 2
    for _ in range(100):
        robot.step(DT)
    np.testing.assert_array_equal(robot.setpoint_cp(), held)
    np.testing.assert_allclose(robot.measured_cp()[:3, 3], T[:3, 3], atol=2e-5)
    # a bad command while holding still raises (and still changes nothing)
    with pytest.raises(InputError):
        robot.servo_cp([np.nan, 0, 0])
    robot.resume()
    assert robot.state is RobotMode.ENABLED
    assert robot.servo_cp(T[:3, 3] + [0.0001, 0, 0]) is True


def test_position_command_keeps_the_orientation(robot):
    R = robot.setpoint_cp()[:3, :3].copy()
    p = robot.setpoint_cp()[:3, 3] + [0.001, -0.001, 0.0005]
    assert robot.servo_cp(p)
    np.testing.assert_allclose(robot.setpoint_cp()[:3, :3], R, atol=1e-12)
    np.testing.assert_allclose(robot.setpoint_cp()[:3, 3], p, atol=1e-12)
    for _ in range(200):
        robot.step(DT)
    np.testing.assert_allclose(robot.measured_cp()[:3, 3], p, atol=2e-5)
    np.testing.assert_allclose(robot.measured_cp()[:3, :3], R, atol=1e-3)


def test_pose_command_sets_the_orientation(robot):
    T = robot.setpoint_cp()
    T[:3, :3] = T[:3, :3] @ _rot([1, 1, 0], 0.05)
    T[:3, 3] += [0.0, 0.0005, 0.0]
    assert robot.servo_cp(T)
    for _ in range(300):
        robot.step(DT)
    np.testing.assert_allclose(robot.measured_cp(), T, atol=5e-5)


def test_servo_jp_moves_the_joints(robot):
    q = robot.setpoint_js().position
    q[0] += 0.001
    assert robot.servo_jp(q)
    np.testing.assert_allclose(robot.setpoint_cp(), robot.forward_kinematics(q), atol=1e-12)
    for _ in range(300):
        robot.step(DT)
    np.testing.assert_allclose(robot.measured_js().position, q, atol=2e-5)


def test_state_structs_are_plain_copies(robot):
    assert isinstance(robot, Robot)
    js = robot.measured_js()
    assert isinstance(js, JointState)
    assert js.name == robot.joint_names
    for a in (js.position, js.velocity, js.effort):
        assert a.shape == (robot.dof,)
    js.position[:] = 99.0
    assert not np.any(robot.measured_js().position == 99.0)
    T = robot.measured_cp()
    T[:] = 0.0
    assert robot.measured_cp()[3, 3] == 1.0
    out = np.empty((4, 4))
    assert robot.measured_cp(out=out) is out
    st = robot.read_state()
    assert isinstance(st, RobotState)
    assert st.mode is RobotMode.ENABLED and st.t == pytest.approx(robot.t)
    np.testing.assert_array_equal(st.setpoint_jp, robot.setpoint_js().position)
    assert st.measured_cp.shape == (4, 4)
    assert RobotMode.ENABLED == 0 and RobotMode.HOLDING == 1 and RobotMode.FAULT == 2


def test_ik_agrees_with_fk(robot):
    q = robot.measured_js().position
    T = robot.forward_kinematics(q)
    np.testing.assert_allclose(robot.inverse_kinematics(T, seed=q), q, atol=1e-9)


def test_explicit_fault_and_enable(robot):
    robot.fault("e-stop pressed")
    assert robot.state is RobotMode.FAULT and robot.fault_reason == "e-stop pressed"
    robot.hold()
    robot.resume()
    assert robot.state is RobotMode.FAULT            # only enable() clears a fault
    assert robot.servo_cp(robot.measured_cp()) is False
    robot.enable()
    assert robot.state is RobotMode.ENABLED
    np.testing.assert_allclose(robot.setpoint_cp(), robot.measured_cp(), atol=1e-12)


def test_world_mount_is_applied():
    T = np.eye(4)
    T[:3, :3] = _rot([0, 0, 1], 0.3)
    T[:3, 3] = [0.1, -0.2, 0.3]
    for model in MODELS:
        a = make_robot(model)
        b = make_robot(model, T_world_base=T)
        np.testing.assert_allclose(b.measured_cp(), T @ a.measured_cp(), atol=1e-12)
        target = b.setpoint_cp()[:3, 3] + [0.0005, 0.0, 0.0]
        assert b.servo_cp(target)
        for _ in range(300):
            b.step(DT)
        np.testing.assert_allclose(b.measured_cp()[:3, 3], target, atol=2e-5)


def test_workspace_box_rejects_commands_outside():
    r = make_robot("raven2", workspace_min=[-0.1, -0.1, -0.1], workspace_max=[0.1, 0.1, 0.1])
    p = r.setpoint_cp()[:3, 3]
    with pytest.raises(InputError, match="outside the workspace"):
        r.servo_cp(p + [0.0, 0.0, 0.2])
    assert r.servo_cp(p + [0.0, 0.0, 0.001])


# --- the pose check every setpoint passes (compiled: the tick calls it for every arm) -----------------

def _rigid_error(T):
    """max |R^T R - I| and the determinant, in NumPy (the definition the check implements)."""
    R = T[:3, :3]
    return float(np.abs(R.T @ R - np.eye(3)).max()), float(np.linalg.det(R))


def test_pose_check_agrees_with_its_definition_at_the_tolerance():
    from pointfence.service.robot.base import RIGID_TOL, as_pose

    rng = np.random.default_rng(7)
    accepted = refused = 0
    for k in range(400):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        w, x, y, z = q
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        T = np.eye(4)
        T[:3, :3] = R * (1.0 + (k % 40 - 20) * 0.5 * RIGID_TOL / 10)   # scale errors around the tolerance
        T[:3, 3] = rng.uniform(-1, 1, 3)
        err, det = _rigid_error(T)
        if err > 1.01 * RIGID_TOL:
            with pytest.raises(InputError, match="not orthonormal"):
                as_pose(T)
            refused += 1
        elif err < 0.99 * RIGID_TOL:
            got = as_pose(T)
            assert np.array_equal(got, T) and got is not T
            accepted += 1
    assert accepted > 50 and refused > 50


def test_pose_check_writes_into_out_and_names_each_fault():
    from pointfence.service.robot.base import as_pose

    out = np.zeros((4, 4))
    T = np.eye(4)
    T[:3, 3] = (0.1, -0.2, 0.3)
    assert as_pose(T, "p", out) is out and np.array_equal(out, T)
    assert as_pose(T.tolist(), "p", out) is out            # (a nested list is read, not kept)
    bad = {"not finite": np.where(np.eye(4) == 1, np.inf, 0.0), "last row": T + np.eye(4)[3] * 0.01,
           "determinant": np.diag([1.0, 1.0, -1.0, 1.0])}
    nan = T.copy()
    nan[1, 3] = np.nan
    bad["not finite "] = nan
    for want, B in bad.items():
        with pytest.raises(InputError, match=want.strip()):
            as_pose(B, "p", out)
    with pytest.raises(InputError, match="shape"):
        as_pose(np.eye(3), "p", out)
