"""Issue 8 tests not covered by test_cable_control.py: a parameter leaving its physical range and a
compile failure end in a safe torque with an alert; UKF parameter convergence within 100 s of
simulated time; the external-torque estimate within 10 % at steady state; closed-loop tracking of
the fig. 4.8 ramp-and-hold trajectory through free motion and tissue within the seed's 0.0069 rad.
(A NaN encoder reading: ``test_cable_control.test_controller_nan_gives_zero_torque_and_alert``.)
"""
import time

import numpy as np
import pytest

from pointfence.service.cable import ilqg as ilqg_mod
from pointfence.service.cable import ukf as ukf_mod
from pointfence.service.cable.codegen import CodegenFallbackWarning
from pointfence.service.cable.controller import CableController
from pointfence.service.cable.identify import identify
from pointfence.service.cable.loop import ONLINE_UKF, ONLINE_UKF_TENSION, CableLoop
from pointfence.service.cable.params import NX, GrasperParams
from pointfence.service.cable.plant import HuntCrossley, LinearSpring, SimulatedPlant
from pointfence.service.cable.sim import run_closed_loop, tracking_rms
from pointfence.service.cable.trajectories import fig48_trajectory, ramp_hold
from pointfence.service.cable.ukf import UKF

TAU_MAX = 0.2


# -- bad input --------------------------------------------------------------------------------
def test_estimated_parameter_leaving_physical_range_trips_to_zero_torque():
    """The tension UKF's k_e estimate driven below zero (as a diverging estimator would) must not
    reach the MPC: the loop latches a fault naming the parameter and holds zero torque."""
    truth = GrasperParams()
    plant = SimulatedPlant(truth, seed=8)
    loop = CableLoop(truth, ONLINE_UKF_TENSION)
    loop.reset(plant.measure())
    loop.qd[:] = 0.2
    torques = []
    for _ in range(300):
        u = loop.tick(plant.measure())
        plant.actuate(u)
        torques.append(u)
    assert loop.fault is None and max(abs(t) for t in torques) > 0.01  # it was driving
    j = loop.ukf.config.estimate.index("k_e")
    loop.ukf._xa[NX + j] = -0.3  # k_e = -3000 N/m
    assert loop.tick(plant.measure()) == 0.0
    assert loop.fault is not None and "k_e" in loop.fault and "physical range" in loop.fault
    for _ in range(20):  # latched: zero torque even once the estimate would look sane again
        loop.ukf._xa[NX + j] = 2.0
        assert loop.tick(plant.measure()) == 0.0
    loop.reset(plant.measure())
    assert loop.fault is None


class _CorruptKeAfter:
    """Plant wrapper: after ``n`` encoder reads the controller's k_e estimate is forced negative."""

    def __init__(self, plant, n):
        self.plant, self.n, self.reads, self.torques, self.ctl = plant, n, 0, [], None

    def measure(self):
        self.reads += 1
        if self.reads > self.n and self.ctl is not None:
            j = self.ctl.loop.ukf.config.estimate.index("k_e")
            self.ctl.loop.ukf._xa[NX + j] = -0.1
        return self.plant.measure()

    def actuate(self, tau):
        self.torques.append(tau)
        self.plant.actuate(tau)


def test_controller_parameter_out_of_range_holds_zero_torque_with_alert():
    plant = _CorruptKeAfter(SimulatedPlant(seed=9), 200)
    ctl = CableController(plant, GrasperParams(), ukf_config=ONLINE_UKF_TENSION)
    plant.ctl = ctl
    ctl.start()
    try:
        ctl.set_grasp_command(0.3)
        deadline = time.monotonic() + 60.0  # tick counts, not wall time: the machine may be loaded
        while ctl.status().ticks < 300 and time.monotonic() < deadline:
            time.sleep(0.02)
        s = ctl.status()
    finally:
        ctl.stop()
    assert s.ticks >= 300
    assert s.fault is not None and "k_e" in s.fault
    assert any(a.startswith("FAULT") and "k_e" in a for a in s.alerts)
    assert max(abs(t) for t in plant.torques[:150]) > 0.01
    assert all(t == 0.0 for t in plant.torques[205:])
    assert s.motor_torque == 0.0


@pytest.mark.parametrize("cc", ["/nonexistent/bin/cc", "false"])
def test_compile_failure_falls_back_and_controller_stays_within_tau_max(cc, tmp_path, monkeypatch):
    """No compiler / a failing compiler: the UKF and MPC run in CasADi's interpreter (warning),
    the controller reports a DEGRADED alert and still tracks with torque inside +-tau_max."""
    truth = GrasperParams()
    plant = SimulatedPlant(truth, seed=5)  # the plant (the "hardware") is not under test here
    monkeypatch.setenv("POINTFENCE_CACHE", str(tmp_path))
    monkeypatch.setenv("POINTFENCE_CC", cc)
    monkeypatch.setattr(ukf_mod, "_CACHE", {})  # force a fresh build in this process
    monkeypatch.setattr(ilqg_mod, "_CACHE", {})
    with pytest.warns(CodegenFallbackWarning):
        ctl = CableController(plant, truth)
    assert ctl.loop.ukf.how == "interpreted" and ctl.loop.mpc.how == "interpreted"
    assert not list(tmp_path.glob("**/*.so"))
    assert any(a.startswith("DEGRADED") and "interpreter" in a for a in ctl.status().alerts)
    res = run_closed_loop(plant, ctl.loop, ramp_hold([0.2], duration_ramp=0.3, duration_hold=0.3))
    assert ctl.loop.fault is None
    assert np.isfinite(res["tau"]).all() and np.abs(res["tau"]).max() <= TAU_MAX
    assert abs(res["q_l"][-1] - 0.2) < 0.01


