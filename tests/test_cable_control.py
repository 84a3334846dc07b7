"""UKF, identification, iLQG MPC closed loop, tension curve and alerts, 1 kHz controller thread."""
import time

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service.cable.controller import CableController
from pointfence.service.cable.identify import _run_stage, CABLE_PARAMS, INITIAL_GUESS, multisine
from pointfence.service.cable.ilqg import ILQGController, MPCConfig
from pointfence.service.cable.loop import ONLINE_UKF, CableLoop
from pointfence.service.cable.params import GrasperParams, NP
from pointfence.service.cable.plant import HuntCrossley, LinearSpring, SimulatedPlant
from pointfence.service.cable.sim import run_closed_loop, tracking_rms
from pointfence.service.cable.tension import TensionMonitor, fit_tension_curve
from pointfence.service.cable.trajectories import ramp_hold
from pointfence.service.cable.ukf import UKF, UKFConfig


def test_ukf_estimates_spring_torque_from_motor_encoder_only():
    truth = GrasperParams()
    plant = SimulatedPlant(truth, spring=LinearSpring(k=0.08, q0=0.0), seed=1)
    ukf = UKF(truth, ONLINE_UKF)
    ukf.reset(plant.measure())
    up, est, meas = 0.0, [], []
    for k in range(3000):
        ukf.step(up, plant.measure())
        plant.actuate(0.04)
        up = plant.applied_torque
        est.append(ukf.estimates()["tau_l"])
        meas.append(plant.env_torque)
    est, meas = np.array(est[-500:]), np.array(meas[-500:])
    assert meas.mean() < -0.02  # the spring is loaded
    assert abs(est.mean() - meas.mean()) < 0.15 * abs(meas.mean())
    assert abs(ukf.x[1] - plant.link_angle) < 0.01  # link angle estimated without a link sensor


def test_ukf_config_validation():
    with pytest.raises(InputError, match="unknown parameter 'stiffness'"):
        UKFConfig(estimate=("stiffness",))
    with pytest.raises(InputError, match="q_param has 3 entries"):
        UKFConfig(estimate=("k_e", "b_e"), q_param=(1, 2, 3))


def test_identification_stage1_moves_k_e_to_truth():
    truth = GrasperParams()
    plant = SimulatedPlant(truth, seed=2)
    st = _run_stage(plant, INITIAL_GUESS, CABLE_PARAMS, (0.5, 3.5), 10.0, 0.06, (1e-7,), 1e-4, seed=0)
    k0 = INITIAL_GUESS.k_e
    assert abs(st.final["k_e"] - truth.k_e) < 0.25 * truth.k_e
    assert abs(st.final["k_e"] - truth.k_e) < 0.5 * abs(k0 - truth.k_e)
    assert st.traces.shape == (1000, 2)
    with pytest.raises(InputError, match="band"):
        multisine(1.0, 3.0, 1.0, 0.1)


def test_friction_split_keeps_the_observable_motor_side_sum():
    from pointfence.service.cable.identify import split_like

    prior = GrasperParams(Fc_m=3e-3, Fc_l=2e-3, Fv_m=1e-4, Fv_l=1e-4)
    rho = prior.r_m / prior.r_l
    found = {"Fc_m": 6e-3, "Fc_l": 0.0, "Fv_m": 2e-5, "Fv_l": 3e-4}  # all Coulomb put on the motor
    out = split_like(found, prior)
    for m, l in (("Fc_m", "Fc_l"), ("Fv_m", "Fv_l")):
        assert out[m] + rho * out[l] == pytest.approx(found[m] + rho * found[l])
        assert out[m] / out[l] == pytest.approx(getattr(prior, m) / getattr(prior, l))


