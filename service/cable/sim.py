"""Offline closed-loop and open-loop simulation on the simulated plant (no real-time pacing)."""
from __future__ import annotations

import numpy as np

from pointfence.kernels.errors import InputError

from .loop import CableLoop
from .plant import SimulatedPlant


def run_closed_loop(plant: SimulatedPlant, loop: CableLoop, qd: np.ndarray) -> dict:
    """Track the desired link angle ``qd`` (1 kHz samples); the MPC sees the next N samples.

    Returns arrays: t, qd, q_l (true), q_l_hat, q_m (true), tau, tau_l_hat, tau_env (true load
    torque), k_e_hat, compute_s (time of each tick's estimation + MPC).
    """
    qd = np.asarray(qd, dtype=float).ravel()
    if qd.size < 2 or not np.isfinite(qd).all():
        raise InputError(f"desired trajectory must be >= 2 finite samples; got {qd.size} samples")
    n, N = qd.size, loop.N
    padded = np.concatenate([qd, np.full(N + 1, qd[-1])])
    out = {k: np.empty(n) for k in ("q_l", "q_l_hat", "q_m", "tau", "tau_l_hat", "tau_env", "k_e_hat", "compute_s")}
    loop.reset(plant.measure())
    qwin = loop.qd
    track_k = "k_e" in loop.ukf.config.estimate
    for k in range(n):
        y = plant.measure()
        qwin[:] = padded[k:k + N + 1]
        u = loop.tick(y)
        out["compute_s"][k] = loop.last_compute_s
        out["q_l_hat"][k] = loop.ukf.x[1]
        out["tau_l_hat"][k] = loop.tau_l_estimate
        out["k_e_hat"][k] = loop.k_e_estimate if track_k else np.nan
        plant.actuate(u)
        out["q_l"][k] = plant.link_angle
        out["q_m"][k] = plant._x[0]
        out["tau"][k] = u
        out["tau_env"][k] = plant.env_torque
    out["t"] = np.arange(n) * plant.dt
    out["qd"] = qd
    return out


def rms(a) -> float:
    a = np.asarray(a, dtype=float)
    return float(np.sqrt(np.mean(a * a)))


def tracking_rms(res: dict, skip_s: float = 0.0, mask=None) -> float:
    """r.m.s. of q_l - q_ld (q_l one period after the command, as the plant has advanced)."""
    e = res["q_l"] - res["qd"]
    keep = res["t"] >= skip_s
    if mask is not None:
        keep &= mask
    return rms(e[keep])
