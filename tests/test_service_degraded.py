"""Degraded mode: kernel failure, NaN master input, a stale camera and a loop overrun all ramp
the force to zero within the configured time and hold the robot; recovery does not jump."""
import numpy as np
import pytest

from pointfence.kernels.errors import InputError, KernelError
from pointfence.service.holds import KERNEL, MASTER, OVERRUN, STALE
from pointfence.service.masters import ScriptedMaster
from pointfence.service.replay import simulate
from pointfence.service.robot import RobotMode

from service_cases import balloon_config, needs_opencl, push, steps

pytestmark = needs_opencl
RAMP = 0.02      # force_ramp_s of the test configuration
RECOVER = 0.05   # recover_s
V, DT = 0.05, 1e-3


def close(sources):
    for s in sources:
        s.close()


def in_contact_then(cfg, events, duration=1.4, master=None):
    svc, loop, sources = simulate(cfg, [master or push(0.10, t_end=0.8, hold=1.0)], duration, events=events)
    close(sources)
    return svc, svc.recorder.ticks(), loop


def force_ramped_out(rows, k0):
    """Ticks after k0 until the force is exactly zero."""
    f = np.linalg.norm(rows[k0:, 16:19], axis=1)
    return int(np.argmax(f == 0.0))


def test_kernel_failure_ramps_force_and_holds_robot(tmp_path):
    cfg = balloon_config(tmp_path, arch="III")
    state = {}

    def break_kernel(svc):
        good = svc.batch.step
        state["good"] = good

        def failing(h):
            raise KernelError("injected device failure")

        svc.batch.step = failing

    def repair(svc):
        svc.batch.step = state["good"]

    seen = {}

    def clear(svc):            # S3: a latched fault; clearing needs the pedal up
        seen["latched"] = svc.status()
        try:
            svc.clear_faults()
        except InputError as e:
            seen.setdefault("refused", str(e))

    # the pedal goes up at 1.25 s and down again at 1.35 s; clear-faults is tried at 1.2 and 1.3 s
    t = np.array([0.0, 0.1, 0.8, 1.25, 1.35, 1.8])
    p = np.array([[0, 0, 0], [0, 0, 0], [0, 0, -0.10], [0, 0, -0.10], [0, 0, -0.10], [0, 0, -0.10]], float)
    master = ScriptedMaster(t, p, clutch=[1, 1, 1, 0, 1, 1])
    svc, rows, loop = in_contact_then(cfg, {900: break_kernel, 1100: repair, 1200: clear, 1300: clear},
                                      duration=1.5, master=master)
    assert np.linalg.norm(rows[899, 16:19]) > 2.0
    n = force_ramped_out(rows, 900)
    assert 0 < n <= RAMP / DT + 1, f"force took {n} ticks to reach zero"
    assert steps(rows[900:1100, 10:13]).max() < 1e-12                 # the command stopped
    assert steps(rows[950:1100, 13:16]).max() < 2e-5                  # the robot holds (settles)
    assert svc.kernel_errors == 200                                   # surfaced, loop kept running
    assert loop.error is None and loop.ticks == 1500
    # latched: the repaired kernel does not bring the arm back; clearing with the pedal down is refused
    assert seen["latched"]["hold"] == ["kernel failure"] and "pedal" in seen["refused"]
    assert seen["latched"]["hold_causes"] == [{"reason": "kernel failure", "invariant": "S3", "latched": True}]
    assert np.linalg.norm(rows[1100:1350, 16:19], axis=1).max() == 0.0
    # cleared with the pedal up: the arm couples again when the pedal goes down; nothing jumps
    assert svc.status()["hold"] == [] and svc.robots[0].state == RobotMode.ENABLED and svc.coupled[0]
    assert steps(rows[1090:, 10:13]).max() <= V * DT * (1 + 1e-6)


def test_nan_master_input_holds_that_arm(tmp_path):
    cfg = balloon_config(tmp_path, arch="I")
    t = np.array([0.0, 0.1, 0.5, 0.6, 0.6001, 0.8, 0.8001, 1.2])
    z = np.array([0.0, 0.0, -0.04, -0.04, np.nan, np.nan, -0.04, -0.04])
    m = ScriptedMaster(t, np.stack([np.zeros(8), np.zeros(8), z], 1))
    events = {700: lambda s: held.append(s.status())}
    held = []
    svc, rows, loop = in_contact_then(cfg, events, 1.2, master=m)
    assert held[0]["arms_holding"] == [["master input invalid"]]
    assert svc.robots[0].state == RobotMode.ENABLED                   # back after the NaNs stopped
    assert np.isfinite(rows[:, :19]).all()                            # NaN never reached anything
    assert steps(rows[600:850, 10:13]).max() < 1e-12                  # command held, no jump after
    assert steps(rows[:, 10:13]).max() <= V * DT * (1 + 1e-6)


