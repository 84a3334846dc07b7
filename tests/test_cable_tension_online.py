"""The online cable-tension estimate of the service's grasper (chapter 5, fig. 5.5;
service/cable_grasper_child.py, service/cable/tension.py): on the simulated plant it reads the
true tension within 10 % at the nominal 743 g, at table 5.1's 1929 g and at a slack 450 g while the
jaw is worked in free motion; it reads "unknown" (NaN), never a wrong number, while the jaw is in
tissue or moves too slowly to show the cable; an alert is raised only for a cable really out of
range and stays while the tension is unknown. Deterministic: the grasper ticks on a fake clock.

10 %: the dissertation's own estimates were off by +23 %, +22 %, +16 % and -4 % (table 5.1), so
10 % asks for better than the chapter while leaving room for the estimator's scatter; here it reads
-0.0 %, -0.5 % and +4 % (743, 1929, 450 g)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from pointfence.service.cable.params import DT, true_params_at_tension
from pointfence.service.cable.tension import (OnlineTension, TensionGate, TensionMonitor, k_e_seen,
                                              sim_filter_curve)
from pointfence.service.cable.trajectories import fig48_trajectory
from pointfence.service.cable_block import ALERT_TEXT, GrasperBlock, get_text
from pointfence.service.cable_grasper_child import ChildGrasper
from pointfence.service.cable_settings import CableTable
from pointfence.service.clock import FakeClock
from pointfence.service.periodic import PeriodicLoop


class Bench:
    """``ChildGrasper`` on a private block, ticked on a FakeClock schedule."""

    def __init__(self, **table):
        self.blk = GrasperBlock(None)
        self.g = ChildGrasper(self.blk, CableTable(**table))
        self.sched = PeriodicLoop(DT, FakeClock())
        self.C = self.blk.command_layout
        self.cmd = np.zeros(self.C.size)
        self.S = self.blk.state_layout
        self.row = np.zeros(self.S.size)

    def tick(self, jaw):
        s = self.sched
        s.begin()
        self.cmd[self.C.seq] += 1
        self.cmd[self.C.jaw] = jaw
        self.blk.cmd.write(self.cmd)
        s.late_s = 0.0
        self.g.tick(s)
        s.end()
        return self.g

    def published(self):
        assert self.blk.state.read(self.row)
        return self.row[self.S.tension_g], int(self.row[self.S.tension_alert])


def grasp(seconds, hz=1.5, amplitude=0.3):
    """A jaw worked open and closed (rad, 1 kHz): peak speed 2.8 rad/s."""
    t = np.arange(int(round(seconds / DT))) * DT
    return amplitude * np.sin(2 * np.pi * hz * t)


def run(b, qd):
    """Tick through ``qd``; the published (tension, alert) every 0.1 s."""
    out = []
    for k, q in enumerate(qd):
        b.tick(q)
        if k % 100 == 99:
            out.append(b.published())
    assert b.g.loop.fault is None
    return out


# --- the estimate on the simulated plant -------------------------------------------------------------
@pytest.mark.parametrize("tension, alert", [(743.0, 0), (1929.0, 2), (450.0, 1)])
def test_the_tension_is_read_within_10_percent_in_free_motion(tension, alert):
    """Before the fix: 743 g read 581 g after the fig. 4.8 run and raised "tighten"."""
    b = Bench(sim_tension_g=tension)
    out = run(b, grasp(7.0))
    known = [t for t, _ in out if math.isfinite(t)]
    assert len(known) >= 10, out                              # it became known within the run ...
    assert all(abs(t - tension) < 0.1 * tension for t in known), (tension, known)   # ... and right
    t, code = out[-1]
    assert abs(t - tension) < 0.1 * tension and code == alert, (tension, out[-1])
    text = get_text(b.blk.text[ALERT_TEXT])
    if alert == 0:
        assert not text
    else:
        assert ("tighten" if alert == 1 else "slacken") in text and "axis 'grasp'" in text


def test_no_alert_at_nominal_tension_in_tissue_and_the_tension_is_unknown_in_contact():
    """The jaw worked into tissue beyond 0.1 rad at 743 g: the model lacks the tissue load, so the
    stiffness filter must not learn and no tension may be reported (before: 448 g and "tighten")."""
    b = Bench(sim_contact_rad=0.1)
    qd = grasp(7.0)
    contact_at = -10 ** 9
    for k, q in enumerate(qd):
        g = b.tick(q)
        if g.plant.env_torque != 0.0:
            contact_at = k
        if k % 100 == 99:
            t, code = b.published()
            assert code == 0, (k, t)
            if k - contact_at < 100:                            # touched tissue in this 0.1 s
                assert math.isnan(t), (k, t)
    assert contact_at > 6000                                    # it kept grasping tissue to the end


def test_no_alert_on_the_fig48_ramps_at_nominal_tension():
    """The fig. 4.8 ramps (0.25-0.4 rad/s) in free motion: too slow to show the cable, so the
    tension stays unknown rather than reading ~8 % low; before: 591 g and "tighten" at 11.8 s in
    free motion, "tighten" at 5.1 s in tissue beyond 0 rad."""
    for contact, n in ((None, 12500), (0.0, 6500)):
        b = Bench(sim_contact_rad=contact)
        out = run(b, fig48_trajectory()[:n])
        assert all(code == 0 for _, code in out), (contact, out)
        assert all(math.isnan(t) or abs(t - 743.0) < 74.3 for t, _ in out), (contact, out)


def test_the_service_sees_an_over_tight_cable_and_the_alert_stays_while_the_jaw_rests():
    """Before: 1429 g after the same grasp (k_e and tau_l in one filter), and a number, not
    "unknown", while the jaw rests."""
    b = Bench(sim_tension_g=1929.0)
    run(b, grasp(7.0))
    t, code = b.published()
    assert code == 2 and abs(t - 1929.0) < 192.9
    out = run(b, np.zeros(3000))                 # resting: unknown 2 s after the jaw stops, alert kept
    assert all(code == 2 for _, code in out)
    assert all(math.isnan(t) for t, _ in out[22:]), out
    assert "slacken" in get_text(b.blk.text[ALERT_TEXT])


# --- the pieces -------------------------------------------------------------------------------------
def test_the_filter_sees_the_cable_stiffer_by_the_1ms_step_as_identification_measured():
    """service/cable/README.md: identification through the 1 ms model needs k_e +4.6 % (743 g),
    +8.4 % (1929 g) to match the plant's cable mode."""
    for T, measured in ((743.0, 0.046), (1929.0, 0.084)):
        p = true_params_at_tension(T)
        assert k_e_seen(p) / p.k_e - 1.0 == pytest.approx(measured, abs=0.005)
    c = sim_filter_curve()
    for T in (300.0, 743.0, 1177.0, 1929.0, 2500.0):
        assert c.estimate(k_e_seen(true_params_at_tension(T))) == pytest.approx(T, abs=15.0)


