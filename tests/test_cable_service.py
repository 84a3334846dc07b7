"""The cable-driven grasper controller in the service (``[cable]``; service/cable_grasper.py, its
process cable_grasper_child.py, its block cable_block.py): settings refused with a message naming
the value; the controller tracks a grasp command on the simulated grasper (deterministic, in
process, on a fake clock; and live, in its process); faults (a NaN encoder reading, a late tick, a
killed or stopped process) are latched, named and give zero torque (SAFETY.md S3, S9); clearing
never makes the jaw jump (S1); ``command`` never waits for the process (S9: the haptic tick)."""
from __future__ import annotations

import json
import math
import threading
import time

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service import config
from pointfence.service.cable.params import DT, PARAM_NAMES, GrasperParams
from pointfence.service.cable.trajectories import fig48_trajectory
from pointfence.service.cable_block import HELD, LATE, GrasperBlock
from pointfence.service.cable_grasper import LOST, GrasperHost
from pointfence.service.cable_grasper_child import ChildGrasper
from pointfence.service.cable_settings import CableTable
from pointfence.service.clock import FakeClock
from pointfence.service.periodic import PeriodicLoop
from pointfence.service.schema import parse_table


def _cfg(tmp_path, cable: str):
    p = tmp_path / "scene.toml"
    p.write_text(config.embedded_defaults() + "\n[cable]\n" + cable)
    return config.load(p)


# --- settings ----------------------------------------------------------------------------------------
def test_a_cable_table_is_parsed_and_absent_means_no_grasper(tmp_path):
    assert config.load().cable is None
    cfg = _cfg(tmp_path, 'arm = 0\nsim_tension_g = 1200\njaw_min = -0.5\njaw_max = 0.9\ntension_min_g = 500\n')
    t = cfg.cable
    assert (t.arm, t.plant, t.params, t.sim_tension_g, t.jaw_min, t.jaw_max, t.tension_min_g) == \
        (0, "sim", "nominal", 1200.0, -0.5, 0.9, 500.0)


@pytest.mark.parametrize("text, match", [
    ('plant = "motor"', r"\[cable\] plant = 'motor'; expected one of 'sim'"),
    ("jaw_min = 0.5\njaw_max = 0.2", r"jaw_min = 0.5 rad is not below jaw_max = 0.2 rad"),
    ("tension_min_g = 1500", r"tension_min_g = 1500.0 g is not below tension_max_g = 1400.0 g"),
    ("watchdog_s = 1.0", r"\[cable\] watchdog_s = 1.0; expected a number > 0"),
    ("max_lateness_s = 0.5", r"\[cable\] max_lateness_s = 0.5"),
    ("max_lateness_s = nan", r"\[cable\] max_lateness_s = nan"),
    ("jaw_max = 3.0", r"\[cable\] jaw_max = 3.0"),
    ("arm = -1", r"\[cable\] arm = -1"),
    ("sim_tension = 700", r"unknown key 'sim_tension'; did you mean 'sim_tension_g'"),
    ('params = "/nonexistent/grasper.json"', r"params = '/nonexistent/grasper.json': cannot read it as JSON"),
    ('tension = false\ntension_curve = "c.json"', r"tension_curve = 'c.json' with tension = false"),
])
def test_bad_cable_settings_are_refused_naming_the_value(tmp_path, text, match):
    with pytest.raises(InputError, match=match):
        _cfg(tmp_path, text + "\n")


def test_a_parameter_file_must_hold_every_parameter_as_a_finite_number(tmp_path):
    good = {n: float(getattr(GrasperParams(), n)) for n in PARAM_NAMES}
    f = tmp_path / "p.json"
    f.write_text(json.dumps({**good, "k_e": 2.5e4}))
    assert parse_table(CableTable, {"params": str(f)}, "[cable]").params == str(f)
    for bad, match in (({k: v for k, v in good.items() if k != "J_l"}, "missing J_l"),
                       ({**good, "stiffness": 1.0}, "unknown stiffness"),
                       ({**good, "k_e": "high"}, "k_e = 'high'; expected a finite number"),
                       ({**good, "k_e": -1.0}, "k_e=-1.0 must be > 0")):
        f.write_text(json.dumps(bad))
        with pytest.raises(InputError, match=match):
            parse_table(CableTable, {"params": str(f)}, "[cable]")


def test_the_arm_must_exist():
    with pytest.raises(InputError, match=r"\[cable\] arm = 2; the service has 2 arm\(s\)"):
        CableTable(arm=2).check_arms(2)
    CableTable(arm=1).check_arms(2)


