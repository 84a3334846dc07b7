"""A robot process that fails (service/robot/hosted.py): a NaN state, a stall and a death each read
as a latched FAULT with its reason within the watchdog time, a faulted arm never moves, and
enable() works again only once the process steps and its state is finite (S3, S9)."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service import replay
from pointfence.service.robot import RobotMode
from pointfence.service.robot.hosted import WATCHDOG_MAX_S, WATCHDOG_S, RobotHost
from pointfence.service.robot.hosted_block import Block

from service_cases import balloon_config, push

TABLE = {"model": "raven2", "mount_tool_down": [0.0, 0.0, 0.25],
         "workspace_min": [-0.1, -0.1, 0.0], "workspace_max": [0.1, 0.1, 0.3]}
PATIENCE_S = 10.0          # liveness only: a loaded test machine may delay the robot process


@pytest.fixture
def host():
    h = RobotHost([TABLE, TABLE], timeout_s=0.05)
    yield h
    h.close()


def tick(host, n=1, period=1e-3):
    for _ in range(n):
        for r in host.robots:
            r.step(period)
        time.sleep(period)


def tick_until(host, cond, limit_s=PATIENCE_S) -> int:
    """Tick the arms (as the service does) until ``cond()``; returns the ticks it took."""
    end, k = time.monotonic() + limit_s, 0
    while not cond():
        assert time.monotonic() < end, "condition not reached"
        tick(host)
        k += 1
    return k


def test_a_record_holding_nan_reads_and_is_not_rejected_forever():
    # the old checksum was a float sum: NaN != NaN, so a NaN record never read and the service
    # kept showing the last good state
    blk = Block(bytearray(Block.nbytes(1, 6)), 1, 6)
    rec = np.arange(blk.S, dtype=float)
    rec[blk.layout.q] = math.nan
    blk.state.write(rec)
    out = np.zeros(blk.S)
    assert blk.state.read(out)
    assert blk.layout.nonfinite_fields(out) == ["q"]
    blk.state.data[blk.state.meta[2], 0] += 1.0         # a torn copy (bytes changed under the reader)
    assert not blk.state.read(out)


def test_the_layout_is_one_dtype_for_both_sides():
    blk = Block(None, 2, 6)
    L = blk.layout
    assert L.size == blk.S == 8 + 4 * 6 + 32 + 2
    assert (L.t, L.q, L.T_meas, L.T_d, L.jaw, L.jaw_known) == (0, slice(8, 14), slice(32, 48), slice(48, 64), 64, 65)


def test_nan_state_faults_the_arm_and_a_faulted_arm_never_moves(host):
    a, b = host.robots
    for r in host.robots:
        r.resume()
    tick(host, 20)
    x0, s0 = a.measured_cp()[:3, 3].copy(), a.setpoint_cp()[:3, 3].copy()
    assert np.isnan(host.injected_at(0))
    t_inject = time.perf_counter()
    host.inject("nan", arm=0)
    k = tick_until(host, lambda: a.state is RobotMode.FAULT)
    assert k < 2000                                     # bounded: a few control periods, not a timeout
    # when the child published the NaN state: after the request, before the service saw it (the
    # soak judges the hold's latency from it); the other arm was not injected
    assert t_inject < host.injected_at(0) < time.perf_counter() and np.isnan(host.injected_at(1))
    assert a.fault_reason == "robot state non-finite: q, T_meas (arm 0)"
    assert b.state is RobotMode.ENABLED and b.fault_reason is None    # the other arm is healthy
    assert np.isfinite(a.measured_cp()).all() and np.isfinite(a.measured_js().position).all()
    # faulted: a setpoint is not sent, the child was told to brake
    sent = host.sent(0)[0]
    assert a.servo_cp(x0 + [0.01, 0.0, 0.0]) is False and host.sent(0)[0] == sent
    np.testing.assert_allclose(a.setpoint_cp()[:3, 3], s0, atol=1e-12)
    a.enable()                                          # still NaN: refused, says why
    assert a.state is RobotMode.FAULT and "non-finite" in a.last_error
    tick(host, 20)
    assert a.state is RobotMode.FAULT and a.fault_reason.startswith("robot state non-finite")
    host.inject("none")
    tick_until(host, lambda: host.ready(0) is None)
    a.enable()
    tick_until(host, lambda: a.state is RobotMode.ENABLED and a.fault_reason is None)
    tick(host, 50)
    assert a.state is RobotMode.ENABLED
    assert np.linalg.norm(a.measured_cp()[:3, 3] - x0) < 2e-4       # enabling re-seats: no jump
    assert a.servo_cp(x0) is True


def test_a_stalled_robot_process_faults_within_the_watchdog_and_recovers(host):
    a, b = host.robots
    tick(host, 20)
    assert a.state is not RobotMode.FAULT and host.alive
    host.inject("stall")                                # SIGSTOP: the process neither steps nor dies
    t0 = time.monotonic()
    tick_until(host, lambda: a.state is RobotMode.FAULT and b.state is RobotMode.FAULT)
    waited = time.monotonic() - t0
    assert waited >= host.timeout_s                     # not before the watchdog time ...
    for r in (a, b):                                    # ... and then with the reason
        assert r.fault_reason.startswith("robot process not answering: no step for")
        assert "(process alive)" in r.fault_reason
    assert not host.alive
    a.enable()
    assert a.state is RobotMode.FAULT and "not answering" in a.last_error
    host.inject("none")                                 # SIGCONT: it steps again
    tick_until(host, lambda: host.ready(0) is None)
    assert a.state is RobotMode.FAULT                   # latched until enable()
    a.enable()
    b.enable()
    tick_until(host, lambda: a.state is RobotMode.ENABLED and b.state is RobotMode.ENABLED)


def test_a_killed_robot_process_faults_and_a_restarted_one_resumes_where_the_arms_were(host):
    a, b = host.robots
    for r in host.robots:
        r.resume()
    tick(host, 20)
    x0 = a.measured_cp()[:3, 3].copy()
    host.inject("kill")
    tick_until(host, lambda: a.state is RobotMode.FAULT and b.state is RobotMode.FAULT)
    assert a.fault_reason.startswith("robot process not answering") and "(process ended)" in a.fault_reason
    a.enable()
    assert a.state is RobotMode.FAULT and "has ended" in a.last_error
    assert a.servo_cp(x0) is False
    host.restart()
    tick_until(host, lambda: host.ready(0) is None)
    tick(host, 20)
    assert a.state is RobotMode.FAULT                   # restarted braked, as the arm read here
    a.enable()
    tick_until(host, lambda: a.state is RobotMode.ENABLED)
    tick(host, 50)
    assert np.linalg.norm(a.measured_cp()[:3, 3] - x0) < 2e-4        # where it was, no jump
    assert a.servo_cp(x0 + [0.0, 0.0, -0.002]) is True


def test_watchdog_time_has_a_ceiling_and_faults_are_named():
    with pytest.raises(InputError, match="watchdog"):
        RobotHost([TABLE], timeout_s=WATCHDOG_MAX_S * 2)
    with pytest.raises(InputError, match="watchdog"):
        RobotHost([TABLE], timeout_s=math.nan)
    h = RobotHost([TABLE])
    try:
        assert h.timeout_s == WATCHDOG_S == 0.05
        with pytest.raises(InputError, match="expected one of nan, stall, kill, none"):
            h.inject("explode")
        with pytest.raises(InputError, match="arm 3"):
            h.inject("nan", arm=3)
    finally:
        h.close()


def test_the_service_holds_and_reports_a_robot_whose_state_turns_nan(tmp_path):
    cfg = balloon_config(tmp_path, arch="III")
    h = RobotHost([cfg.robot.table()], timeout_s=WATCHDOG_MAX_S)   # offline ticks run faster than real time
    try:
        def nan(svc):
            h.inject("nan")
            time.sleep(0.05)                            # the child publishes it

        svc, _, sources = replay.simulate(cfg, [push(0.10, t_end=0.5, hold=0.5)], 0.6, robots=h.robots,
                                          backend="numpy", events={300: nan})
        for s in sources:
            s.close()
        st = svc.status()
        assert st["robots"][0]["mode"] == "FAULT"
        assert st["robots"][0]["fault"] == "robot state non-finite: q, T_meas (arm 0)"
        assert svc.arm_hold[0] != 0                     # the tick holds the arm
        rec = svc.recorder
        xr = rec.robots[: rec.count, 0, :3]
        assert np.isfinite(xr).all()
        after = xr[310:]                                # the robot's position is frozen once faulted
        assert np.abs(after - after[0]).max() < 1e-4
    finally:
        h.close()
