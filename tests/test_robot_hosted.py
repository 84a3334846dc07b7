"""Simulated robots in their own process (service/robot/hosted.py): the same arm as in the tick,
commands and state through shared memory, bad data refused before it leaves the service, a dead
robot process read as FAULT, and a live run of the service on hosted arms."""
from __future__ import annotations

import os
import time

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service.robot import RobotMode, robot_from_config
from pointfence.service.robot.hosted import HostedRobot, RobotHost
from pointfence.service.runner import LiveRun

from service_cases import RAVEN, REGION_TOP, balloon_config, needs_opencl, push

TABLE = {"model": "raven2", "mount_tool_down": [0.0, 0.0, 0.25],
         "workspace_min": [-0.1, -0.1, 0.0], "workspace_max": [0.1, 0.1, 0.3]}


@pytest.fixture
def host():
    h = RobotHost([TABLE, TABLE])
    yield h
    h.close()


def tick(host, n=1, period=1e-3, order=None):
    """``n`` ticks of the service: every arm steps once a tick (in index order, or ``order``)."""
    for _ in range(n):
        for i in (order if order is not None else range(len(host.robots))):
            host.robots[i].step(period)
        time.sleep(period)


@pytest.mark.parametrize("order", [None, [1, 0]], ids=["index-order", "reverse-order"])
def test_hosted_arm_follows_a_setpoint_stream_like_the_arm_in_the_tick(host, order):
    """The same in any order of the arms' steps within a tick."""
    local = robot_from_config(TABLE)            # the same model stepped in this process
    a, b = host.robots
    x0 = a.measured_cp()[:3, 3].copy()
    np.testing.assert_allclose(x0, local.measured_cp()[:3, 3], atol=5e-5)   # (the child has stepped for as long as it has run: up to ~20 um of gravity sag)
    for r in host.robots:
        r.resume()
    target = x0 + [0.01, -0.005, -0.01]
    for k in range(400):                          # 2.5 cm/s for 0.4 s, then settle
        x = x0 + (target - x0) * min(1.0, k / 300)
        a.servo_cp(x)
        local.servo_cp(x)
        local.step(1e-3)
        tick(host, order=order)
    tick(host, 300, order=order)
    local.step(0.3)
    got = a.measured_cp()[:3, 3]
    assert np.linalg.norm(got - target) < 2e-4 and np.linalg.norm(local.measured_cp()[:3, 3] - target) < 2e-4
    np.testing.assert_allclose(a.setpoint_cp()[:3, 3], target, atol=1e-12)
    assert np.linalg.norm(b.measured_cp()[:3, 3] - x0) < 1e-4      # the other arm was never commanded
    assert a.state is RobotMode.ENABLED and a.rejected_commands == 0
    q = np.zeros(6)
    a.measured_jp_into(q)                         # the joints the self-filter reads: the child's
    np.testing.assert_allclose(a.forward_kinematics(q)[:3, 3], got, atol=1e-9)
    assert a.measured_js().position.shape == (6,)


def test_hold_freezes_the_hosted_arm_and_resume_never_moves_it(host):
    a = host.robots[0]
    x0 = a.measured_cp()[:3, 3].copy()
    a.hold()
    assert a.state is RobotMode.HOLDING
    assert a.servo_cp(x0 + [0.01, 0, 0]) is False          # ignored while holding
    tick(host, 100)
    assert a.state is RobotMode.HOLDING
    assert np.linalg.norm(a.measured_cp()[:3, 3] - x0) < 1e-4
    a.resume()
    tick(host, 100)
    assert a.state is RobotMode.ENABLED and np.linalg.norm(a.measured_cp()[:3, 3] - x0) < 1e-4



def test_applied_tells_when_the_child_has_taken_this_sides_commands(host):
    """``state`` reads the mode asked for at once; ``applied`` says when the child has it too."""
    a = host.robots[0]
    tick(host, 5)
    assert host.applied(0) == host.sent(0)
    a.hold()
    a.servo_cp(a.measured_cp())                               # ignored while holding: not sent
    assert host.sent(0)[1] == host.applied(0)[1] + 1          # HOLD asked for, not yet taken
    assert a.state is RobotMode.HOLDING
    for _ in range(2000):
        tick(host)
        if host.applied(0) == host.sent(0):
            break
    assert host.applied(0) == host.sent(0) and a.state is RobotMode.HOLDING
    assert host.applied(1) == host.sent(1) == (0, 0)


@pytest.mark.parametrize("bad, message", [
    ([np.nan, 0.0, 0.1], "not finite"),
    ([0.0, 0.0, 0.5], "outside the workspace"),
    ([[1.0, 2.0], [3.0, 4.0]], r"shape \(2, 2\)"),
])
def test_bad_setpoints_are_refused_here_and_never_reach_the_robot(host, bad, message):
    a = host.robots[0]
    a.resume()
    x0, s0 = a.measured_cp()[:3, 3].copy(), a.setpoint_cp()[:3, 3].copy()
    sent = host.sent(0)[0]
    with pytest.raises(InputError, match=message):
        a.servo_cp(bad)
    assert host.sent(0)[0] == sent and a.rejected_commands == 1
    tick(host, 50)
    np.testing.assert_allclose(a.setpoint_cp()[:3, 3], s0, atol=1e-12)
    assert np.linalg.norm(a.measured_cp()[:3, 3] - x0) < 1e-4 and a.rejected_commands == 1