def test_stale_camera_keeps_fixtures_then_holds(tmp_path):
    # the camera delivers 6 frames (0.2 s) and then stalls: its points stay, the proxy still
    # rests on the fixture; past max_frame_age_s (0.3 s) the robot holds and the force ramps out
    cfg = balloon_config(tmp_path, arch="III", options=", max_frames = 6")
    seen = {}
    events = {400: lambda s: seen.update(s400=s.status(now=0.4)), 450: lambda s: seen.update(s450=s.status(now=0.45))}
    svc, rows, loop = in_contact_then(cfg, events, 1.0, master=push(0.10, t_end=0.6, hold=0.4))
    assert seen["s400"]["frames"]["stale"] == ["overhead"]           # reported once older than 100 ms
    assert seen["s400"]["hold"] == []                                 # not yet beyond max age
    assert seen["s450"]["hold"] == []
    frame_age_hold = int(np.argmax(rows[:, 0] >= 0.5 - 1e-9 + 1e-3))  # last frame at 0.1667 s + 0.3 s
    assert svc.status()["hold"] == ["frames too old"]
    # the fixture did not vanish with the stalled camera: the robot stayed out until the hold
    assert rows[:, 15].min() >= 0.14 - 0.001
    n = force_ramped_out(rows, frame_age_hold - 40)
    assert n > 0 and np.linalg.norm(rows[-1, 16:19]) == 0.0
    assert svc.robots[0].state == RobotMode.HOLDING


def test_overrun_flag_holds_and_recovers(tmp_path):
    cfg = balloon_config(tmp_path, arch="III")
    svc, loop, sources = simulate(cfg, [push(0.10, t_end=0.8, hold=0.4)], 0.9)
    rows0 = svc.recorder.count
    # one overrun tick (the loop saw a tick start too late): hold, then recover after recover_s
    svc.tick(900, 0.9, 1e-3, True, 0.9)
    assert svc.hold_mask & OVERRUN and svc.robots[0].state == RobotMode.HOLDING
    for k in range(901, 901 + int(RECOVER / DT) + 5):
        svc.tick(k, k * DT, DT, False, k * DT)
    assert svc.hold_mask == 0 and svc.robots[0].state == RobotMode.ENABLED
    assert svc.recorder.count == rows0 and svc.recorder.full   # recording stops when full; the ticks do not
    close(sources)
    assert {KERNEL, MASTER, STALE, OVERRUN} == {4, 8, 2, 1}


def test_recoupling_after_a_fault_does_not_move_the_robot(tmp_path):
    """S1, S3: architecture III, the operator 1 cm inside the fixture and holding still; a
    kernel fault holds the arm for 0.3 s (its proxy and the master's mapping stay where they
    are), the operator clears it (pedal up, clear-faults, pedal down). While held nothing moves;
    re-coupling keeps the operator's push (the force comes back) and the arm takes up where it
    was: on the noisy cloud the proxy wanders about a millimetre under a steady push, and the
    robot with it, before the fault as after (the old re-anchoring moved the robot to where the
    proxy had crept during the hold)."""
    cfg = balloon_config(tmp_path, arch="III")
    state = {}

    def brk(svc):
        state["good"] = svc.batch.step
        svc.batch.step = lambda *a, **k: (_ for _ in ()).throw(KernelError("injected"))

    def fix(svc):
        svc.batch.step = state["good"]

    t = np.array([0.0, 0.1, 0.8, 1.35, 1.45, 2.0])
    p = np.array([[0, 0, 0], [0, 0, 0], [0, 0, -0.074], [0, 0, -0.074], [0, 0, -0.074], [0, 0, -0.074]], float)
    master = ScriptedMaster(t, p, clutch=[1, 1, 1, 0, 1, 1])
    svc, rows, loop = in_contact_then(cfg, {1000: brk, 1300: fix, 1400: lambda s: s.clear_faults()},
                                      duration=2.0, master=master)
    cmd, xr, f = rows[:, 10:13], rows[:, 13:16], np.linalg.norm(rows[:, 16:19], axis=1)
    assert f[990] > 2.0 and f[1100] == 0.0                          # pushing; held
    wander = np.linalg.norm(cmd[500:1000] - cmd[999], axis=1).max()      # under the push, before
    assert np.linalg.norm(cmd[1000:1450] - cmd[1000], axis=1).max() < 1e-4   # held: nothing moves
    assert np.linalg.norm(xr[1100:1450] - xr[1100], axis=1).max() < 1e-4
    assert np.linalg.norm(cmd[1450:] - cmd[1449], axis=1).max() < max(wander, 1e-3) * 1.5
    assert f[-1] > 2.0 and svc.status()["hold"] == []                # the push is felt again