def test_mpc_respects_barrier_and_tracks_in_contact():
    p = GrasperParams().vector()
    for target, lo, hi in ((0.3, 0.15, 0.21), (1.0, 0.2, 0.26), (3.0, 0.2, 0.3 + 1e-12)):
        mpc = ILQGController()
        mpc.qd[:] = target  # far away: the soft barrier (a = 30) holds the torque near tau_max = 0.2
        for _ in range(20):
            u = mpc.solve(np.zeros(4), p)
        assert lo < u < hi, (target, u)
        assert np.all(np.abs(mpc.plan) < hi)
    with pytest.raises(InputError, match="horizon"):
        MPCConfig(horizon=0)

    truth = GrasperParams()
    qd = ramp_hold([-0.2, 0.25, 0.0], duration_ramp=0.5, duration_hold=0.6)
    res = run_closed_loop(SimulatedPlant(truth, contact=HuntCrossley(q_contact=0.0), seed=3), CableLoop(truth), qd)
    contact = res["q_l"] > 0.0
    assert contact.sum() > 300 and res["tau_env"].min() < -0.03  # real tissue load
    assert tracking_rms(res) < 0.012
    hold = (res["t"] > 2.35) & (res["t"] < 2.75)  # holding at 0.25 rad inside the tissue
    assert abs(np.mean(res["q_l"][hold]) - 0.25) < 0.02
    # the UKF's external torque matches the tissue torque it never saw
    assert abs(np.mean(res["tau_l_hat"][hold]) - np.mean(res["tau_env"][hold])) < 0.01
    assert np.percentile(res["compute_s"], 50) < 1e-3


def test_tension_fit_estimate_and_alerts():
    k = np.array([1.2e4, 1.6e4, 2.1e4, 2.9e4])
    t = 300.0 + 900.0 * np.log(k / 1e4)
    curve = fit_tension_curve(t, k)
    assert curve.estimate(2.0e4) == pytest.approx(300 + 900 * np.log(2.0), rel=1e-9)
    mon = TensionMonitor(curve, safe_min_g=600, safe_max_g=1000, axis="grasp")
    t_low, a_low = mon.check(1.3e4)
    assert a_low is not None and a_low.direction == "increase" and "grasp" in a_low.message
    assert "tighten" in a_low.message and t_low < 600
    _, a_high = mon.check(3.5e4)
    assert a_high.direction == "decrease" and "slacken" in a_high.message
    assert mon.check(2.0e4)[1] is None
    # one failed identification (an outlier) is dropped by the robust fit
    k_bad = np.append(k, 2.2e4)
    t_bad = np.append(t, 300.0 + 900.0 * np.log(3.0e4 / 1e4))
    rob = fit_tension_curve(t_bad, k_bad, robust=True)
    assert len(rob.k_e_points) == 4 and rob.b == pytest.approx(900.0)
    assert abs(fit_tension_curve(t_bad, k_bad).b - 900.0) > 10
    with pytest.raises(InputError, match="at least 2"):
        fit_tension_curve([700], [2e4])
    with pytest.raises(InputError, match="safe tension range"):
        TensionMonitor(curve, safe_min_g=900, safe_max_g=800)
    with pytest.raises(InputError, match="k_e"):
        curve.estimate(-1.0)


def test_table_5_1_log_fit_recovers_tension_from_identified_k_e():
    """Table 5.1 on the simulated plant: identify k_e (UKF, motor encoder only) at four known
    tensions, fit tension = a + b ln(k_e), then estimate the tension at the four table-5.1
    tensions (gauge mid-points) from k_e identified there. Each estimate must be within the
    error the dissertation measured at that tension (|534-432|, |1041-851|, |1370-1177|,
    |1623-1692| g, i.e. +23 %, +22 %, +16 %, -4 %). Shortened identification (15 s stages; the
    demo uses 30 s and gets -20, -19, +1, +36 g)."""
    from pointfence.service.cable.experiments import TABLE51_MEASURED
    from pointfence.service.cable.identify import identify
    from pointfence.service.cable.params import true_params_at_tension

    def k_id(t, seed):
        truth = true_params_at_tension(t)
        k = identify(SimulatedPlant(truth, seed=seed), duration1=15.0, duration2=15.0).params.k_e
        assert abs(k / truth.k_e - 1.0) < 0.15, (t, k, truth.k_e)  # bias +0..+12 %, rising with tension
        return k

    calib = (450.0, 900.0, 1400.0, 1900.0)
    curve = fit_tension_curve(calib, [k_id(t, 40 + i) for i, t in enumerate(calib)], robust=True)
    dissertation_estimate = (534.0, 1041.0, 1370.0, 1623.0)
    for i, ((lo, hi), est_d) in enumerate(zip(TABLE51_MEASURED, dissertation_estimate)):
        mid = 0.5 * (lo + hi)
        est = curve.estimate(k_id(mid, 60 + i))
        assert abs(est - mid) <= abs(est_d - mid), (mid, est, est_d)