# --- the controller's tick, in process, on a fake clock ---------------------------------------------
class Bench:
    """``ChildGrasper`` on a private block, ticked on a FakeClock schedule with commands written
    into the block as the service writes them."""

    def __init__(self, **table):
        self.blk = GrasperBlock(None)
        self.g = ChildGrasper(self.blk, CableTable(**table))
        self.sched = PeriodicLoop(DT, FakeClock())
        C = self.C = self.blk.command_layout
        self.cmd = np.zeros(C.size)

    def tick(self, jaw=None, late_s=0.0, hold=0.0, clear=False):
        s = self.sched
        s.begin()
        if jaw is not None:
            self.cmd[self.C.seq] += 1
            self.cmd[self.C.jaw] = jaw
        self.cmd[self.C.hold] = hold
        if clear:
            self.cmd[self.C.clear_seq] += 1
        self.blk.cmd.write(self.cmd)
        s.late_s = late_s       # (a late start, as begin() measures it on a real clock)
        self.g.tick(s)
        s.end()
        return self.g


def test_the_controller_tracks_the_fig48_grasp_in_free_motion_and_in_tissue():
    """r.m.s. error of the true jaw (simulated plant) against the setpoint over the fig. 4.8
    ramp-and-hold: service/cable/README.md gives 0.0018 rad (free) and 0.0033 rad (tissue) with
    the MPC seeing the trajectory ahead; here it sees the present command only (a master's
    grasp has no future), measured 0.0021 / 0.0039 rad."""
    qd = fig48_trajectory()[:9000]
    for contact, bound in ((None, 0.004), (0.0, 0.006)):
        b = Bench(sim_contact_rad=contact, tension=False)
        err = np.empty(qd.size)
        for k, q in enumerate(qd):
            g = b.tick(q)
            err[k] = g.plant.link_angle - g.setpoint
        assert g.loop.fault is None
        rms = float(np.sqrt(np.mean(err ** 2)))
        assert 0.0005 < rms < bound, (contact, rms)
        assert np.max(np.abs(g.setpoint - qd[-1])) < 1e-12       # the setpoint reached the command


def test_commands_are_clamped_and_a_non_finite_one_is_ignored():
    b = Bench(jaw_min=-0.2, jaw_max=0.3, tension=False)
    for _ in range(400):
        g = b.tick(5.0)
    assert g.target == 0.3 and g.setpoint == pytest.approx(0.3)
    for _ in range(50):
        g = b.tick(math.nan)
    assert g.target == 0.3 and g.loop.fault is None


def test_a_nan_encoder_reading_latches_zero_torque_until_cleared_and_clearing_does_not_jump():
    b = Bench(tension=False)
    for _ in range(300):
        g = b.tick(0.4)
    assert abs(g.loop.u_prev) > 0 or abs(g.plant.link_angle - 0.4) < 0.01
    b.blk.ctl["inject"] = 1
    g = b.tick(0.4)
    assert "motor encoder reading is not finite" in g.loop.fault and g.loop.u_prev == 0.0
    assert g.plant.applied_torque == 0.0
    b.blk.ctl["inject"] = 0
    for _ in range(100):                     # the cause is gone; the fault stays latched
        g = b.tick(-0.4)
        assert g.loop.fault is not None and g.plant.applied_torque == 0.0
    jaw_now = g.plant.link_angle
    g = b.tick(-0.4, clear=True)
    assert g.loop.fault is None
    # S1: the setpoint restarts at the jaw and ramps to the command at JAW_SPEED (4 rad/s), no jump
    assert abs(g.setpoint - jaw_now) < 0.01
    for _ in range(20):
        prev = g.setpoint
        g = b.tick(-0.4)
        assert abs(g.setpoint - prev) <= 4.0 * DT + 1e-12


def test_a_late_tick_and_a_hold_from_the_service_latch_named_faults():
    b = Bench(max_lateness_s=0.02, tension=False)
    b.tick(0.2)
    g = b.tick(0.2, late_s=0.019)
    assert g.loop.fault is None
    g = b.tick(0.2, late_s=0.021)
    assert g.loop.fault.startswith("grasper loop late: a tick started 21.0 ms after its deadline")
    S = b.blk.state_layout
    row = np.zeros(S.size)
    assert b.blk.state.read(row) and row[S.fault_code] == LATE and row[S.motor_torque] == 0.0
    b.tick(0.2, clear=True)
    g = b.tick(0.2, hold=1.0)
    assert g.loop.fault.startswith("held by the service") and g.plant.applied_torque == 0.0
    assert b.blk.state.read(row) and row[S.fault_code] == HELD


