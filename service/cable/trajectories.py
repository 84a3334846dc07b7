"""Desired link-angle trajectories of chapters 4 and 5 (sampled at 1 kHz)."""
from __future__ import annotations

import math

import numpy as np

from pointfence.kernels.errors import InputError

from .params import DT


def _n(duration):
    if not (math.isfinite(duration) and duration > 0):
        raise InputError(f"trajectory duration={duration!r} s must be a finite number > 0")
    return int(round(duration / DT))


def ramp_hold(points, duration_ramp=1.0, duration_hold=1.5, start=0.0) -> np.ndarray:
    """Ramp-and-hold through ``points`` [rad] (fig. 4.8: free motion below the contact angle,
    compression above it), starting with a hold at ``start``."""
    segs = [np.full(_n(duration_hold), start)]
    prev = start
    for p in points:
        r = np.linspace(prev, p, _n(duration_ramp), endpoint=False)
        segs += [r, np.full(_n(duration_hold), p)]
        prev = p
    return np.concatenate(segs)


def fig48_trajectory() -> np.ndarray:
    """The compression task of fig. 4.8: free motion (q_l < 0), contact (q_l > 0) and back."""
    return ramp_hold([-0.25, 0.15, 0.3, -0.15, 0.25, -0.25, 0.0], duration_ramp=1.0, duration_hold=1.5)


def step_trajectory(angle=math.radians(45), duration=1.0, delay=0.1) -> np.ndarray:
    """Step of ``angle`` [rad] after ``delay`` [s] (fig. 5.1)."""
    n, nd = _n(duration), _n(delay)
    q = np.zeros(n)
    q[nd:] = angle
    return q


def hand_trajectory(duration=12.0, peaks=13, amplitude=0.45, seed=5) -> np.ndarray:
    """A recorded-hand-like trajectory (fig. 5.3): ``peaks`` smooth peaks of varying height and
    width over ``duration`` s, low-pass like a human hand (minimum-jerk segments)."""
    rng = np.random.default_rng(seed)
    n = _n(duration)
    knots_t = np.concatenate([[0.0], np.linspace(0.4, duration - 0.4, 2 * peaks), [duration]])
    knots_t[1:-1] += rng.uniform(-0.12, 0.12, 2 * peaks)
    vals = [0.0]
    for i in range(peaks):
        vals += [amplitude * rng.uniform(0.5, 1.0), amplitude * rng.uniform(-0.15, 0.2)]
    vals.append(0.0)
    t = np.arange(n) * DT
    q = np.empty(n)
    for a, b, va, vb in zip(knots_t[:-1], knots_t[1:], vals[:-1], vals[1:]):
        m = (t >= a) & (t < b)
        s = (t[m] - a) / (b - a)
        q[m] = va + (vb - va) * (10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5)
    q[t >= knots_t[-1]] = vals[-1]
    return q


def peaks_of(q: np.ndarray, min_separation=0.2) -> np.ndarray:
    """Indices of the local maxima of a trajectory (for the peak error of fig. 5.4)."""
    d = np.diff(q)
    idx = np.where((np.hstack([[0], d]) > 0) & (np.hstack([d, [0]]) <= 0))[0]
    out = []
    for i in idx:
        if not out or (i - out[-1]) * DT >= min_separation:
            out.append(i)
    return np.array(out, dtype=int)