def test_the_gate_reports_only_a_full_consistent_window_of_free_moving_samples():
    curve = sim_filter_curve()
    k743 = k_e_seen(true_params_at_tension(743.0))
    k450 = k_e_seen(true_params_at_tension(450.0))
    on = OnlineTension(TensionMonitor(curve, 600.0, 1400.0), TensionGate(window=5, max_spread_g=60.0))
    for _ in range(4):
        assert math.isnan(on.sample(k450, 100.0, free=True, moving=True))
    assert on.sample(k450, 100.0, True, True) == pytest.approx(450.0, abs=15.0) and on.alert.direction == "increase"
    assert math.isnan(on.sample(k743, 100.0, free=False, moving=True))     # contact: unknown ...
    assert on.alert is not None                                             # ... the alert stays
    for _ in range(4):
        on.sample(k743, 100.0, True, True)
    assert math.isnan(on.tension) and on.alert is not None                 # a new window must fill
    on.sample(k743, 100.0, True, True)
    assert on.tension == pytest.approx(743.0, abs=15.0) and on.alert is None
    on.sample(k743 * 1.2, 100.0, True, True)                                 # +365 g: inconsistent
    assert math.isnan(on.tension)
    on2 = OnlineTension(TensionMonitor(curve), TensionGate(window=2))
    for _ in range(3):
        on2.sample(k743, 0.5 * k743, True, True)                            # not confident: never known
    assert math.isnan(on2.tension)
    on2.sample(k743, 100.0, True, False)                                    # not moving: no new sample
    assert math.isnan(on2.tension)
    on3 = OnlineTension(TensionMonitor(curve), TensionGate(window=3))
    for _ in range(3):
        on3.sample(k743, 100.0, True, True)
    for _ in range(2):                                                       # paused: still known ...
        assert on3.sample(k743, 100.0, True, False) == pytest.approx(743.0, abs=15.0)
    assert math.isnan(on3.sample(k743, 100.0, True, False))                  # ... for one window only


@pytest.mark.parametrize("kw", [dict(window=1), dict(max_spread_g=0.0), dict(contact_nm=math.nan),
                                dict(min_speed=-1.0), dict(max_rel_std=math.inf)])
def test_a_bad_gate_is_refused_naming_the_value(kw):
    from pointfence.kernels.errors import InputError

    with pytest.raises(InputError, match=next(iter(kw))):
        TensionGate(**kw)
