"""Cable tension from the identified cable stiffness (chapter 5, fig. 5.5, table 5.1).

Calibration: identify k_e at several known tensions, fit tension = a + b ln(k_e).
Online: map the current k_e estimate through the curve and compare with the safe range; an
alert names the axis and whether to tighten or slacken its cable, and by about how much.
"""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from pointfence.kernels.errors import InputError

from ..files import write_atomic
from .params import DT, GrasperParams, true_params_at_tension


@dataclasses.dataclass(frozen=True)
class TensionCurve:
    """tension [g] = a + b ln(k_e [N/m])."""

    a: float
    b: float
    k_e_points: tuple = ()
    tension_points: tuple = ()

    def estimate(self, k_e: float) -> float:
        if not (math.isfinite(k_e) and k_e > 0):
            raise InputError(f"cable stiffness k_e={k_e!r} N/m must be a finite number > 0 to estimate tension")
        return self.a + self.b * math.log(k_e)

    def to_json(self) -> dict:
        return {"model": "tension_g = a + b*ln(k_e)", "a": self.a, "b": self.b,
                "k_e_points": list(self.k_e_points), "tension_points_g": list(self.tension_points)}

    def save(self, path) -> None:
        """Write the curve as JSON to ``path`` atomically; an existing file is kept as a backup
        (``path.bak``, ``.bak.2``, ...: ``service/files.write_atomic``, S8)."""
        try:
            write_atomic(path, json.dumps(self.to_json(), indent=2) + "\n")
        except OSError as e:
            raise InputError(f"tension calibration {path}: cannot write it ({e.strerror or e}); choose a file in a "
                             "folder you may write to") from None

    @classmethod
    def load(cls, path) -> "TensionCurve":
        try:
            d = json.loads(Path(path).read_text())
            return cls(float(d["a"]), float(d["b"]), tuple(d.get("k_e_points", ())),
                       tuple(d.get("tension_points_g", ())))
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise InputError(f"tension calibration {path}: cannot read it ({e}); expected JSON with keys a, b") from e


def fit_tension_curve(tensions_g, k_e, robust: bool = False) -> TensionCurve:
    """Least-squares logarithmic fit of known tensions [g] against identified k_e [N/m].

    With ``robust``, a point whose residual exceeds 3x the median absolute residual of the
    others is dropped and the fit repeated (one failed identification should not skew the
    curve); at least 3 points are kept. The curve lists only the points it kept.
    """
    t = np.asarray(tensions_g, dtype=float).ravel()
    k = np.asarray(k_e, dtype=float).ravel()
    if t.size != k.size:
        raise InputError(f"{t.size} tensions but {k.size} stiffness values; expected one k_e per tension")
    if t.size < 2:
        raise InputError(f"a tension fit needs at least 2 (tension, k_e) points, got {t.size}")
    if not (np.isfinite(t).all() and np.isfinite(k).all()) or (k <= 0).any() or (t <= 0).any():
        raise InputError(f"tensions {t.tolist()} g and k_e {k.tolist()} N/m must be finite and > 0")
    if np.ptp(np.log(k)) < 1e-9:
        raise InputError(f"all k_e values are equal ({k[0]} N/m): cannot fit tension against stiffness")
    while True:
        A = np.vstack([np.ones_like(k), np.log(k)]).T
        (a, b), *_ = np.linalg.lstsq(A, t, rcond=None)
        if not robust or t.size <= 3:
            break
        r = np.abs(t - (a + b * np.log(k)))
        worst = int(np.argmax(r))
        others = np.delete(r, worst)
        if r[worst] <= 3.0 * max(np.median(others), 1e-9):
            break
        t, k = np.delete(t, worst), np.delete(k, worst)
    return TensionCurve(float(a), float(b), tuple(k.tolist()), tuple(t.tolist()))


def k_e_seen(params: GrasperParams, dt: float = DT) -> float:
    """The stiffness [N/m] a filter whose model steps at ``dt`` with the implicit trapezoidal rule
    (``model.implicit_step_expr``) finds on a continuous cable of stiffness ``params.k_e``.

    The trapezoidal rule maps a mode of angular frequency w to (2/dt) atan(w dt/2): it runs slow,
    so the model needs a stiffer cable, by (tan(x)/x)^2 with x = w dt/2, to ring at the cable's
    frequency. w is the cable mode of eq. 4.4 linearised at rest, w^2 = 2 k_e (r_m^2/J_m + r_l^2/J_l)
    (spring force k_e (e^d - e^-d) ~ 2 k_e d). On the nominal grasper: +4.6 % at 743 g, +8.8 % at
    1929 g (the identification of service/cable/README.md measured +4.6 % and +8.4 %).
    """
    p = params
    w = math.sqrt(2.0 * p.k_e * (p.r_m ** 2 / p.J_m + p.r_l ** 2 / p.J_l))
    x = 0.5 * w * dt
    if not x < 0.5 * math.pi:
        raise InputError(f"cable mode {w / (2 * math.pi):.0f} Hz is beyond what a {dt * 1e3:g} ms model step resolves")
    return p.k_e * (math.tan(x) / x) ** 2


def sim_filter_curve(base: GrasperParams | None = None, lo_g: float = 300.0, hi_g: float = 2500.0) -> TensionCurve:
    """Tension of the simulated plant against the stiffness the 1 ms filter sees on it
    (``k_e_seen`` of ``params.true_params_at_tension``), fitted as tension = a + b ln(k_e) over
    [lo_g, hi_g]: what `pointfence calib tension` (identification through the same 1 ms model)
    finds on the simulated plant, without its identification scatter. Within 15 g of the exact
    mapping over the range; the plant's own law (``cable_settings.sim_curve``) would read the
    filter's stiffness 90 g (743 g) to 170 g (1929 g) high."""
    t = np.linspace(lo_g, hi_g, 45)
    k = np.array([k_e_seen(true_params_at_tension(x, base)) for x in t])
    return fit_tension_curve(t, k)


