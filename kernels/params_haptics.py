"""Parameters of the proxy kernel and of force rendering (SPEC 2 and 3, dissertation table 2.1).

All lengths in metres, stiffness in N/m, damping in N s/m, forces in N, rates in Hz.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from .errors import InputError

MODES = ("rendering", "fixture")


@dataclass(frozen=True)
class HapticParams:
    """Everything the proxy kernel and the force renderer need.

    Proxy (chapter 2): a sphere of radius ``r1`` with bands ``r1 < r2 < r3`` around its centre.
    In ``"rendering"`` mode every point counts and point i's clearance is
    ``e_i = |X_p - P_i| - r1``; in ``"fixture"`` mode only protected points count and
    ``e_i = |X_p - P_i| - r_f(i)`` (SPEC 3). Either way the proxy is entrenched if some
    ``e_i < 0``, in contact if some ``e_i < r2 - r1``, free otherwise, and the normal (eq. 2.1)
    uses the points with ``e_i < r3 - r1``.

    Attributes:
        r1, r2, r3: proxy radius, contact radius, normal-estimation radius (5, 5.1, 10 mm).
        step: proxy step length delta (1 mm); at most ``r3 - r1`` so that the normal
            neighbourhood always holds every point a step can reach.
        max_steps: step budget of one haptic tick (all steps run inside one kernel launch).
            20 steps of 1 mm let a free proxy follow a HIP at 20 m/s, far beyond hand speeds.
        tolerance: a tick has converged when the step it would take is shorter than this (m).
        turn_back_cos: a tick has also converged when its next step would turn back against the
            previous sliding or free step, i.e. the cosine between the two directions is below
            this (-0.5: by more than 120 degrees). In a crease of the point cloud (between two
            fixture spheres, or where the normal estimate flips) the proxy would otherwise rock
            back and forth by tens of micrometres until the budget ran out: on the service's
            benchmark scene this ends ticks after 2.6 steps instead of 15.7 (of 20), with the
            proxy within 0.1 mm (p99) of where 80 steps of rocking leave it. Push-outs along the
            normal do not count as the previous step. -1 turns the rule off.
        slack: how deep (m) a sliding step may dig into the point cloud before the next
            step pushes the proxy back out along the normal. Steps are clipped (swept sphere)
            so that in a static scene no point ever comes closer than ``r1 - slack``
            (``r_f - slack`` for fixtures) to the proxy's centre; where the scene moved into the
            proxy, its deepest penetration never grows (kernels/proxy.py, step 3).
        margin: rounding margin of the clipping rule (1 um, about ten float32 roundings of a
            position near 1 m): a clipped step ends ``margin`` above its limit, and a point
            within ``margin`` of the limit counts as at the limit, so that no decision turns
            on the last bit of a clearance. At most (r2 - r1)/4.
        skin: margin (m) of the per-tick working set gathered around the proxy (performance
            only: results do not depend on it). 0.5 mm: every step scans fewer points, and a
            regather is cheap (dev VM, apc frame 49: 1-proxy tick p50 37 us against 41 us with
            2 mm, 64 proxies 590 against 670-720 us).
        mode: ``"rendering"`` (all points, chapter 2) or ``"fixture"`` (protected points with
            their own radius r_f, chapter 3).
        k: spring constant of eq. 2.2 (350 N/m). k_s: fixture spring constant (800 N/m).
        b: damping during contact (3 N s/m), applied as ``-b * xdot_hip``.
        fir_taps: length of the force low-pass FIR (26; 1 disables it).
        fir_cutoff_hz: its -6 dB cutoff (windowed sinc, Hamming window, unity DC gain).
        rate_hz: haptic tick rate (1000 Hz), for the FIR design and HIP velocity.
        max_force: saturation of the force magnitude (N; 3.3 N is a Phantom Omni's peak).
    """

    r1: float = 0.005
    r2: float = 0.0051
    r3: float = 0.010
    step: float = 0.001
    max_steps: int = 20
    tolerance: float = 1e-6
    turn_back_cos: float = -0.5
    slack: float = 0.0002
    margin: float = 1e-6
    skin: float = 0.0005
    mode: str = "rendering"
    k: float = 350.0
    k_s: float = 800.0
    b: float = 3.0
    fir_taps: int = 26
    fir_cutoff_hz: float = 100.0
    rate_hz: float = 1000.0
    max_force: float = 3.3

    def __post_init__(self):
        for key in ("r1", "r2", "r3", "step", "tolerance", "turn_back_cos", "slack", "margin", "skin", "k", "k_s",
                    "b", "fir_cutoff_hz", "rate_hz", "max_force"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise InputError(f"haptic parameter {key} = {v!r}; expected a finite number")
            object.__setattr__(self, key, float(v))
        for key in ("r1", "step", "tolerance", "margin", "rate_hz", "fir_cutoff_hz"):
            if getattr(self, key) <= 0:
                raise InputError(f"haptic parameter {key} = {getattr(self, key)!r}; expected > 0")
        for key in ("slack", "skin", "k", "k_s", "b", "max_force"):
            if getattr(self, key) < 0:
                raise InputError(f"haptic parameter {key} = {getattr(self, key)!r}; expected >= 0")
        if not self.r1 < self.r2 < self.r3:
            raise InputError(
                f"proxy radii r1 = {self.r1}, r2 = {self.r2}, r3 = {self.r3} m; expected r1 < r2 < r3 "
                "(proxy radius < contact radius < normal-estimation radius)")
        if self.step > self.r3 - self.r1:
            raise InputError(
                f"step = {self.step} m > r3 - r1 = {self.r3 - self.r1:.6g} m; a step must stay inside the "
                "normal neighbourhood (the dissertation uses 1 mm with r3 - r1 = 5 mm)")
        if self.margin > (self.r2 - self.r1) / 4:
            raise InputError(f"margin = {self.margin} m; expected at most (r2 - r1)/4 = {(self.r2 - self.r1) / 4:.6g} m "
                             "(a rounding margin, 1e-6 m by default)")
        if not -1.0 <= self.turn_back_cos <= 0.0:
            raise InputError(f"turn_back_cos = {self.turn_back_cos}; expected between -1 (rule off) and 0 (stop on "
                             "any turn by more than 90 degrees); -0.5 by default")
        if self.slack >= self.r1:
            raise InputError(f"slack = {self.slack} m; expected below r1 = {self.r1} m (0.2 mm by default)")
        if self.mode not in MODES:
            raise InputError(f"haptic mode {self.mode!r}; expected one of {', '.join(MODES)}")
        for key, lo in (("max_steps", 1), ("fir_taps", 1)):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise InputError(f"haptic parameter {key} = {v!r}; expected an integer >= {lo}")
        if self.fir_cutoff_hz >= self.rate_hz / 2:
            raise InputError(
                f"fir_cutoff_hz = {self.fir_cutoff_hz} Hz; expected below the Nyquist rate {self.rate_hz / 2} Hz")

    @property
    def band(self) -> float:
        """Thickness of the contact band, r2 - r1 (m)."""
        return self.r2 - self.r1

    @property
    def dead_band(self) -> float:
        """|X_hip - X_proxy| below which no spring force acts: (r1 + r2) / 2 in rendering mode
        (the spring is attached to the middle of the contact band, eq. 2.2); (r2 - r1) / 2 in
        fixture mode, where the proxy is a point resting mid-band outside the spheres."""
        return (self.r1 + self.r2) / 2 if self.mode == "rendering" else (self.r2 - self.r1) / 2

    @property
    def stiffness(self) -> float:
        return self.k if self.mode == "rendering" else self.k_s

    def reach(self, r_max: float = 0.0) -> float:
        """Largest centre-to-point distance that matters: r3 (rendering) or r_max + r3 - r1 (fixture)."""
        return self.r3 if self.mode == "rendering" else r_max + self.r3 - self.r1

    def replace(self, **changes) -> "HapticParams":
        return HapticParams(**{**asdict(self), **changes})
