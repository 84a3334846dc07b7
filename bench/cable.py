"""`pointfence bench cable`: the 1 kHz cable controller against the peers a user would pick.

- UKF step (states + external link torque, L = 5, one generated C function per step; the filter
  of the control loop, ``loop.ONLINE_UKF``) vs filterpy's ``UnscentedKalmanFilter`` on the same
  discrete model: the same implicit 1 ms step (called as compiled C on preallocated buffers from
  filterpy's ``fx``, the cheapest way to give filterpy the model), the same sigma points
  (Merwe, alpha = 1, beta = 2, kappa = 0), noise, start and measurement sequence. Both run on one
  recorded encoder/torque sequence of a plant pulling a spring; the two estimates are compared
  (filterpy has no redraw of sigma points after the time update, so they differ slightly).
- MPC tick (iLQG, horizon 10, 3 iterations, compiled C) timed inside a closed-loop run of the
  fig. 4.8 ramp-and-hold trajectory through free motion and Hunt-Crossley tissue (true
  parameters), which also gives ``tracking_rms_rad``; peer: the same horizon and cost solved by
  CasADi Opti + Ipopt from states sampled along that run.
- First compile: a subprocess constructs a ``CableLoop`` (UKF + MPC: build, generate C, compile,
  load) with ``POINTFENCE_CACHE`` on an empty temporary folder; a second subprocess with the same
  folder is the cached start.

filterpy is needed only here: ``pip install filterpy``.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from .stats import pct

_START_CODE = r"""
import json, time
t0 = time.perf_counter()
from pointfence.service.cable import codegen
from pointfence.service.cable.loop import CableLoop
from pointfence.service.cable.params import GrasperParams
t1 = time.perf_counter()
loop = CableLoop(GrasperParams())
t2 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "start_s": t2 - t1, "ukf": loop.ukf.how, "mpc": loop.mpc.how}))
"""


def add_arguments(p):
    p.add_argument("--filterpy-steps", type=int, default=None,
                   help="filterpy UKF steps to time (default: repeat / 5, at least 200)")
    p.add_argument("--ipopt-solves", type=int, default=30, help="Ipopt MPC solves to time (0: skip)")
    p.add_argument("--no-compile", action="store_true", help="skip the first-compile / cached-start subprocesses")


def _us(samples):
    return round(pct(samples, 50) * 1e6, 2), round(pct(samples, 99) * 1e6, 2)


def _record_sequence(n: int, seed: int = 1):
    """Encoder readings and applied torques of a plant pulling a spring (the fig. 4.4 load)."""
    from pointfence.service.cable.params import GrasperParams
    from pointfence.service.cable.plant import LinearSpring, SimulatedPlant

    plant = SimulatedPlant(GrasperParams(), spring=LinearSpring(k=0.08, q0=0.0), seed=seed)
    y0 = plant.measure()
    ys, us = np.empty(n), np.empty(n)
    up = 0.0
    for k in range(n):
        ys[k], us[k] = plant.measure(), up
        plant.actuate(0.04 + 0.02 * np.sin(2 * np.pi * 2.0 * k * 1e-3))
        up = plant.applied_torque
    return y0, ys, us


def _bench_ukf(n: int, n_fp: int) -> dict:
    from pointfence.service.cable.codegen import BufferedCall, compile_functions
    from pointfence.service.cable.loop import ONLINE_UKF
    from pointfence.service.cable.model import implicit_step
    from pointfence.service.cable.params import DT, IDX, NX, GrasperParams
    from pointfence.service.cable.ukf import PARAM_SCALE, UKF

    try:
        from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter
    except ImportError as e:  # only the benchmark needs it
        raise SystemExit("bench cable compares against filterpy's UnscentedKalmanFilter: "
                         f"pip install filterpy ({e})") from e

    cfg = ONLINE_UKF
    truth = GrasperParams()
    y0, ys, us = _record_sequence(max(n, n_fp))

    ukf = UKF(truth, cfg)
    ukf.reset(y0)
    x_init, P_init = ukf._xa.copy(), ukf._P.copy()
    for k in range(50):  # warm up caches and branch predictors, then restart
        ukf.step(us[k], ys[k])
    ukf.reset(y0)
    perf = time.perf_counter
    t_pf = np.empty(n)
    xs_pf = np.empty((n, ukf.L))
    for k in range(n):
        t0 = perf()
        ukf.step(us[k], ys[k])
        t_pf[k] = perf() - t0
        xs_pf[k] = ukf._xa
    assert ukf.healthy()

    # filterpy on the same discrete model: the implicit step of appendix A, compiled C, no allocation
    fns, how = compile_functions([implicit_step()], "cable_step")
    step = BufferedCall(fns["cable_step"])
    sx, su, sp = step.args
    (sxn,) = step.res
    sp[:] = truth.vector()
    j_tau = IDX["tau_l"]
    scale = PARAM_SCALE["tau_l"]

    def fx(x, dt, u=0.0):
        sx[:] = x[:NX]
        su[0] = u
        sp[j_tau] = x[NX] * scale
        step()
        out = np.empty_like(x)
        out[:NX] = sxn
        out[NX:] = x[NX:]
        return out

    def hx(x):
        return x[:1]

    L = NX + len(cfg.estimate)
    points = MerweScaledSigmaPoints(L, alpha=1.0, beta=2.0, kappa=0.0)
    fp = UnscentedKalmanFilter(dim_x=L, dim_z=1, dt=DT, hx=hx, fx=fx, points=points)
    fp.Q = np.diag(list(cfg.q_state) + list(cfg.q_param))
    fp.R = np.array([[cfg.r_meas]])
    t_fp = np.empty(n_fp)
    xs_fp = np.empty((n_fp, L))
    z = np.empty(1)
    for rep in range(2):  # first pass: warm-up of 50 steps
        fp.x, fp.P = x_init.copy(), P_init.copy()
        for k in range(50 if rep == 0 else n_fp):
            z[0] = ys[k]
            t0 = perf()
            fp.predict(u=us[k])
            fp.update(z)
            if rep:
                t_fp[k] = perf() - t0
                xs_fp[k] = fp.x
    m = min(n, n_fp)
    tail = slice(m // 2, m)
    d_ql = np.abs(xs_pf[tail, 1] - xs_fp[tail, 1]).max()
    tau_pf, tau_fp = xs_pf[m - 1, NX] * scale, xs_fp[m - 1, NX] * scale
    p50, p99 = _us(t_pf)
    f50, f99 = _us(t_fp)
    return {
        "ukf_state_dim": L,
        "ukf_estimates": list(cfg.estimate),
        "ukf_codegen": ukf.how,
        "ukf_steps": n,
        "ukf_step_us_p50": p50,
        "ukf_step_us_p99": p99,
        "filterpy_steps": n_fp,
        "filterpy_model_codegen": how,
        "filterpy_ukf_step_us_p50": f50,
        "filterpy_ukf_step_us_p99": f99,
        "ukf_speedup_vs_filterpy_p50": round(f50 / p50, 1),
        "ukf_speedup_vs_filterpy_p99": round(f99 / p99, 1),
        "filterpy_agreement_q_l_max_diff_rad": float(f"{d_ql:.3g}"),
        "filterpy_agreement_tau_l_Nm": [round(float(tau_pf), 5), round(float(tau_fp), 5)],
    }


def _bench_mpc(n_ipopt: int) -> dict:
    from pointfence.service.cable.loop import CableLoop
    from pointfence.service.cable.params import GrasperParams
    from pointfence.service.cable.plant import HuntCrossley, SimulatedPlant
    from pointfence.service.cable.sim import run_closed_loop, tracking_rms
    from pointfence.service.cable.trajectories import fig48_trajectory

    truth = GrasperParams()
    loop = CableLoop(truth)
    solve = loop.mpc.solve
    perf = time.perf_counter
    times, samples = [], []

    def timed(x, p):
        t0 = perf()
        u = solve(x, p)
        times.append(perf() - t0)
        if len(times) % 600 == 300:
            samples.append((x.copy(), p.copy(), loop.qd.copy(), loop.mpc.plan.copy()))
        return u

    loop.mpc.solve = timed
    qd = fig48_trajectory()
    # warm-up run (first calls into the loaded libraries), then the measured one
    run_closed_loop(SimulatedPlant(truth, contact=HuntCrossley(q_contact=0.0), seed=3), loop, qd[:500])
    times.clear()
    samples.clear()
    res = run_closed_loop(SimulatedPlant(truth, contact=HuntCrossley(q_contact=0.0), seed=3), loop, qd)
    m50, m99 = _us(times)
    t50, t99 = _us(res["compute_s"])
    tau_max = loop.mpc.config.tau_max
    out = {
        "mpc_codegen": loop.mpc.how,
        "mpc_horizon": loop.mpc.N,
        "mpc_iterations": loop.mpc.config.iterations,
        "mpc_ticks": len(times),
        "mpc_tick_us_p50": m50,
        "mpc_tick_us_p99": m99,
        "control_tick_us_p50": t50,
        "control_tick_us_p99": t99,
        "tracking_case": "fig. 4.8 ramp-and-hold, tissue beyond 0 rad, true parameters",
        "tracking_rms_rad": round(tracking_rms(res), 5),
        "tracking_max_abs_torque_Nm": round(float(np.abs(res["tau"]).max()), 4),
        "tau_max_Nm": tau_max,
    }
    if n_ipopt > 0:
        out.update(_bench_ipopt(loop.mpc.config, samples[:n_ipopt]))
    return out


def _bench_ipopt(cfg, samples) -> dict:
    """The same horizon and cost (eq. 4.17/4.18) by CasADi Opti + Ipopt, multiple shooting."""
    import casadi as ca

    from pointfence.service.cable.ilqg import barrier
    from pointfence.service.cable.model import implicit_step
    from pointfence.service.cable.params import NP, NX

    N = cfg.horizon
    step = implicit_step()
    opti = ca.Opti()
    X, U = opti.variable(NX, N + 1), opti.variable(N)
    x0, qd, p = opti.parameter(NX), opti.parameter(N + 1), opti.parameter(NP)
    J = cfg.w_track * (X[1, N] - qd[N]) ** 2
    for i in range(N):
        J += cfg.w_track * (X[1, i] - qd[i]) ** 2 + cfg.w_tau * U[i] ** 2 + barrier(U[i], cfg.barrier_a, cfg.tau_max)
        opti.subject_to(X[:, i + 1] == step(X[:, i], U[i], p))
    opti.subject_to(X[:, 0] == x0)
    opti.minimize(J)
    opti.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes"})
    times, diffs, fails = [], [], 0
    for x, pv, q, plan in samples:
        opti.set_value(x0, x)
        opti.set_value(p, pv)
        opti.set_value(qd, q)
        opti.set_initial(U, plan)
        opti.set_initial(X, np.repeat(x[:, None], N + 1, axis=1))
        t0 = time.perf_counter()
        try:
            sol = opti.solve()
            u0 = float(np.atleast_1d(sol.value(U))[0])
        except RuntimeError:
            fails += 1
            u0 = float("nan")
        times.append(time.perf_counter() - t0)
        diffs.append(abs(u0 - plan[0]) if np.isfinite(u0) else np.nan)
    if not times:
        return {}
    return {
        "ipopt_solves": len(times),
        "ipopt_failures": fails,
        "ipopt_mpc_ms_p50": round(pct(times, 50) * 1e3, 3),
        "ipopt_mpc_ms_p99": round(pct(times, 99) * 1e3, 3),
        "ipopt_first_torque_vs_ilqg_Nm_median": float(f"{np.nanmedian(diffs):.3g}") if fails < len(times) else None,
    }


def _start(cache: str) -> dict:
    env = dict(os.environ, POINTFENCE_CACHE=cache)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", _START_CODE], env=env, capture_output=True, text=True, timeout=900)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"cable start subprocess failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}")
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    r["process_s"] = wall
    return r


def _bench_compile() -> dict:
    with tempfile.TemporaryDirectory(prefix="pointfence-cable-bench-") as tmp:
        first = _start(tmp)
        cached = _start(tmp)
    return {
        "first_compile_s": round(first["start_s"], 2),
        "first_compile_how": f"ukf {first['ukf']}, mpc {first['mpc']}",
        "first_compile_process_s": round(first["process_s"], 2),
        "cached_start_s": round(cached["start_s"], 3),
        "cached_start_how": f"ukf {cached['ukf']}, mpc {cached['mpc']}",
        "cached_start_process_s": round(cached["process_s"], 2),
    }


def run(args) -> dict:
    reps = args.repeat or 5000
    n_fp = args.filterpy_steps or max(200, reps // 5)
    out = {}
    out.update(_bench_ukf(reps, n_fp))
    out.update(_bench_mpc(args.ipopt_solves))
    if not args.no_compile:
        out.update(_bench_compile())
    checks = {
        "ukf_step_p99_le_100us": out["ukf_step_us_p99"] <= 100.0,
        "ukf_ge_10x_filterpy_p50": out["ukf_speedup_vs_filterpy_p50"] >= 10.0,
        "mpc_tick_p99_le_500us": out["mpc_tick_us_p99"] <= 500.0,
        "tracking_rms_le_0.0069rad": out["tracking_rms_rad"] <= 0.0069,
    }
    if "first_compile_s" in out:
        checks["first_compile_le_60s"] = out["first_compile_s"] <= 60.0
        checks["cached_start_no_compile"] = "compiled" not in out["cached_start_how"]
    out["targets_met"] = checks
    return out