@dataclasses.dataclass(frozen=True)
class TensionAlert:
    axis: str
    direction: str          # "increase" or "decrease"
    estimated_g: float
    safe_min_g: float
    safe_max_g: float

    @property
    def message(self) -> str:
        if self.direction == "increase":
            by = self.safe_min_g - self.estimated_g
            what = "below"
            how = "tighten"
        else:
            by = self.estimated_g - self.safe_max_g
            what = "above"
            how = "slacken"
        return (f"axis '{self.axis}': cable tension ~{self.estimated_g:.0f} g is {what} the safe range "
                f"[{self.safe_min_g:.0f}, {self.safe_max_g:.0f}] g: {how} the cable "
                f"({self.direction} tension by at least ~{by:.0f} g)")


@dataclasses.dataclass(frozen=True)
class TensionMonitor:
    curve: TensionCurve
    safe_min_g: float = 600.0
    safe_max_g: float = 1400.0
    axis: str = "grasp"

    def __post_init__(self):
        if not (math.isfinite(self.safe_min_g) and math.isfinite(self.safe_max_g)
                and 0 < self.safe_min_g < self.safe_max_g):
            raise InputError(f"safe tension range [{self.safe_min_g}, {self.safe_max_g}] g must satisfy "
                             "0 < min < max")

    def check(self, k_e: float) -> tuple[float, TensionAlert | None]:
        """Estimated tension [g] for stiffness ``k_e`` and an alert if it is outside the range."""
        return self.judge(self.curve.estimate(k_e))

    def judge(self, t: float) -> tuple[float, TensionAlert | None]:
        """Tension ``t`` [g] and an alert if it is outside the range."""
        if t < self.safe_min_g:
            return t, TensionAlert(self.axis, "increase", t, self.safe_min_g, self.safe_max_g)
        if t > self.safe_max_g:
            return t, TensionAlert(self.axis, "decrease", t, self.safe_min_g, self.safe_max_g)
        return t, None


@dataclasses.dataclass(frozen=True)
class TensionGate:
    """When an online stiffness estimate may be read as a tension (units: samples, g, N m, rad/s).

    The cable stiffness is seen from the motor encoder only through the cable mode, which a slow
    grasp hardly excites, and only while the link feels no load the model lacks (tissue): the
    estimate is then a wrong number, not a noisy one (the fig. 4.8 ramps at 0.25-0.4 rad/s pulled it
    ~8 % low). The filter therefore learns only while the jaw moves faster than ``min_speed`` in
    free motion, and a tension is reported only from ``window`` consecutive free-motion samples,
    each taken while the jaw moved so for at least half of it, that agree within
    ``max_spread_g`` with a filter standard deviation below ``max_rel_std`` of k_e, the last
    moving one at most ``window`` samples ago; otherwise it is unknown (NaN) and no alert changes.
    """

    window: int = 20              # consecutive free, moving samples needed (one per 0.1 s: 2 s)
    max_spread_g: float = 60.0    # largest max - min of the window's tension samples [g]
    max_rel_std: float = 0.03     # largest filter std of k_e, relative to k_e
    contact_nm: float = 0.01      # |estimated external link torque| above this: contact [N m]
    min_speed: float = 1.0        # |estimated jaw velocity| above this: excited [rad/s]

    def __post_init__(self):
        if not (isinstance(self.window, int) and self.window >= 2):
            raise InputError(f"tension gate window={self.window!r} must be an integer >= 2 samples")
        for n in ("max_spread_g", "max_rel_std", "contact_nm", "min_speed"):
            v = getattr(self, n)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"tension gate {n}={v!r} must be a finite number > 0")


class OnlineTension:
    """The tension reported online: ``sample`` every ~0.1 s with the stiffness estimate, its
    std and whether the jaw was in free motion and moving over the interval; ``tension`` (g,
    NaN: unknown) and ``alert`` (latched: changed only by a confident estimate, so that an alert
    neither flickers nor disappears while the jaw rests or grasps) follow ``gate``."""

    def __init__(self, monitor: TensionMonitor, gate: TensionGate | None = None):
        self.monitor, self.gate = monitor, gate or TensionGate()
        self._ring = np.zeros(self.gate.window)
        self.reset()

    def reset(self) -> None:
        """Forget everything, the alert included."""
        self.restart()
        self.alert: TensionAlert | None = None

    def restart(self) -> None:
        """The stiffness filter restarted: the tension is unknown until a new window; the alert stays."""
        self._n = self._still = 0
        self.tension = math.nan

    def sample(self, k_e: float, k_e_std: float, free: bool, moving: bool) -> float:
        """One sample; returns the tension [g] or NaN (unknown). A jaw that stopped keeps its
        tension for one ``window`` of samples (a grasp pauses at its ends), then reads unknown."""
        g = self.gate
        ok = free and math.isfinite(k_e) and k_e > 0 and math.isfinite(k_e_std) and k_e_std < g.max_rel_std * k_e
        if not ok:
            self._n = 0                     # contact (or no estimate) breaks the window
            self.tension = math.nan
            return self.tension
        if moving:
            self._ring[self._n % g.window] = self.monitor.curve.estimate(k_e)
            self._n += 1
            self._still = 0
        else:
            self._still += 1
        if self._n < g.window or self._still >= g.window or float(np.ptp(self._ring)) > g.max_spread_g:
            self.tension = math.nan
            return self.tension
        self.tension, self.alert = self.monitor.judge(float(self._ring.mean()))
        return self.tension