def _bad_pose(T, kind):
    T = T.copy()
    if kind == "nan":
        T[1, 3] = np.nan
    elif kind == "workspace":
        T[2, 3] = 0.5
    elif kind == "scaled":
        T[:3, :3] *= 1.01
    elif kind == "reflection":
        T[:3, 0] *= -1.0
    elif kind == "last row":
        T[3, 0] = 0.1
    return T


@pytest.mark.parametrize("kind, message", [("nan", "not finite"), ("workspace", "outside the workspace"),
                                           ("scaled", "orthonormal"), ("reflection", "reflection"),
                                           ("last row", "last row")])
def test_a_bad_4x4_setpoint_is_refused_by_the_compiled_check_with_the_same_message(host, kind, message):
    a = host.robots[0]                          # (a 4x4 float64 array: the compiled path, pf_host_servo)
    a.resume()
    T0, s0 = a.measured_cp(), a.setpoint_cp()
    sent = host.sent(0)[0]
    with pytest.raises(InputError, match=message):
        a.servo_cp(_bad_pose(T0, kind))
    assert host.sent(0)[0] == sent and a.rejected_commands == 1
    tick(host, 20)
    np.testing.assert_allclose(a.setpoint_cp(), s0, atol=1e-12)
    T1 = T0.copy()
    T1[0, 3] += 0.002
    assert a.servo_cp(T1) is True and host.sent(0)[0] == sent + 1       # a good one goes through
    a.hold()
    assert a.servo_cp(T1) is False and host.sent(0)[0] == sent + 1 and a.ignored_commands == 1


def test_an_unreachable_setpoint_is_rejected_by_the_robot_and_reported_by_a_later_servo_cp():
    table = dict(TABLE)
    del table["workspace_min"], table["workspace_max"]
    h = RobotHost([table])
    try:
        a = h.robots[0]
        a.resume()
        x0, s0 = a.measured_cp()[:3, 3].copy(), a.setpoint_cp()[:3, 3].copy()
        a.servo_cp(x0 + [0.0, 0.0, 0.5])          # the insertion joint cannot reach it
        end = time.monotonic() + 10.0              # (a loaded machine may delay the robot process)
        while a.rejected_commands == 0 and time.monotonic() < end:
            tick(h)
        with pytest.raises(InputError, match="out of reach"):
            a.servo_cp(x0)
        np.testing.assert_allclose(a.setpoint_cp()[:3, 3], s0, atol=1e-12)   # the robot kept its setpoint
        assert np.linalg.norm(a.measured_cp()[:3, 3] - x0) < 1e-4 and a.rejected_commands == 1
        assert a.servo_cp(x0) is True             # reported once; the next setpoint goes through
    finally:
        h.close()


def test_a_dead_robot_process_reads_as_fault_and_cannot_be_enabled(host):
    a, b = host.robots
    host._proc.kill()
    host._proc.wait(timeout=5)
    end = time.monotonic() + host.timeout_s + 0.1
    while time.monotonic() < end:                # the service keeps ticking, as it does
        tick(host)
    for r in (a, b):
        assert r.state is RobotMode.FAULT and r.fault_reason.startswith("robot process not answering")
    a.enable()
    assert a.state is RobotMode.FAULT and not host.alive


def test_close_ends_the_process_and_frees_the_shared_memory():
    h = RobotHost([TABLE])
    pid, name = h.pid, h._shm.name
    h.close()
    h.close()
    assert not os.path.exists(f"/proc/{pid}") or open(f"/proc/{pid}/stat").read().split()[2] == "Z"
    assert not os.path.exists(f"/dev/shm/{name.lstrip('/')}")
    h.robots[0].step(1e-3)                       # a closed host's arms keep their last state
    assert h.robots[0].state is RobotMode.ENABLED


def test_a_bad_table_fails_in_the_service_process_with_the_configs_message():
    with pytest.raises(InputError, match="did you mean"):
        RobotHost([{"model": "raven2", "mount_tool_dwn": [0, 0, 0.25]}])


@needs_opencl
def test_live_run_hosts_the_arms_and_architecture_iii_keeps_them_out(tmp_path):
    cfg = balloon_config(tmp_path, arch="III", robot=RAVEN, extra="max_lateness_s = 1.0\n")
    run = LiveRun(cfg, [push(0.12, t_end=0.8, hold=0.6)], record_s=2.0)
    try:
        assert isinstance(run.service.robots[0], HostedRobot) and run.robot_host.alive
        run.start()
        run.wait_ticks(1300)
    finally:
        run.stop()
    assert run.loop.error is None
    rec = run.service.recorder
    xr = rec.robots[: rec.count, 0, :3]
    assert xr[:, 2].min() > REGION_TOP - 0.001       # held out of the fixture (1 mm)
    assert xr[0, 2] - xr[:, 2].min() > 0.005           # and it did move down towards it
    assert run.robot_host.pid is None                 # stop() ended the robot process
    assert run.service.status()["robots"][0]["process"] == "own"


@needs_opencl
def test_the_configured_robot_watchdog_reaches_the_robot_process(tmp_path):
    """[service] robot_watchdog_s is the hosted robot process's watchdog in a live run."""
    cfg = balloon_config(tmp_path, arch="III", robot=RAVEN, extra="robot_watchdog_s = 0.07\n")
    assert cfg.service.robot_watchdog_s == 0.07
    run = LiveRun(cfg, [push()])
    try:
        assert run.robot_host is not None and run.robot_host.timeout_s == 0.07
    finally:
        run.stop()
    with pytest.raises(InputError, match=r"robot_watchdog_s = 0.5 s is above its hard limit of 0.25 s"):
        balloon_config(tmp_path, robot=RAVEN, extra="robot_watchdog_s = 0.5\n")