# -- estimation -------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def identified():
    """Two-stage identification (section 4.4) on the nominal plant, 2 rounds of 19 s cable stage
    + 29 s friction stage, each after 1 s of settling: 100 s of simulated time in all."""
    truth = GrasperParams()
    res = identify(SimulatedPlant(truth, seed=23), duration1=19.0, duration2=29.0, rounds=2, seed=23)
    return truth, res.params


def test_ukf_parameters_converge_within_100s_to_10_percent(identified):
    """From a starting guess 50 % off (k_e, b_e) and 0-100 % off (friction), after 100 s of
    simulated time from motor encoder and commanded torque only:

    - meet 10 %: the cable stiffness k_e (+3.0 % here, -0.1..+3.4 % over five seeds; the 1 ms
      trapezoidal step's frequency warping biases it high, see README), and the motor-side
      friction sums Fc_m + (r_m/r_l) Fc_l (0.0 % here, within 0.4 %) and Fv_m + (r_m/r_l) Fv_l
      (+1.5 % here, within 6.4 %).
    - cannot: the cable damping b_e (-27 % here, -27..+5 % over the seeds tried): it acts on the
      relative motor/link cable velocity, which the 0.5-3.5 Hz excitation hardly moves (the cable
      mode is at ~80 Hz), so it is weakly observable from the motor encoder. Nor can the
      motor/link split of each friction pair: only the sum is observable, and ``identify`` splits
      it in the starting guess's ratio (Coulomb 1:1 vs the plant's 4:3: Fc_m ~-10 %, Fc_l ~+19 %).
    - the external torque tau_l: ``test_external_torque_estimate_within_10_percent_at_steady_state``.
    """
    truth, p = identified
    rho = truth.r_m / truth.r_l
    assert abs(p.k_e / truth.k_e - 1.0) < 0.10, p.k_e
    fc, fc_true = p.Fc_m + rho * p.Fc_l, truth.Fc_m + rho * truth.Fc_l
    fv, fv_true = p.Fv_m + rho * p.Fv_l, truth.Fv_m + rho * truth.Fv_l
    assert abs(fc / fc_true - 1.0) < 0.10, (fc, fc_true)
    assert abs(fv / fv_true - 1.0) < 0.10, (fv, fv_true)
    assert 0.3 < p.b_e / truth.b_e < 3.0  # moved, but not asserted to 10 % (see docstring)


@pytest.mark.parametrize("k_spring", [0.05, 0.08])
def test_external_torque_estimate_within_10_percent_at_steady_state(k_spring):
    """Constant 0.04 N m against a linear spring on the link (the fig. 4.4 validation load): the
    UKF's tau_l, from the motor encoder only, matches the spring torque over the last second."""
    truth = GrasperParams()
    plant = SimulatedPlant(truth, spring=LinearSpring(k=k_spring, q0=0.0), seed=1)
    ukf = UKF(truth, ONLINE_UKF)
    ukf.reset(plant.measure())
    up, est, true_tau = 0.0, [], []
    for _ in range(4000):
        ukf.step(up, plant.measure())
        plant.actuate(0.04)
        up = plant.applied_torque
        est.append(ukf.estimates()["tau_l"])
        true_tau.append(plant.env_torque)
    est, true_tau = np.array(est[-1000:]), np.array(true_tau[-1000:])
    assert true_tau.mean() < -0.03  # loaded
    assert abs(est.mean() - true_tau.mean()) <= 0.10 * abs(true_tau.mean())


# -- closed loop ------------------------------------------------------------------------------
def test_ramp_and_hold_through_free_motion_and_tissue_within_seed_rms(identified):
    """Fig. 4.8's compression task (free motion below 0 rad, Hunt-Crossley tissue above it), MPC
    with the parameters identified above and no tissue knowledge (the UKF's tau_l absorbs it):
    r.m.s. error <= 0.0069 rad (the seed's figure) and the torque inside +-tau_max."""
    _, params = identified
    truth = GrasperParams()
    res = run_closed_loop(SimulatedPlant(truth, contact=HuntCrossley(q_contact=0.0), seed=3),
                          CableLoop(params), fig48_trajectory())
    contact = res["q_l"] > 0.0
    assert contact.sum() > 2000 and res["tau_env"].min() < -0.03  # real time in the tissue
    assert (~contact).sum() > 2000
    assert tracking_rms(res) <= 0.0069
    assert tracking_rms(res, mask=contact) <= 0.0069
    assert np.isfinite(res["tau"]).all() and np.abs(res["tau"]).max() <= TAU_MAX
