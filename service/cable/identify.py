"""Two-stage identification of the grasper in free motion (section 4.4, fig. 4.3).

Stage 1: cable parameters (k_e, b_e) under a 0.5-3.5 Hz multisine torque.
Stage 2: friction coefficients (Fc_m, Fc_l, Fv_m, Fv_l) under a 0.2-1.2 Hz multisine, with the
cable parameters fixed at their stage-1 values. Both stages run the joint state/parameter UKF
on the motor encoder and the commanded torque only. A weak PD on the measured motor angle
keeps the grasper centred (its torque is part of the commanded torque the UKF sees).

From the motor encoder alone only the motor-side sum of the friction, F_m + (r_m/r_l) F_l, is
observable; how stage 2 splits it between motor and link drifts from run to run (often all of
it onto the motor), and a wrong split biases the next round's k_e (the model then mis-judges
the cable force that moves the link): without a fixed split k_e came out +4..+39 % over the
tensions of table 5.1 and chapter 5. ``identify`` therefore keeps the identified sum and splits
it in the ratio of the starting guess (a prior; on hardware, e.g. from a run with the link
side disconnected).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from pointfence.kernels.errors import InputError

from .params import DT, GrasperParams
from .plant import SimulatedPlant
from .ukf import UKF, UKFConfig

CABLE_PARAMS = ("k_e", "b_e")
FRICTION_PARAMS = ("Fc_m", "Fc_l", "Fv_m", "Fv_l")

#: Starting guess of the identification (deliberately off from the simulated truth).
INITIAL_GUESS = GrasperParams(k_e=1.0e4, b_e=2.0, Fc_m=2.0e-3, Fc_l=2.0e-3, Fv_m=1.0e-4, Fv_l=2.0e-4)


def multisine(duration: float, f_lo: float, f_hi: float, amplitude: float, n_freq: int = 8,
              seed: int = 0) -> np.ndarray:
    """Sum of ``n_freq`` sines in [f_lo, f_hi] Hz with random phases, peak ~``amplitude`` N m."""
    if not (0 < f_lo < f_hi) or not math.isfinite(f_hi):
        raise InputError(f"excitation band [{f_lo}, {f_hi}] Hz must satisfy 0 < f_lo < f_hi")
    if not (math.isfinite(duration) and duration > 0):
        raise InputError(f"excitation duration={duration!r} s must be > 0")
    rng = np.random.default_rng(seed)
    t = np.arange(int(round(duration / DT))) * DT
    f = np.linspace(f_lo, f_hi, n_freq)
    ph = rng.uniform(0, 2 * np.pi, n_freq)
    u = np.sin(2 * np.pi * f[None, :] * t[:, None] + ph[None, :]).sum(axis=1)
    return amplitude * u / np.abs(u).max()


@dataclasses.dataclass
class StageResult:
    names: tuple
    t: np.ndarray          # time of the traces [s]
    traces: np.ndarray     # (n_samples, n_params) estimates over time
    final: dict            # final estimates (mean over the last 20 %)


@dataclasses.dataclass
class IdentificationResult:
    params: GrasperParams
    stage1: StageResult
    stage2: StageResult


def _run_stage(plant: SimulatedPlant, start: GrasperParams, names, band, duration, amplitude,
               q_param, q_link, seed, kp=0.02, kd=0.0015) -> StageResult:
    ukf = UKF(start, UKFConfig(estimate=names, q_param=q_param, p0_param=(0.5,),
                               q_state=(1e-10, 1e-10, 2e-3, q_link)))
    exc = multisine(duration, band[0], band[1], amplitude, seed=seed)
    y_prev = plant.measure()
    for _ in range(int(1.0 / DT)):  # settle at rest under the PD before the filter starts
        y = plant.measure()
        plant.actuate(-kp * y - kd * (y - y_prev) / DT)
        y_prev = y
    ukf.reset(plant.measure())
    every = 10
    tr = np.empty((exc.size // every, len(names)))
    u_prev, y_prev = 0.0, plant.measure()
    for k in range(exc.size):
        y = plant.measure()
        ukf.step(u_prev, y)
        # weak PD on the encoder keeps the jaw centred; the UKF gets the total torque
        u = exc[k] - kp * y - kd * (y - y_prev) / DT
        y_prev = y
        plant.actuate(u)
        u_prev = plant.applied_torque
        if k % every == 0 and k // every < tr.shape[0]:
            est = ukf.estimates()
            tr[k // every] = [est[n] for n in names]
    if not np.isfinite(tr).all():
        raise InputError(f"identification of {names} diverged (non-finite estimates); check the excitation")
    tail = tr[int(0.8 * len(tr)):]
    final = {n: float(v) for n, v in zip(names, tail.mean(axis=0))}
    return StageResult(tuple(names), np.arange(tr.shape[0]) * DT * every, tr, final)


def split_like(friction: dict, prior: GrasperParams) -> dict:
    """Keep the motor-side sums Fc_m + (r_m/r_l) Fc_l and Fv_m + (r_m/r_l) Fv_l of ``friction``,
    split in the motor/link ratio of ``prior``."""
    rho = prior.r_m / prior.r_l
    out = dict(friction)
    for m, l in (("Fc_m", "Fc_l"), ("Fv_m", "Fv_l")):
        total = friction[m] + rho * friction[l]
        pm, pl = getattr(prior, m), getattr(prior, l)
        w = pm / (pm + rho * pl) if pm + rho * pl > 0 else 0.5
        out[m], out[l] = w * total, (1.0 - w) * total / rho
    return out


def identify(plant: SimulatedPlant, start: GrasperParams = INITIAL_GUESS, *, duration1: float = 30.0,
             duration2: float = 30.0, amplitude1: float = 0.06, amplitude2: float = 0.04,
             rounds: int = 3, seed: int = 0, split_friction: bool = True) -> IdentificationResult:
    """Run the two stages on ``plant`` (free motion) and return the identified parameters.

    With ``rounds`` > 1 the pair of stages is repeated, starting the cable stage from the
    friction found in the previous round (the first round's cable estimate is biased by the
    friction guess). The result carries the traces of the last round (stage-2 traces and
    ``final`` as the filter found them, before the split).

    With ``split_friction`` the identified motor/link friction pairs keep only their motor-side
    sum and are split in the ratio of ``start`` (see the module docstring).
    """
    if not (isinstance(rounds, int) and rounds >= 1):
        raise InputError(f"identification rounds={rounds!r} must be an integer >= 1")
    cur = start
    for r in range(rounds):
        s1 = _run_stage(plant, cur, CABLE_PARAMS, (0.5, 3.5), duration1, amplitude1, (1e-7,), 1e-4,
                        seed + 2 * r)
        cur = cur.replace(**{n: max(v, 1e-9) for n, v in s1.final.items()})
        s2 = _run_stage(plant, cur, FRICTION_PARAMS, (0.2, 1.2), duration2, amplitude2, (1e-8,), 1e-5,
                        seed + 2 * r + 1)
        fr = {n: max(v, 0.0) for n, v in s2.final.items()}
        if split_friction:
            fr = split_like(fr, start)
        cur = cur.replace(**fr)
    return IdentificationResult(cur, s1, s2)
