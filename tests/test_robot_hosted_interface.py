"""The hosted arm's contract (service/robot/hosted.py, hosted_block.py, hosted_child.py): each
arm's step is right in any call order, the shared block's layout is declared once and both sides
read it through that declaration, and the arm is the robot interface spelt out (nothing of the
model leaks through)."""
from __future__ import annotations

import time

import numpy as np
import pytest

from pointfence.service.robot import RobotMode, robot_from_config
from pointfence.service.robot.base import Robot
from pointfence.service.robot.hosted import HostedRobot, RobotHost
from pointfence.service.robot.hosted_block import (COMMAND, HOLD, Block, Commands, block_dtype, state_dtype)
from pointfence.service.robot.hosted_child import ChildArms

TABLE = {"model": "raven2", "mount_tool_down": [0.0, 0.0, 0.25],
         "workspace_min": [-0.1, -0.1, 0.0], "workspace_max": [0.1, 0.1, 0.3]}
PATIENCE_S = 10.0          # liveness only: a loaded test machine may delay the robot process


def _as_child_reads(host) -> Commands:
    """The command record as the robot process reads it from the shared block."""
    blk = host._blk                                   # (the test looks at the wire)
    got = Commands(host.n)
    assert blk.cmd.read(got.rec)
    return got


@pytest.mark.parametrize("order", [[2, 0, 1], [2, 1, 0], [1, 2, 0]])
def test_each_arms_step_sends_its_setpoint_whatever_the_order(order):
    """A tick that steps the arms in any order: once an arm has stepped, the setpoint it was given
    in this tick is on the wire (a hidden index-order contract left some for the next tick)."""
    h = RobotHost([TABLE] * 3)
    try:
        for r in h.robots:
            r.resume()
        x0 = [r.measured_cp()[:3, 3].copy() for r in h.robots]
        for k in range(1, 4):
            for b in order:
                target = x0[b] + [0.0005 * k * (b + 1), 0.0, 0.0]
                assert h.robots[b].servo_cp(target) is True
                h.robots[b].step(1e-3)
                wire = _as_child_reads(h)
                assert wire.servo_seq[b] == k
                np.testing.assert_allclose(wire.pose[b].reshape(4, 4)[:3, 3], target, atol=1e-12)
    finally:
        h.close()


def test_an_arm_stepped_alone_reads_the_child_and_runs_the_watchdog():
    """Only arm 1 steps (the service steps no other): its state still follows the child, and a dead
    child still reads as FAULT within the watchdog time."""
    h = RobotHost([TABLE, TABLE], timeout_s=0.05)
    try:
        b = h.robots[1]
        t0 = b.t
        end = time.monotonic() + PATIENCE_S
        while b.t <= t0 + 0.005:
            assert time.monotonic() < end, "arm 1's state never moved on"
            b.step(1e-3)
            time.sleep(1e-3)
        h.inject("kill")
        end = time.monotonic() + PATIENCE_S
        while b.state is not RobotMode.FAULT:
            assert time.monotonic() < end, "a dead robot process never read as FAULT"
            b.step(1e-3)
            time.sleep(1e-3)
        assert b.fault_reason.startswith("robot process not answering")
    finally:
        h.close()


def test_one_tick_reads_the_record_once_in_any_order():
    """Every arm stepped once in a tick takes the same read of the child's record."""
    h = RobotHost([TABLE] * 3)
    try:
        for order in ([0, 1, 2], [2, 0, 1], [1, 2, 0]):
            for _ in range(5):
                for b in order:
                    h.robots[b].step(1e-3)
                assert len({r.t for r in h.robots}) == 1
                time.sleep(2e-3)
    finally:
        h.close()


def test_the_block_is_one_declaration_both_sides_read():
    """The service side writes commands through ``Commands``; the robot process's ``ChildArms``
    applies them and publishes state that the service side reads by the state dtype's fields:
    all offsets come from ``block_dtype``."""
    n, dof = 2, 6
    assert Block.nbytes(n, dof) == block_dtype(n, dof).itemsize
    blk = Block(bytearray(Block.nbytes(n, dof)), n, dof)
    dt = block_dtype(n, dof)
    def addr(a):
        return a.__array_interface__["data"][0]

    for name in ("ctl", "inject", "text"):             # every region sits where the dtype puts it
        assert addr(getattr(blk, name)) - addr(blk.raw) == dt.fields[name][1]
    for name in ("state", "cmd"):
        ch, sub = getattr(blk, name), dt.fields[name]
        assert addr(ch.data) - addr(blk.raw) == sub[1] + sub[0].fields["data"][1]
        assert addr(ch.meta) - addr(blk.raw) == sub[1] + sub[0].fields["meta"][1]
    robots = [robot_from_config(TABLE) for _ in range(n)]
    child = ChildArms(blk, robots)
    cmds = Commands(n)                                # the service's side
    target = robots[1].measured_cp()
    target[:3, 3] += [0.002, 0.0, 0.0]
    cmds.pose[1] = target.ravel()
    cmds.servo_seq[1] = 1
    cmds.ring[0, 0] = HOLD
    cmds.mode_seq[0] = 1
    np.testing.assert_array_equal(cmds.rec.reshape(n, -1).copy().view(COMMAND)["pose"][1, 0], target.ravel())
    blk.cmd.write(cmds.rec)
    child.period(1e-3)
    assert robots[0].state is RobotMode.HOLDING
    np.testing.assert_allclose(robots[1].setpoint_cp(), target, atol=1e-12)
    flat = np.zeros(n * blk.S)
    assert blk.state.read(flat)
    rows = flat.reshape(n, blk.S).copy().view(state_dtype(dof))[:, 0]     # by name, from the dtype
    for b, r in enumerate(robots):
        np.testing.assert_array_equal(rows["q"][b], r.measured_js().position)
        np.testing.assert_array_equal(rows["T_d"][b], r.setpoint_cp().ravel())
        assert rows["mode"][b] == int(r.state) and rows["t"][b] == r.t
    assert rows["servo_seq"][1] == 1 and rows["mode_seq"][0] == 1


#: the plumbing of a model whose controller runs elsewhere: the hosted arm's own business
_PLUMBING = {"copy_state", "adopt_state", "adopt_setpoint", "adopt_texts", "checked_setpoint"}


def test_the_hosted_arm_is_the_robot_interface_and_nothing_of_the_model_leaks():
    h = RobotHost([TABLE])
    try:
        a = h.robots[0]
        assert "__getattr__" not in vars(HostedRobot)
        interface = {n for n in dir(Robot) if not n.startswith("_")} - _PLUMBING
        missing = sorted(n for n in interface if not hasattr(a, n))
        assert not missing, f"HostedRobot lacks {missing}"
        for name in ("kp", "gravity_torque", "arm", "_q", "_q_d", "_advance", "adopt_state", "copy_state"):
            assert not hasattr(a, name), name                # Raven II's own, or the model's state: not here
        assert a.kin is not None and hasattr(a.kin, "wrist_point")   # the self-filter's instrument axis
        local = robot_from_config(TABLE)
        assert (a.model, a.dof, a.joint_names) == (local.model, local.dof, local.joint_names)
        q = np.zeros(6)
        a.measured_jp_into(q)
        np.testing.assert_allclose(a.forward_kinematics(q), a.measured_cp(), atol=1e-9)
        st = a.read_state()
        assert st.mode is a.state and st.rejected_commands == a.rejected_commands == 0
        assert isinstance(a, HostedRobot) and a.hosted and f"process {h.pid}" in repr(a)
    finally:
        h.close()
