"""Reproduction of the dissertation's figures on the simulated plant (``pointfence cable demo``).

Figures: A.1 (implicit step vs RK4 vs reference), 4.3 (identified parameters), 4.4 (spring
torque vs estimated external torque), 4.8 (tracking in free motion and tissue contact),
5.1-5.4 (step and hand-trajectory tracking at four tensions, nominal vs re-identified
parameters), 5.5 and table 5.1 (tension from stiffness). Every function returns its numbers
in a dict; ``write_report`` writes the plots, ``report.md`` and ``metrics.json``.
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from . import model
from .identify import identify
from .loop import ONLINE_UKF, CableLoop
from .params import DT, K_E_LOG_SLOPE_G, GrasperParams, NOMINAL_TENSION_G, true_params_at_tension
from .plant import HuntCrossley, LinearSpring, SimulatedPlant
from .sim import rms, run_closed_loop, tracking_rms
from .tension import fit_tension_curve
from .trajectories import fig48_trajectory, hand_trajectory, peaks_of, step_trajectory
from .ukf import UKF, UKFConfig

#: Appendix A's stiff case: a grasper with high Coulomb friction, under a small step torque.
STIFF_CASE = GrasperParams(Fc_m=8.0e-3, Fc_l=6.0e-3)
STIFF_STEP_TORQUE = 0.004
#: Chapter 5 tension levels [g] and the table 5.1 evaluation tensions (mid-points of the gauge).
CH5_TENSIONS = (743.0, 988.0, 1575.0, 1929.0)
CALIB_TENSIONS = (450.0, 650.0, 900.0, 1150.0, 1400.0, 1650.0, 1900.0)
TABLE51_MEASURED = ((410, 455), (822, 880), (1152, 1202), (1677, 1706))
#: States-only estimator for chapter 5 (no external-torque estimate that would hide a model error).
STATES_ONLY = UKFConfig(estimate=(), q_param=(), p0_param=())
TISSUE = HuntCrossley(q_contact=0.0)


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def fig_a1(duration=2.0, params=STIFF_CASE, torque=STIFF_STEP_TORQUE) -> dict:
    n = int(round(duration / DT))
    u = np.full(n, torque)
    p = params.vector()
    ref = model.reference_simulation(np.zeros(4), u, p)
    imp = model.simulate_steps(model.implicit_step(), np.zeros(4), u, p)
    rk4 = model.simulate_steps(model.rk4_step(), np.zeros(4), u, p)
    return {"t": np.arange(n + 1) * DT, "reference": ref, "implicit": imp, "rk4": rk4,
            "rms_implicit": np.sqrt(((imp - ref) ** 2).mean(axis=0)).tolist(),
            "rms_rk4": np.sqrt(((rk4 - ref) ** 2).mean(axis=0)).tolist()}


def fig_4_4(params: GrasperParams, true_params: GrasperParams, duration=20.0, seed=3) -> dict:
    """Open-loop torque stretching a linear spring; the UKF estimates the link torque."""
    spring = LinearSpring(k=0.08, q0=0.0)
    plant = SimulatedPlant(true_params, spring=spring, seed=seed)
    ukf = UKF(params, ONLINE_UKF)
    n = int(round(duration / DT))
    t = np.arange(n) * DT
    u_cmd = 0.03 + 0.025 * np.sin(2 * np.pi * 0.25 * t) * (t > 1.0)
    est, meas = np.empty(n), np.empty(n)
    ukf.reset(plant.measure())
    up = 0.0
    for k in range(n):
        ukf.step(up, plant.measure())
        plant.actuate(u_cmd[k])
        up = plant.applied_torque
        est[k] = ukf.estimates()["tau_l"]
        meas[k] = plant.env_torque
    keep = t > 2.0
    return {"t": t, "tau_spring": -meas, "tau_l_hat": -est,
            "rms_error": rms((est - meas)[keep]), "mean_abs_spring": float(np.abs(meas[keep]).mean())}


def fig_4_8(params: GrasperParams, true_params: GrasperParams, qd=None, seed=4) -> dict:
    qd = fig48_trajectory() if qd is None else qd
    out = {}
    for name, contact in (("free", None), ("tissue", TISSUE)):
        plant = SimulatedPlant(true_params, contact=contact, seed=seed)
        res = run_closed_loop(plant, CableLoop(params), qd)
        free = res["q_l"] < TISSUE.q_contact
        out[name] = {
            "res": res,
            "rms": tracking_rms(res),
            "rms_free_motion": tracking_rms(res, mask=free),
            "rms_in_contact": tracking_rms(res, mask=~free) if contact is not None else None,
            "compute_p50_us": float(np.percentile(res["compute_s"], 50) * 1e6),
            "compute_p99_us": float(np.percentile(res["compute_s"], 99) * 1e6),
        }
    return out


def step_metrics(res: dict, target: float, t_step: float, hold_s: float = 0.2) -> dict:
    t, q = res["t"], res["q_l"]
    after = t >= t_step
    qa, ta = q[after], t[after] - t_step
    over = max(0.0, (qa.max() - target) / target * 100.0)
    rise = ta[np.argmax(qa >= 0.9 * target)] - ta[np.argmax(qa >= 0.1 * target)] if (qa >= 0.9 * target).any() else math.nan
    outside = np.where(np.abs(qa - target) > 0.05 * abs(target))[0]
    settle = ta[outside[-1]] if outside.size else 0.0
    hold = int(round(hold_s / DT))
    e_hold = q[-hold:] - target
    return {"overshoot_pct": float(over), "rise_time_s": float(rise), "settling_5pct_s": float(settle),
            "steady_state_error_rad": float(np.mean(e_hold)), "steady_state_rms_rad": rms(e_hold)}


def peak_errors(res: dict, peaks, window_s: float = 0.15) -> dict:
    """Fig. 5.4: how well the response reaches each peak of the desired trajectory.

    ``peak_error_rad``: mean over the peaks of |max of q_l within +-window of the desired peak -
    desired peak| (the response reaches its peak with some delay, as in fig. 5.3);
    ``peak_error_at_time_rad``: mean |q_l - q_ld| at the desired peak instants.
    """
    q, qd = res["q_l"], res["qd"]
    w = int(round(window_s / DT))
    reach = [abs(q[max(i - w, 0):i + w + 1].max() - qd[i]) for i in peaks]
    return {"peak_error_rad": float(np.mean(reach)),
            "peak_error_at_time_rad": float(np.mean(np.abs(q[peaks] - qd[peaks])))}


def chapter5(nominal: GrasperParams, adjusted: dict, truth_of=true_params_at_tension, seed=6,
             tensions=CH5_TENSIONS, with_tau_l=True) -> dict:
    """Step (fig. 5.1/5.2) and hand trajectory (fig. 5.3/5.4) at each tension.

    Chapter 5's conditions: the plant is at tension T; the controller's model holds either the
    nominal parameters (identified once at 743 g) or the ones re-identified at T ("adjusted"),
    and its UKF estimates the states only (the dissertation's on-line UKF ran "based upon the
    off-line parameter estimates"), so nothing on-line can absorb a model error.
    With ``with_tau_l`` the nominal parameters are also run with the chapter-4 estimator that
    augments the external link torque (hand trajectory only), to measure how much of the
    mismatch that estimate absorbs.
    """
    step = step_trajectory(math.radians(45), duration=1.0, delay=0.1)
    hand = hand_trajectory()
    pk = peaks_of(hand)
    out = {}
    for T in tensions:
        truth = truth_of(T)
        row = {}
        for label, prm in (("nominal", nominal), ("adjusted", adjusted[T])):
            r_step = run_closed_loop(SimulatedPlant(truth, seed=seed), CableLoop(prm, STATES_ONLY), step)
            r_hand = run_closed_loop(SimulatedPlant(truth, seed=seed + 1), CableLoop(prm, STATES_ONLY), hand)
            m = step_metrics(r_step, math.radians(45), 0.1)
            m.update(peak_errors(r_hand, pk))
            m["hand_rms_rad"] = tracking_rms(r_hand)
            m["hand_link_estimate_rms_rad"] = rms(r_hand["q_l_hat"] - r_hand["q_l"])
            row[label] = {"metrics": m, "step": r_step, "hand": r_hand}
        if with_tau_l:
            r = run_closed_loop(SimulatedPlant(truth, seed=seed + 1), CableLoop(nominal, ONLINE_UKF), hand)
            m = {"hand_rms_rad": tracking_rms(r), **peak_errors(r, pk)}
            row["nominal_tau_l"] = {"metrics": m, "hand": r}
        out[T] = row
    return {"tensions": out, "hand": hand, "peaks": pk}


def tension_calibration(identified_k: dict, eval_k: dict) -> dict:
    """Fit (fig. 5.5a) and evaluation at the table 5.1 tensions (fig. 5.5b)."""
    Ts = sorted(identified_k)
    curve = fit_tension_curve(Ts, [identified_k[t] for t in Ts], robust=True)
    rows = []
    for (lo, hi) in TABLE51_MEASURED:
        mid = 0.5 * (lo + hi)
        est = curve.estimate(eval_k[mid])
        k_true = true_params_at_tension(mid).k_e
        rows.append({"measured_g": [lo, hi], "true_g": mid, "k_e_identified": eval_k[mid], "k_e_true": k_true,
                     "k_e_error_pct": (eval_k[mid] / k_true - 1.0) * 100.0,
                     "estimated_g": est, "error_g": est - mid, "error_pct": (est - mid) / mid * 100.0})
    return {"curve": curve, "rows": rows, "all_points": {t: identified_k[t] for t in Ts}}


def run_all(quick: bool = False, log=print) -> dict:
    """Every experiment; ``quick`` shortens the identifications (for smoke tests)."""
    dur = 8.0 if quick else 30.0
    idk = {"duration1": dur, "duration2": dur}
    R = {}
    t0 = time.perf_counter()
    R["a1"] = fig_a1()
    log(f"fig A.1: rms error vs reference, q_l: implicit {R['a1']['rms_implicit'][1]:.2e} rad, "
        f"RK4 {R['a1']['rms_rk4'][1]:.2e} rad")
    truth = true_params_at_tension(NOMINAL_TENSION_G)
    ident = identify(SimulatedPlant(truth, seed=10), **idk)
    R["ident"] = ident
    nominal = ident.params
    log("fig 4.3: identified at 743 g: " + ", ".join(
        f"{n}={getattr(nominal, n):.4g} (true {getattr(truth, n):.4g})"
        for n in ("k_e", "b_e", "Fc_m", "Fc_l", "Fv_m", "Fv_l")))
    R["f44"] = fig_4_4(nominal, truth)
    log(f"fig 4.4: r.m.s. error of the estimated spring torque {R['f44']['rms_error']:.4f} N m "
        f"(mean spring torque {R['f44']['mean_abs_spring']:.4f} N m)")
    R["f48"] = fig_4_8(nominal, truth)
    log(f"fig 4.8: tracking r.m.s. error: free motion run {R['f48']['free']['rms']:.4f} rad; tissue run "
        f"{R['f48']['tissue']['rms']:.4f} rad (free part {R['f48']['tissue']['rms_free_motion']:.4f}, "
        f"in contact {R['f48']['tissue']['rms_in_contact']:.4f}); tick compute p50/p99 "
        f"{R['f48']['tissue']['compute_p50_us']:.0f}/{R['f48']['tissue']['compute_p99_us']:.0f} us")
    adjusted, k_id = {NOMINAL_TENSION_G: nominal}, {}
    for i, T in enumerate(CH5_TENSIONS[1:]):
        adjusted[T] = identify(SimulatedPlant(true_params_at_tension(T), seed=20 + i), **idk).params
    R["ch5"] = chapter5(nominal, adjusted)
    for T, row in R["ch5"]["tensions"].items():
        n_, a_, t_ = row["nominal"]["metrics"], row["adjusted"]["metrics"], row["nominal_tau_l"]["metrics"]
        log(f"fig 5.1-5.4 @ {T:.0f} g: hand-trajectory tracking r.m.s. nominal {n_['hand_rms_rad']:.4f} / "
            f"re-identified {a_['hand_rms_rad']:.4f} rad (nominal with the tau_l estimate {t_['hand_rms_rad']:.4f}); "
            f"peak error nominal {n_['peak_error_rad']:.4f} / re-identified {a_['peak_error_rad']:.4f} rad; step hold "
            f"r.m.s. nominal {n_['steady_state_rms_rad']:.4f} / re-identified {a_['steady_state_rms_rad']:.4f} rad")
    for i, T in enumerate(CALIB_TENSIONS):
        k_id[T] = identify(SimulatedPlant(true_params_at_tension(T), seed=40 + i), **idk).params.k_e
    eval_k = {}
    for i, (lo, hi) in enumerate(TABLE51_MEASURED):
        mid = 0.5 * (lo + hi)
        eval_k[mid] = identify(SimulatedPlant(true_params_at_tension(mid), seed=60 + i), **idk).params.k_e
    R["tension"] = tension_calibration(k_id, eval_k)
    # the same fit and evaluation on the plant's true k_e: the error the logarithmic curve makes
    # by itself (zero up to rounding: the simulated law is the logarithmic one of fig. 5.5a), so
    # the table's error is the identification's
    R["tension_exact"] = tension_calibration({T: true_params_at_tension(T).k_e for T in CALIB_TENSIONS},
                                             {m: true_params_at_tension(m).k_e for m in eval_k})
    for row, ex in zip(R["tension"]["rows"], R["tension_exact"]["rows"]):
        log(f"table 5.1: true {row['true_g']:.0f} g -> estimated {row['estimated_g']:.0f} g "
            f"({row['error_pct']:+.1f} %, {row['error_g']:+.0f} g; k_e identified {row['k_e_identified']:.0f} vs true "
            f"{row['k_e_true']:.0f} N/m ({row['k_e_error_pct']:+.1f} %); the fit on exact k_e: {ex['error_pct']:+.1f} %)")
    c = R["tension"]["curve"]
    log(f"table 5.1 curve (from identified k_e at {', '.join(f'{t:.0f}' for t in c.tension_points)} g): "
        f"tension = {c.a:.0f} + {c.b:.0f} ln(k_e); plant law: slope {K_E_LOG_SLOPE_G:.0f}")
    R["elapsed_s"] = time.perf_counter() - t0
    return R


def write_report(R: dict, out_dir) -> Path:
    plt = _plt()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figs = []

    def save(fig, name, caption):
        fig.tight_layout()
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        figs.append((name, caption))

    a = R["a1"]
    fig, axs = plt.subplots(2, 2, figsize=(10, 6), sharex=True)
    for i, (ax, lab) in enumerate(zip(axs.ravel(), ("q_m [rad]", "q_l [rad]", "qd_m [rad/s]", "qd_l [rad/s]"))):
        ax.plot(a["t"], a["reference"][:, i], "k-", lw=2, label="reference (CVODES BDF, tol 1e-10)")
        ax.plot(a["t"], a["implicit"][:, i], "g--", label="implicit 1 ms (15 Euler + Newton)")
        ax.plot(a["t"], a["rk4"][:, i], "r:", label="explicit RK4 1 ms")
        ax.set_ylabel(lab)
    axs[1, 0].set_xlabel("t [s]"); axs[1, 1].set_xlabel("t [s]"); axs[0, 0].legend(fontsize=7)
    save(fig, "fig_A1_solvers.png", "Fig. A.1: step torque response of the stiff (high Coulomb friction) case")

    ident = R["ident"]
    fig, axs = plt.subplots(2, 3, figsize=(11, 5))
    for j, n in enumerate(ident.stage1.names):
        axs[0, j].plot(ident.stage1.t, ident.stage1.traces[:, j]); axs[0, j].set_title(f"{n} (stage 1)")
    axs[0, 2].axis("off")
    for j, n in enumerate(ident.stage2.names[:3]):
        axs[1, j].plot(ident.stage2.t, ident.stage2.traces[:, j]); axs[1, j].set_title(f"{n} (stage 2)")
    save(fig, "fig_4_3_identification.png", "Fig. 4.3: UKF parameter estimates (stage 1: cable, 0.5-3.5 Hz; "
         "stage 2: friction, 0.2-1.2 Hz; Fv_l omitted from the plot)")

    f = R["f44"]
    fig, ax = plt.subplots(figsize=(8, 3.5))
    ax.plot(f["t"], f["tau_spring"], "k", label="spring torque (from link angle)")
    ax.plot(f["t"], f["tau_l_hat"], "r", alpha=0.8, label="UKF external torque estimate")
    ax.set_xlabel("t [s]"); ax.set_ylabel("torque [N m]"); ax.legend()
    save(fig, "fig_4_4_spring_torque.png", "Fig. 4.4: measured spring torque vs estimated external link torque")

    for name in ("free", "tissue"):
        r = R["f48"][name]["res"]
        fig, axs = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
        axs[0].plot(r["t"], r["qd"], "k--", label="desired"); axs[0].plot(r["t"], r["q_l"], "b", label="link")
        if name == "tissue":
            for ax in axs:
                ax.fill_between(r["t"], 0, 1, where=r["q_l"] > TISSUE.q_contact, color="0.85",
                                transform=ax.get_xaxis_transform())
        axs[0].set_ylabel("q_l [rad]"); axs[0].legend()
        axs[1].plot(r["t"], -r["tau_env"], "k", label="true load torque")
        axs[1].plot(r["t"], -r["tau_l_hat"], "r", label="estimated external torque")
        axs[1].set_ylabel("torque [N m]"); axs[1].set_xlabel("t [s]"); axs[1].legend()
        save(fig, f"fig_4_8_tracking_{name}.png",
             f"Fig. 4.8 ({name}): r.m.s. error {R['f48'][name]['rms']:.4f} rad; shaded: contact")

    ch = R["ch5"]["tensions"]
    fig, axs = plt.subplots(1, len(ch), figsize=(13, 3.5), sharey=True)
    for ax, (T, row) in zip(axs, ch.items()):
        for lab, st in (("nominal", "r"), ("adjusted", "b")):
            r = row[lab]["step"]
            ax.plot(r["t"], np.degrees(r["q_l"]), st, label=lab)
        ax.plot(r["t"], np.degrees(r["qd"]), "k--", lw=0.8)
        ax.set_xlim(0.05, 0.8); ax.set_title(f"{T:.0f} g"); ax.set_xlabel("t [s]")
    axs[0].set_ylabel("link angle [deg]"); axs[0].legend()
    save(fig, "fig_5_1_step.png", "Fig. 5.1: 45 deg step with nominal (743 g) and re-identified parameters")

    Ts = list(ch)
    fig, axs = plt.subplots(1, 3, figsize=(14, 3.5))
    for lab, st in (("nominal", "ro-"), ("adjusted", "bs-")):
        m = [ch[T][lab]["metrics"] for T in Ts]
        axs[0].plot(Ts, [math.degrees(x["steady_state_rms_rad"]) for x in m], st, label=lab)
        axs[1].plot(Ts, [math.degrees(x["peak_error_rad"]) for x in m], st, label=lab)
        axs[2].plot(Ts, [math.degrees(x["hand_rms_rad"]) for x in m], st, label=lab)
    axs[2].plot(Ts, [math.degrees(ch[T]["nominal_tau_l"]["metrics"]["hand_rms_rad"]) for T in Ts], "g^--",
                label="nominal + on-line tau_l (ch. 4 UKF)")
    axs[0].set_title("Fig. 5.2: step hold r.m.s. error [deg]"); axs[1].set_title("Fig. 5.4: mean peak error [deg]")
    axs[2].set_title("hand trajectory r.m.s. error [deg]")
    for ax in axs:
        ax.set_xlabel("tension [g]"); ax.legend(fontsize=7)
    save(fig, "fig_5_2_5_4_errors.png", "Figs. 5.2 and 5.4: step hold error, hand-trajectory peak error and "
         "r.m.s. error with nominal (743 g) and re-identified parameters, states-only UKF")

    T = max(ch)
    fig, ax = plt.subplots(figsize=(10, 3.5))
    r = ch[T]["nominal"]["hand"]
    ax.plot(r["t"], r["qd"], "k--", label="desired (hand)")
    ax.plot(r["t"], r["q_l"], "r", label="nominal parameters")
    ax.plot(r["t"], ch[T]["adjusted"]["hand"]["q_l"], "b", label="adjusted parameters")
    ax.set_xlabel("t [s]"); ax.set_ylabel("q_l [rad]"); ax.legend()
    save(fig, "fig_5_3_hand.png", f"Fig. 5.3: hand trajectory at {T:.0f} g")

    tc = R["tension"]
    curve = tc["curve"]
    fig, axs = plt.subplots(1, 2, figsize=(10, 3.8))
    k = np.array(curve.k_e_points)
    kk = np.linspace(k.min() * 0.8, k.max() * 1.1, 100)
    axs[0].plot(k, curve.tension_points, "ko", label="identified k_e at known tension")
    axs[0].plot(kk, curve.a + curve.b * np.log(kk), "b-", label=f"T = {curve.a:.0f} + {curve.b:.0f} ln k_e")
    axs[0].set_xlabel("k_e [N/m]"); axs[0].set_ylabel("tension [g]"); axs[0].legend()
    for i, row in enumerate(tc["rows"]):
        axs[1].plot([i], [row["true_g"]], "ks", ms=8, label="measured" if i == 0 else None)
        axs[1].vlines(i, *row["measured_g"], color="k")
        axs[1].plot([i], [row["estimated_g"]], "rx", ms=10, label="estimated" if i == 0 else None)
    axs[1].set_xlabel("test"); axs[1].set_ylabel("tension [g]"); axs[1].legend()
    save(fig, "fig_5_5_tension.png", "Fig. 5.5: (a) logarithmic fit, (b) tension estimated from stiffness")

    metrics = metrics_of(R)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    lines = ["# pointfence cable demo: chapters 4-5 and appendix A on the simulated plant", "",
             f"Run time {R['elapsed_s']:.1f} s. All numbers below are from this run (metrics.json).", "",
             "## Headline", "",
             f"- Tracking r.m.s. error (fig. 4.8 trajectory, identified parameters, no tissue knowledge): "
             f"free-motion run **{metrics['tracking_rms_free_rad']:.4f} rad**, tissue run "
             f"**{metrics['tracking_rms_tissue_rad']:.4f} rad** (in contact {metrics['tracking_rms_in_contact_rad']:.4f} rad). "
             "Dissertation: 0.0069 rad.",
             f"- Control tick (UKF + 3 iLQG iterations) compute p50/p99: {metrics['tick_compute_p50_us']:.0f} / "
             f"{metrics['tick_compute_p99_us']:.0f} us.",
             f"- Fig. A.1 r.m.s. q_l error vs reference: implicit {metrics['a1_rms_ql_implicit']:.2e} rad, RK4 "
             f"{metrics['a1_rms_ql_rk4']:.2e} rad.", "",
             "## Table 5.1 (simulated)", "",
             f"Curve fitted to the k_e identified at {', '.join(f'{t:.0f}' for t in tc['curve'].tension_points)} g: "
             f"tension = {tc['curve'].a:.0f} + {tc['curve'].b:.0f} ln(k_e) (plant law slope {K_E_LOG_SLOPE_G:.0f} g).", "",
             "| measured [g] | true [g] | k_e identified / true [N/m] | k_e error | estimated [g] | error |",
             "|---|---|---|---|---|---|"]
    for row in tc["rows"]:
        lines.append(f"| {row['measured_g'][0]} - {row['measured_g'][1]} | {row['true_g']:.0f} | "
                     f"{row['k_e_identified']:.0f} / {row['k_e_true']:.0f} | {row['k_e_error_pct']:+.1f} % | "
                     f"{row['estimated_g']:.0f} | {row['error_pct']:+.1f} % ({row['error_g']:+.0f} g) |")
    ex = R["tension_exact"]["rows"]
    lines += ["", "Error of the logarithmic fit by itself (fitted and evaluated on the plant's exact k_e): " +
              ", ".join(f"{r['true_g']:.0f} g {r['error_pct']:+.1f} %" for r in ex) +
              ". The simulated stiffness law is the logarithmic relation of fig. 5.5a, so the table's error is "
              "the identification's (the k_e bias that varies with tension).",
              "", "## Chapter 5: nominal vs re-identified (adjusted) parameters", "",
              "Plant at the tension T; controller model with the 743 g parameters (nominal) or those "
              "re-identified at T (adjusted); the on-line UKF estimates the states only, as in chapter 5. "
              "Last column, for comparison: nominal parameters with the chapter-4 UKF (states + external link "
              "torque), whose torque estimate can take up part of a model error.", "",
              "| tension [g] | hand r.m.s. nominal [rad] | hand r.m.s. adjusted [rad] | peak err. nominal [deg] | "
              "peak err. adjusted [deg] | step hold r.m.s. nominal [deg] | step hold r.m.s. adjusted [deg] | "
              "link-estimate r.m.s. nominal / adjusted [deg] | overshoot adj. [%] | rise adj. [ms] | "
              "hand r.m.s. nominal + tau_l [rad] |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for T, row in ch.items():
        n_, a_ = row["nominal"]["metrics"], row["adjusted"]["metrics"]
        lines.append(f"| {T:.0f} | {n_['hand_rms_rad']:.4f} | {a_['hand_rms_rad']:.4f} | "
                     f"{math.degrees(n_['peak_error_rad']):.2f} | {math.degrees(a_['peak_error_rad']):.2f} | "
                     f"{math.degrees(n_['steady_state_rms_rad']):.2f} | {math.degrees(a_['steady_state_rms_rad']):.2f} | "
                     f"{math.degrees(n_['hand_link_estimate_rms_rad']):.2f} / "
                     f"{math.degrees(a_['hand_link_estimate_rms_rad']):.2f} | {a_['overshoot_pct']:.1f} | "
                     f"{a_['rise_time_s'] * 1e3:.0f} | {row['nominal_tau_l']['metrics']['hand_rms_rad']:.4f} |")
    lines += ["", "## Figures", ""]
    for name, cap in figs:
        lines += [f"![{cap}]({name})", "", f"*{cap}*", ""]
    (out / "report.md").write_text("\n".join(lines) + "\n")
    return out / "report.md"


def metrics_of(R: dict) -> dict:
    f48 = R["f48"]
    return {
        "tracking_rms_free_rad": f48["free"]["rms"],
        "tracking_rms_tissue_rad": f48["tissue"]["rms"],
        "tracking_rms_in_contact_rad": f48["tissue"]["rms_in_contact"],
        "tick_compute_p50_us": f48["tissue"]["compute_p50_us"],
        "tick_compute_p99_us": f48["tissue"]["compute_p99_us"],
        "a1_rms_ql_implicit": R["a1"]["rms_implicit"][1],
        "a1_rms_ql_rk4": R["a1"]["rms_rk4"][1],
        "spring_torque_rms_error_nm": R["f44"]["rms_error"],
        "identified_743g": {n: getattr(R["ident"].params, n) for n in ("k_e", "b_e", "Fc_m", "Fc_l", "Fv_m", "Fv_l")},
        "table_5_1": [{k: v for k, v in row.items()} for row in R["tension"]["rows"]],
        "tension_curve": R["tension"]["curve"].to_json(),
        "table_5_1_fit_on_exact_k_e": [{k: v for k, v in row.items()} for row in R["tension_exact"]["rows"]],
        "chapter5": {str(T): {lab: row[lab]["metrics"] for lab in ("nominal", "adjusted", "nominal_tau_l")}
                     for T, row in R["ch5"]["tensions"].items()},
        "elapsed_s": R["elapsed_s"],
    }