def test_the_tension_estimate_and_its_alert_are_published():
    """Unknown (NaN) while the jaw is held (a held jaw does not show the cable); known once it is
    worked open and closed, and out of the range [900, 1400] g asked here: "tighten". The accuracy,
    the gate and the alerts: tests/test_cable_tension_online.py."""
    b = Bench(tension=True, tension_min_g=900.0, tension_max_g=1400.0)     # the plant is at 743 g
    S = b.blk.state_layout
    row = np.zeros(S.size)
    for _ in range(1200):
        g = b.tick(0.2)
    assert b.blk.state.read(row) and math.isnan(row[S.tension_g]) and row[S.tension_alert] == 0
    for k in range(6000):
        g = b.tick(0.3 * math.sin(2 * math.pi * 1.5 * k * DT))
    assert g.loop.fault is None
    assert b.blk.state.read(row)
    assert 670.0 < row[S.tension_g] < 820.0 and row[S.tension_alert] == 1
    from pointfence.service.cable_block import ALERT_TEXT, get_text

    assert "axis 'grasp': cable tension" in get_text(b.blk.text[ALERT_TEXT]) and "tighten" in \
        get_text(b.blk.text[ALERT_TEXT])


# --- the process ---------------------------------------------------------------------------------------
@pytest.fixture
def host():
    h = GrasperHost(CableTable(max_lateness_s=0.1, watchdog_s=0.05))
    h.start()
    yield h
    h.close()


def _drive(h, jaw, seconds):
    """Command ``jaw`` about every 0.5 ms for ``seconds`` (as the haptic tick would)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        h.command(jaw)
        time.sleep(0.0005)


def _until(h, cond, seconds=3.0, jaw=0.2):
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        h.command(jaw)
        if cond():
            return True
        time.sleep(0.001)
    return False


def test_the_process_tracks_a_held_grasp_and_publishes_its_estimate(host):
    _drive(host, 0.3, 1.5)
    s = host.snapshot()
    assert s.running and s.fault is None and s.commands > 100 and s.rejected == 0
    assert s.jaw_command == 0.3 and s.setpoint == pytest.approx(0.3)
    assert abs(s.sim_jaw - 0.3) < 0.01 and abs(s.jaw - s.sim_jaw) < 0.01     # tracked; the estimate agrees
    assert s.ticks > 500 and s.periods >= s.ticks and math.isfinite(s.link_torque)
    assert s.tension_g is None and s.k_e > 0        # a held jaw does not show the cable: unknown, not a guess
    host.command(math.nan)
    assert host.rejected == 1 and host.snapshot().jaw_command == 0.3


def test_a_nan_measurement_in_the_process_is_a_named_fault_with_zero_torque(host):
    _drive(host, 0.3, 0.3)
    host.inject("nan")
    assert _until(host, lambda: host.faulted)
    assert "motor encoder reading is not finite" in host.fault_reason
    s = host.snapshot()
    assert s.motor_torque == 0.0 and s.fault == host.fault_reason and s.alerts[0].startswith("FAULT: ")
    host.inject("none")
    host.clear_fault()
    assert _until(host, lambda: not host.faulted and host.snapshot().motor_torque != 0.0)


def test_a_killed_process_is_lost_and_cleared_by_a_restart(host):
    _drive(host, 0.3, 0.2)
    host.inject("kill")
    assert _until(host, lambda: host.faulted, 1.0)
    assert host.fault_reason.startswith(f"{LOST}: no tick for") and "process ended" in host.fault_reason
    s = host.snapshot()
    assert not s.running and s.motor_torque == 0.0
    host.clear_fault()                                  # never waits: the new process comes up later
    assert host.faulted and "restarting" in host.fault_reason
    assert _until(host, lambda: not host.faulted, 60.0)
    _drive(host, 0.1, 0.5)
    assert host.snapshot().running and host.snapshot().ticks > 100


def test_command_never_waits_for_a_stopped_process_which_then_holds_zero_torque(host):
    _drive(host, 0.3, 0.3)
    host.inject("stall")
    done = threading.Event()

    def tick_thread():
        for _ in range(300):                # 300 haptic ticks while the process is stopped
            host.command(0.2)
            time.sleep(0.001)
        done.set()

    th = threading.Thread(target=tick_thread)
    th.start()
    th.join(20.0)
    assert done.is_set()                    # (with a blocking command it would hang on the stopped child)
    assert host.faulted and "process alive" in host.fault_reason
    host.inject("none")                      # the process resumes: told to hold, it applies zero torque
    assert _until(host, lambda: host.snapshot().motor_torque == 0.0 and host.snapshot().ticks > 0)
    time.sleep(0.05)
    s = host.snapshot()
    assert s.motor_torque == 0.0 and host.faulted
    host.clear_fault()
    assert _until(host, lambda: not host.faulted and host.snapshot().motor_torque != 0.0)