def test_controller_thread_tracks_grasp_command_at_1khz():
    truth = GrasperParams()
    plant = SimulatedPlant(truth, contact=HuntCrossley(q_contact=0.15), seed=4)
    curve = fit_tension_curve([500, 1000, 1500], [1.5e4, 2.1e4, 2.6e4])
    ctl = CableController(plant, truth, tension_monitor=TensionMonitor(curve, 1200, 1600))
    ctl.start()
    try:
        ctl.set_grasp_command(0.3)
        # wait for 1000 ticks, however long this shared machine takes: timing belongs to
        # `pointfence bench cable`, not to tests
        deadline = time.monotonic() + 60.0
        while ctl.status().ticks < 1000 and time.monotonic() < deadline:
            time.sleep(0.02)
        s = ctl.status()
    finally:
        ctl.stop()
    assert s.running and s.fault is None
    assert s.ticks >= 1000
    assert abs(plant.link_angle - 0.3) < 0.03
    assert s.estimated_link_torque < -0.005  # pressing into the tissue
    assert 0 <= s.deadline_misses < 0.5 * s.ticks
    assert s.estimated_tension_g is not None and s.estimated_tension_g < 1200
    assert any("tighten" in a for a in s.alerts)
    with pytest.raises(InputError, match="finite"):
        ctl.set_grasp_command(float("nan"))


class _NaNAfter:
    """Plant wrapper whose encoder returns NaN after ``n`` reads; records applied torques."""

    def __init__(self, plant, n):
        self.plant, self.n, self.reads, self.torques = plant, n, 0, []

    def measure(self):
        self.reads += 1
        return float("nan") if self.reads > self.n else self.plant.measure()

    def actuate(self, tau):
        self.torques.append(tau)
        self.plant.actuate(tau)


def test_controller_nan_gives_zero_torque_and_alert():
    plant = _NaNAfter(SimulatedPlant(seed=5), 200)
    ctl = CableController(plant, GrasperParams())
    ctl.start()
    try:
        ctl.set_grasp_command(0.3)
        time.sleep(0.4)
        s = ctl.status()
    finally:
        ctl.stop()
    assert s.fault is not None and "not finite" in s.fault
    assert any(a.startswith("FAULT") for a in s.alerts)
    assert max(abs(t) for t in plant.torques[:150]) > 0.01  # it was driving before
    assert all(t == 0.0 for t in plant.torques[205:])      # zero torque after the NaN
    assert s.motor_torque == 0.0


def test_chapter5_nominal_parameters_degrade_at_high_tension_and_reidentified_restore():
    """Chapter 5 conditions: plant at 1929 g, states-only UKF, parameters held fixed. With the
    743 g parameters the model's cable is too soft; the re-identified (here: true) ones track."""
    from pointfence.service.cable.experiments import STATES_ONLY, peak_errors
    from pointfence.service.cable.params import true_params_at_tension
    from pointfence.service.cable.trajectories import hand_trajectory, peaks_of

    hand = hand_trajectory()
    truth = true_params_at_tension(1929.0)
    res = {}
    for lab, prm in (("nominal", true_params_at_tension(743.0)), ("adjusted", truth)):
        r = run_closed_loop(SimulatedPlant(truth, seed=7), CableLoop(prm, STATES_ONLY), hand)
        res[lab] = (tracking_rms(r), peak_errors(r, peaks_of(hand))["peak_error_rad"],
                    float(np.sqrt(np.mean((r["q_l_hat"] - r["q_l"]) ** 2))))
    (rms_n, pk_n, est_n), (rms_a, pk_a, est_a) = res["nominal"], res["adjusted"]
    assert rms_a < 0.003 and rms_n > 2.5 * rms_a, res
    assert pk_n > 2.0 * pk_a, res
    assert est_n > 3.0 * est_a, res  # the link estimate is what the wrong cable model spoils
