"""Grasper model, implicit step vs RK4 (fig. A.1), parameters, plant loads."""
import math

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service.cable import model
from pointfence.service.cable.experiments import STIFF_CASE, STIFF_STEP_TORQUE, fig_a1
from pointfence.service.cable.params import ENCODER_RES, GrasperParams, true_params_at_tension
from pointfence.service.cable.plant import HuntCrossley, LinearSpring, SimulatedPlant


def test_smooth_sign_eq_4_19():
    import casadi as ca

    v = ca.SX.sym("v")
    f = ca.Function("s", [v], [model.smooth_sign(v)])
    for x in (-3.0, -0.05, 0.0, 0.02, 2.0):
        assert float(f(x)) == pytest.approx(10 * x / math.sqrt(1 + 100 * x * x))
    assert float(f(5.0)) > 0.99 and float(f(-5.0)) < -0.99


def test_dynamics_rest_and_cable_force():
    f = model.continuous_dynamics()
    p = GrasperParams().vector()
    assert np.allclose(np.array(f(np.zeros(4), 0.0, p)).ravel(), 0.0)
    # motor ahead of the link stretches the cable: motor decelerates, link accelerates
    xd = np.array(f([0.01, 0.0, 0.0, 0.0], 0.0, p)).ravel()
    assert xd[2] < 0 < xd[3]
    # a positive motor torque accelerates the motor
    assert float(f(np.zeros(4), 0.01, p)[2]) == pytest.approx(0.01 / GrasperParams().J_m)


def test_fig_a1_implicit_close_rk4_departs():
    r = fig_a1(duration=2.0)
    imp, rk4 = r["rms_implicit"], r["rms_rk4"]
    # implicit 1 ms step stays within 1e-4 rad of the tight-tolerance reference on both angles
    assert imp[0] < 1e-4 and imp[1] < 1e-4
    # explicit RK4 at 1 ms departs by orders of magnitude on the stiff (high Coulomb friction) case
    assert rk4[1] > 100 * imp[1] and rk4[1] > 5e-3
    assert r["reference"][-1, 1] > 0  # the step torque moved the link forward


def test_implicit_step_matches_reference_on_nominal_sine():
    p = GrasperParams().vector()
    t = np.arange(1000) * 1e-3
    u = 0.01 * np.sin(2 * np.pi * 2 * t)
    ref = model.reference_simulation(np.zeros(4), u, p)
    imp = model.simulate_steps(model.implicit_step(), np.zeros(4), u, p)
    assert np.abs(ref[:, 1]).max() > 0.02
    assert np.abs(imp[:, :2] - ref[:, :2]).max() < 1e-3


def test_params_validation_and_vector_roundtrip():
    p = GrasperParams()
    assert GrasperParams.from_vector(p.vector()) == p
    with pytest.raises(InputError, match="J_m"):
        GrasperParams(J_m=-1.0)
    with pytest.raises(InputError, match="k_e"):
        GrasperParams(k_e=float("nan"))
    with pytest.raises(InputError, match="13"):
        GrasperParams.from_vector(np.zeros(3))
    with pytest.raises(InputError, match="unknown grasper parameter"):
        p.replace(stiffness=1.0)
    with pytest.raises(InputError, match="tension"):
        true_params_at_tension(-5)
    lo, hi = true_params_at_tension(500), true_params_at_tension(1900)
    assert hi.k_e > lo.k_e and hi.Fc_m > lo.Fc_m and hi.Fc_l > lo.Fc_l and hi.Fv_m > lo.Fv_m


def test_plant_stiffness_law_is_logarithmic_fig_5_5a():
    """Tension is linear in ln(k_e) on the simulated plant (the relation the dissertation measured),
    so the chapter-5 logarithmic fit on exact k_e recovers any tension; b_e keeps a constant
    cable damping ratio (b_e ~ sqrt(k_e))."""
    from pointfence.service.cable.params import K_E_LOG_SLOPE_G, NOMINAL_TENSION_G, k_e_at_tension
    from pointfence.service.cable.tension import fit_tension_curve

    nom = GrasperParams()
    assert true_params_at_tension(NOMINAL_TENSION_G) == nom
    Ts = np.array([300.0, 432.5, 743.0, 1177.0, 1691.5, 2500.0])
    k = np.array([true_params_at_tension(t).k_e for t in Ts])
    assert np.allclose(k, [k_e_at_tension(t) for t in Ts])
    assert np.allclose(NOMINAL_TENSION_G + K_E_LOG_SLOPE_G * np.log(k / nom.k_e), Ts, atol=1e-9)
    # equal tension steps multiply k_e by equal factors (a power law would not)
    r = [k_e_at_tension(t + 400.0) / k_e_at_tension(t) for t in (400.0, 900.0, 1500.0)]
    assert np.allclose(r, r[0]) and r[0] == pytest.approx(math.exp(400.0 / K_E_LOG_SLOPE_G))
    curve = fit_tension_curve(Ts[[0, 2, 4, 5]], k[[0, 2, 4, 5]])
    assert curve.b == pytest.approx(K_E_LOG_SLOPE_G)
    for t, kk in zip(Ts, k):
        assert curve.estimate(kk) == pytest.approx(t, abs=1e-6)
    hi = true_params_at_tension(1929.0)
    assert hi.k_e / nom.k_e == pytest.approx(1.81, abs=0.01)  # chapter-5 stiffening 743 -> 1929 g
    assert hi.b_e / nom.b_e == pytest.approx(math.sqrt(hi.k_e / nom.k_e))


def test_plant_encoder_quantised_and_loads():
    pl = SimulatedPlant(torque_noise_std=0.0, x0=[0.1234, 0.0925, 0, 0])
    y = pl.measure()
    assert y <= 0.1234 < y + ENCODER_RES
    assert (y / ENCODER_RES) == pytest.approx(round(y / ENCODER_RES))
    # tissue: no torque before contact, a restoring (negative) torque after it
    pl = SimulatedPlant(contact=HuntCrossley(q_contact=0.1), torque_noise_std=0.0)
    for _ in range(200):
        pl.actuate(0.0)
    assert pl.env_torque == 0.0
    for _ in range(2000):
        pl.actuate(0.08)
    assert pl.link_angle > 0.1 and pl.env_torque < -0.01
    # the linear spring pulls back in proportion to the extension
    pl = SimulatedPlant(spring=LinearSpring(k=0.08, q0=0.0), torque_noise_std=0.0)
    for _ in range(3000):
        pl.actuate(0.03)
    assert pl.env_torque == pytest.approx(-0.08 * pl.link_angle, rel=1e-6)
    with pytest.raises(InputError, match="torque_noise_std"):
        SimulatedPlant(torque_noise_std=-1)
    with pytest.raises(InputError, match="HuntCrossley"):
        HuntCrossley(lever=-1)
