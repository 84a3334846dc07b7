"""The tick's device exchange (service/devices.py, masters.py, robot/hosted*.py) made lean: the
same values and the same safety checks as before, through fewer NumPy calls. Each test pins a
check that a leaner path could lose: a scripted master's interpolation, a master's validity, a
refusal's report and its reset, one setpoint message a tick, a record that fails its checksum,
a non-finite state row."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.native import ptr
from pointfence.service.devices import Devices
from pointfence.service.masters import Master, ScriptedMaster
from pointfence.service.robot import RobotMode, make_robot
from pointfence.service.robot.hosted import RobotHost
from pointfence.service.teleop import quat_of_rotation
from pointfence.service.robot.hosted_block import Block
from pointfence.service.tick_io import TickInput, TickOutput

TABLE = {"model": "raven2", "mount_tool_down": [0.0, 0.0, 0.25],
         "workspace_min": [-0.1, -0.1, 0.0], "workspace_max": [0.1, 0.1, 0.3]}


def test_scripted_master_interpolates_exactly_as_the_numpy_reference():
    rng = np.random.default_rng(7)
    t = np.cumsum(rng.uniform(0.001, 0.02, 200))
    p = rng.normal(0.0, 0.05, (200, 3))
    c = rng.random(200) < 0.5
    m = ScriptedMaster(t, p, c, t0=0.3)
    d = np.diff(p, axis=0)
    for s in np.concatenate([[t[0] - 1.0, t[0], t[-1], t[-1] + 1.0], rng.uniform(t[0], t[-1], 500)]):
        m.poll(s + 0.3)
        s = (s + 0.3) - 0.3                                  # (the script's own time, as poll computes it)
        i = int(np.searchsorted(t, s, side="right")) - 1
        if i < 0:
            want, clutch = p[0], c[0]
        elif i >= t.size - 1:
            want, clutch = p[-1], c[-1]
        else:
            want = d[i] * ((s - t[i]) / (t[i + 1] - t[i])) + p[i]
            clutch = c[i]
        np.testing.assert_array_equal(m.position, want)        # bit for bit
        assert m.clutch is bool(clutch) and m.ok is True


def test_a_scripted_masters_pedal_follows_its_clutches_array():
    m = ScriptedMaster([0.0, 1.0, 2.0], np.zeros((3, 3)))
    for t in (-1.0, 0.5, 1.5, 3.0):
        m.poll(t)
        assert m.clutch is True
    m.clutches[:] = False                               # the operator lifts the pedal (tests/test_service_ctl.py)
    for t in (-1.0, 0.5, 1.5, 3.0):
        m.poll(t)
        assert m.clutch is False


def test_a_scripted_master_with_a_non_finite_sample_is_not_ok():
    m = ScriptedMaster([0.0, 1.0], [[0.0, 0.0, 0.0], [math.nan, 0.0, 0.0]])
    m.poll(0.5)
    assert not m.ok and math.isnan(m.position[0])


class _Fixed(Master):
    def __init__(self, pos, ok=True):
        super().__init__()
        self.position[:] = pos
        self.ok = ok

    def poll(self, t):
        pass


@pytest.mark.parametrize("pos, ok, want", [([0.1, 0.2, 0.3], True, True), ([0.1, math.nan, 0.3], True, False),
                                           ([0.1, 0.2, -math.inf], True, False), ([1e308, 1e308, 0.0], True, True),
                                           ([0.1, 0.2, 0.3], False, False)])
def test_a_masters_sample_is_valid_only_when_the_device_says_so_and_every_coordinate_is_finite(pos, ok, want):
    dev = Devices([_Fixed([0.0, 0.0, 0.0]), _Fixed(pos, ok)], [None, None])
    inp = TickInput.zeros(2)
    inp.master_ok[:] = True
    dev.read_masters(inp)
    assert inp.master_ok.tolist() == [True, want]
    np.testing.assert_array_equal(inp.master_pos[1], pos)


def _robot():
    r = make_robot("point-mass", workspace_min=[-0.1, -0.1, -0.1], workspace_max=[0.1, 0.1, 0.1])
    r.reset([0.0, 0.0, 0.0])
    return r


def test_a_refused_command_is_reported_for_its_tick_only():
    robots = [_robot(), None, _robot()]
    dev = Devices([_Fixed([0, 0, 0]) for _ in robots], robots)
    out = TickOutput.zeros(3)
    out.coupled[:] = True
    out.command[:] = [[0.01, 0.0, 0.0], [0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]    # arm 2: outside its workspace
    assert dev.command_robots(out, 1e-3) is True
    assert dev.refused.tolist() == [False, False, True] and dev.refusals == 1
    np.testing.assert_array_equal(dev.kept[2], robots[2].setpoint_cp()[:3, 3])
    assert "robot 2" in dev.last_refusal and "workspace" in dev.last_refusal
    np.testing.assert_array_equal(robots[0].setpoint_cp()[:3, 3], [0.01, 0.0, 0.0])
    out.command[2] = [0.02, 0.0, 0.0]
    assert dev.command_robots(out, 1e-3) is False
    assert dev.refused.tolist() == [False, False, False] and dev.refusals == 1


def test_read_robots_gives_measured_tips_faults_and_the_ideal_arms_command():
    robots = [_robot(), None, _robot()]
    robots[2].fault("test")
    dev = Devices([_Fixed([0, 0, 0]) for _ in robots], robots)
    inp = TickInput.zeros(3)
    ideal = np.array([[9.0, 9.0, 9.0], [0.01, 0.02, 0.03], [9.0, 9.0, 9.0]])
    dev.read_robots(inp, ideal)
    np.testing.assert_array_equal(inp.robot_pos, [robots[0].measured_cp()[:3, 3], ideal[1],
                                                  robots[2].measured_cp()[:3, 3]])
    assert inp.robot_present.tolist() == [True, False, True] and inp.robot_fault.tolist() == [False, False, True]


def test_a_tick_sends_every_hosted_arms_setpoint_in_one_message():
    host = RobotHost([TABLE] * 3, timeout_s=0.25)
    try:
        dev = Devices([_Fixed([0, 0, 0]) for _ in host.robots], host.robots)
        out = TickOutput.zeros(3)
        x0 = np.array([r.measured_cp()[:3, 3] for r in host.robots])
        # each arm's own orientation: the tick's default (identity) is out of a Raven's reach, and
        # the child's refusal would reach the next servo_cp whenever the child answers first
        for b, r in enumerate(host.robots):
            out.orientation[b] = quat_of_rotation(r.measured_cp()[:3, :3])
        out.coupled[:] = out.engage[:] = True
        ch = host._blk.cmd                            # (the test looks at the wire)
        writes = int(ch.meta[0] + ch.meta[1]) // 2
        out.command[:] = x0 + [0.001, 0.0, 0.0]
        assert dev.command_robots(out, 1e-3) is False, dev.last_refusal
        out.engage[:] = False
        out.command[:] = x0 + [0.002, 0.0, 0.0]
        before = int(ch.meta[0] + ch.meta[1]) // 2
        assert before > writes                         # (the resumes: mode commands leave at once)
        assert dev.command_robots(out, 1e-3) is False, dev.last_refusal
        assert int(ch.meta[0] + ch.meta[1]) // 2 == before + 1
        got = np.zeros(3 * host._blk.C)
        assert ch.read(got)
        rows = got.reshape(3, -1)
        L = host._blk.command_layout
        for b in range(3):
            np.testing.assert_array_equal(rows[b, L.pose].reshape(4, 4)[:3, 3], out.command[b])
            assert rows[b, L.servo_seq] == 2 and host.sent(b) == (2, 1)
    finally:
        host.close()


def test_a_record_failing_its_checksum_or_caught_mid_write_is_never_read():
    blk = Block(bytearray(Block.nbytes(2, 6)), 2, 6)
    rec = np.arange(2 * blk.S, dtype=float)
    blk.state.write(rec)
    out = np.zeros(2 * blk.S)
    assert blk.state.read(out) and np.array_equal(out, rec)
    i = int(blk.state.meta[2])
    blk.state.sums[i] ^= 1                              # a checksum that does not match the bytes
    assert not blk.state.read(np.zeros(2 * blk.S))
    blk.state.sums[i] ^= 1
    blk.state.meta[i] += 1                              # the writer is in the middle of this slot
    assert not blk.state.read(np.zeros(2 * blk.S))
    blk.state.meta[i] += 1
    assert blk.state.read(out) and np.array_equal(out, rec)


def test_an_infinite_state_value_faults_its_arm_and_is_not_taken():
    host = RobotHost([TABLE, TABLE], timeout_s=0.25)
    try:
        a, b = host.robots
        host.inject("stall")                            # the child writes no more: this test writes its record
        blk, L = host._blk, host._blk.layout
        rows = host._buf.copy()
        rows[0, L.dq] = [0.0, math.inf, 0.0, 0.0, 0.0, 0.0]
        rows[1, L.t] += 1.0
        q0 = a.measured_js().position.copy()
        blk.state.write(rows.reshape(-1))
        a.step(1e-3)
        b.step(1e-3)
        assert a.state is RobotMode.FAULT and a.fault_reason == "robot state non-finite: dq (arm 0)"
        np.testing.assert_array_equal(a.measured_js().position, q0)
        assert np.isfinite(a.measured_js().velocity).all()
        assert b.state is not RobotMode.FAULT and b.t == rows[1, L.t]    # the other arm took its row
        with pytest.raises(InputError, match="not finite"):
            b.servo_cp([math.nan, 0.0, 0.1])
    finally:
        host.inject("none")
        host.close()


def _read(dev, n, ideal_jaw=None):
    inp = TickInput.zeros(n)
    inp.robot_fault[:] = True                      # (stale values the read must overwrite)
    inp.robot_jaw[:] = -7.0
    dev.read_robots(inp, np.zeros((n, 3)), None, ideal_jaw)
    return inp


@pytest.mark.parametrize("table", [TABLE, {"model": "point-mass"}])
def test_the_compiled_read_of_a_robot_process_equals_the_read_arm_by_arm(table):
    host = RobotHost([table] * 3, timeout_s=0.25)
    try:
        arms = host.robots
        ideal_jaw = np.array([0.1, 0.2, 0.3])
        fast = Devices([_Fixed([0, 0, 0]) for _ in arms], arms)          # arm b on its row b: one call
        order = [2, 0, 1]                                                  # the same arms in another order:
        slow = Devices([_Fixed([0, 0, 0]) for _ in arms], [arms[i] for i in order])   # arm by arm
        for _ in range(20):
            for a in arms:
                a.step(1e-3)
            time.sleep(1e-3)
        arms[1].latch_fault("test")                                        # a latched arm reads as FAULT
        a, b = _read(fast, 3, ideal_jaw), _read(slow, 3, ideal_jaw[order])
        for name in ("robot_pos", "robot_orientation", "robot_fault", "robot_present", "robot_jaw"):
            np.testing.assert_array_equal(getattr(a, name)[order], getattr(b, name), err_msg=name)
        assert a.robot_fault.tolist() == [False, True, False] and a.robot_present.all()
        np.testing.assert_array_equal(a.robot_pos[0], arms[0].measured_cp()[:3, 3])
        np.testing.assert_array_equal(a.robot_jaw, ideal_jaw)              # no jaw: the command's
        # an arm with a jaw reads its measured one, NaN while the child has not reported it
        T4, pos, quat = np.zeros((3, 4, 4)), np.zeros((3, 3)), np.zeros((3, 4))
        fault, present, jaw = np.zeros(3, bool), np.zeros(3, bool), np.zeros(3)
        jawed = np.array([True, False, True])
        host.read_poses(*(ptr(x, x.dtype, "x") for x in (T4, pos, quat, fault, present, jaw, jawed, ideal_jaw)))
        assert math.isnan(jaw[0]) and jaw[1] == 0.2 and math.isnan(jaw[2])
        np.testing.assert_array_equal(pos, T4[:, :3, 3])
    finally:
        host.close()


class _Replacing(Master):
    """A master that puts each sample in new arrays (of any numeric type) instead of in place."""

    def __init__(self, dtype):
        super().__init__()
        self.dtype, self.k = dtype, 0

    def poll(self, t):
        self.k += 1
        self.position = np.array([self.k, 2 * self.k, 3 * self.k], self.dtype) / 100
        self.orientation = np.array([0.0, 1.0, 0.0, 0.0], self.dtype)
        self.grasp, self.clutch = 0.1 * self.k, self.k % 2 == 1


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_a_master_that_replaces_its_arrays_is_read_each_tick(dtype):
    masters = [_Fixed([0.5, 0.5, 0.5]), _Replacing(dtype)]
    dev = Devices(masters, [None, None])
    inp = TickInput.zeros(2)
    for k in (1, 2, 3):
        dev.read_masters(inp)
        np.testing.assert_allclose(inp.master_pos, [[0.5, 0.5, 0.5], [k / 100, 2 * k / 100, 3 * k / 100]], rtol=1e-6)
        np.testing.assert_array_equal(inp.master_orientation[1], [0.0, 1.0, 0.0, 0.0])
        assert inp.grasp[1] == pytest.approx(0.1 * k) and bool(inp.pedal[1]) == (k % 2 == 1)
        assert inp.master_ok.tolist() == [True, True]
    masters[0].position[:] = [0.1, 0.2, np.nan]      # in place, now not finite: not ok
    dev.read_masters(inp)
    assert inp.master_ok.tolist() == [False, True]


def test_the_compiled_command_of_a_robot_process_sends_holds_and_refuses_as_arm_by_arm():
    host = RobotHost([TABLE] * 2, timeout_s=0.25)
    try:
        arms = host.robots
        dev = Devices([_Fixed([0, 0, 0]) for _ in arms], arms)            # arm b on its row b: one call
        for a in arms:
            a.hold()                                                       # (both start held)
        inp, out = _read(dev, 2), TickOutput.zeros(2)
        out.orientation[:] = inp.robot_orientation
        out.command[:] = inp.robot_pos + [0.002, 0.0, 0.0]
        out.coupled[:], out.engage[:], out.release[:] = [True, False], [True, False], [False, False]
        sent = [host.sent(b)[0] for b in range(2)]
        assert dev.command_robots(out, 1e-3) is False
        assert arms[0].state is RobotMode.ENABLED and arms[1].state is RobotMode.HOLDING   # engage resumed arm 0
        assert [host.sent(b)[0] for b in range(2)] == [sent[0] + 1, sent[1]]             # only the coupled arm's
        np.testing.assert_allclose(arms[0].setpoint_cp()[:3, 3], out.command[0], atol=1e-12)
        # arm 0 asked out of the workspace: refused, its setpoint kept, the tick told so
        out.engage[:] = False
        out.command[0] = [0.0, 0.0, 0.5]
        before = arms[0].setpoint_cp()[:3, 3].copy()
        assert dev.command_robots(out, 1e-3) is True
        assert dev.refused.tolist() == [True, False] and "outside the workspace" in dev.last_refusal
        np.testing.assert_allclose(dev.kept[0], before, atol=1e-12)
        assert arms[0].rejected_commands == 1 and host.sent(0)[0] == sent[0] + 1
        # arm 0 decouples: it holds; the next tick's report is reset
        out.coupled[:], out.release[:] = [False, False], [True, False]
        assert dev.command_robots(out, 1e-3) is False and dev.refused.tolist() == [False, False]
        assert arms[0].state is RobotMode.HOLDING and host.sent(0)[0] == sent[0] + 1
        with pytest.raises(InputError, match="dt"):
            dev.command_robots(out, 0.0)
    finally:
        host.close()


@pytest.mark.parametrize("field, value", [("orientation", np.zeros(3)), ("position", np.zeros(4)),
                                          ("position", np.zeros((1, 3)))])
def test_a_master_whose_arrays_have_the_wrong_shape_is_refused_before_any_copy(field, value):
    m = _Fixed([0.0, 0.0, 0.0])
    setattr(m, field, value)
    with pytest.raises(InputError, match=r"expected \(3,\) and \(4,\)"):
        Devices([m], [None])
    good = _Fixed([0.0, 0.0, 0.0])
    dev = Devices([good], [None])
    setattr(good, field, value)                      # replaced later: refused when the tick binds it
    with pytest.raises(InputError, match=r"expected \(3,\) and \(4,\)"):
        dev.read_masters(TickInput.zeros(1))
