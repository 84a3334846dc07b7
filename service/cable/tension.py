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
        t = self.curve.estimate(k_e)
        if t < self.safe_min_g:
            return t, TensionAlert(self.axis, "increase", t, self.safe_min_g, self.safe_max_g)
        if t > self.safe_max_g:
            return t, TensionAlert(self.axis, "decrease", t, self.safe_min_g, self.safe_max_g)
        return t, None
