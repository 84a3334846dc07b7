"""Force rendering from proxy and HIP positions (SPEC 2 and 3, dissertation eq. 2.2).

Per haptic tick, for each of B proxies (v = X_hip - X_proxy):

1. spring, with a dead band: F = -(v / |v|) * k * (|v| - dead_band) when |v| > dead_band, else 0.
   Rendering mode: k = ``k`` (350 N/m) and dead_band = (r1 + r2) / 2 (eq. 2.2: the spring is
   attached to the middle of the contact band). Fixture mode: k = ``k_s`` (800 N/m) and
   dead_band = (r2 - r1) / 2, i.e. F = k_s (X_proxy - X_hip) once the HIP is past the point
   where the proxy rests (chapter 3);
2. damping during contact only: F -= b * xdot_hip while the proxy is in contact or entrenched
   and the spring is engaged (|v| > dead_band), with the HIP velocity from consecutive HIPs
   (zero on the first tick after ``reset``). Outside the dead band nothing holds the HIP, so
   a HIP leaving the surface is not pulled back in by the damper, and the damped force is
   unilateral: its component along the spring direction -v/|v| is clipped at zero;
3. a ``fir_taps``-tap FIR low-pass (windowed sinc, Hamming window, cutoff ``fir_cutoff_hz`` at
   ``rate_hz``, taps normalised to unit DC gain, so a constant force passes unchanged);
4. saturation: the vector is scaled down to ``max_force`` when longer (direction kept).

Non-finite inputs raise ``InputError`` and change nothing; a zero-length v gives zero spring
force (no division). The result is therefore always finite. All arrays are allocated when the
renderer is made (and when B grows), none per tick. The arithmetic runs in the compiled tick
core (``native/tick_core.c``, ``pf_forces_*``) in float64 on this class's arrays: a NumPy call
costs about a microsecond whatever the size, and these steps took some forty of them.
"""
from __future__ import annotations

import ctypes

import numpy as np

from pointfence.native import ForcesCore, fast, lib, ptr

from .errors import InputError
from .params_haptics import HapticParams
from .proxy import FREE, check_points3


def fir_lowpass(taps: int, cutoff_hz: float, rate_hz: float) -> np.ndarray:
    """Linear-phase low-pass FIR taps: windowed sinc (Hamming), unity gain at DC.

    ``cutoff_hz`` is the -6 dB point; the group delay is (taps - 1) / 2 samples (12.5 ms for
    the dissertation's 26 taps at 1 kHz). ``taps`` = 1 gives the identity filter.
    """
    if taps < 1:
        raise InputError(f"fir taps = {taps}; expected >= 1")
    if taps == 1:
        return np.ones(1)
    fc = cutoff_hz / rate_hz
    if not 0 < fc < 0.5:
        raise InputError(f"fir cutoff {cutoff_hz} Hz at {rate_hz} Hz; expected 0 < cutoff < rate / 2")
    k = np.arange(taps) - (taps - 1) / 2
    h = 2 * fc * np.sinc(2 * fc * k) * np.hamming(taps)
    return h / h.sum()


class ForceRenderer:
    """Forces for B proxies, one ``update`` per tick; see the module docstring.

    Attributes after ``update``: ``forces`` (B, 3) N (filtered, saturated), ``raw`` (B, 3)
    before the filter, ``saturated`` (B,) bool.
    """

    def __init__(self, n: int, params: HapticParams | None = None):
        self.params = params if params is not None else HapticParams()
        p = self.params
        self.taps = np.ascontiguousarray(fir_lowpass(p.fir_taps, p.fir_cutoff_hz, p.rate_hz), dtype=np.float64)
        self.core = ForcesCore(taps_n=self.taps.size, free_state=FREE, dead_band=p.dead_band, stiffness=p.stiffness,
                               b=p.b, rate_hz=p.rate_hz, max_force=p.max_force)
        self.core.taps = ptr(self.taps, np.float64, "taps")
        self.ref = ctypes.byref(self.core)
        self.n = 0
        self._cap = 0
        self.resize(n)

    def resize(self, n: int) -> None:
        """Change the number of proxies (filter history and HIP velocity restart)."""
        if not isinstance(n, (int, np.integer)) or n < 0:
            raise InputError(f"number of proxies = {n!r}; expected an integer >= 0")
        n = int(n)
        c = self.core
        if n > self._cap:
            cap = max(n, 2 * self._cap, 1)
            self._hist = np.zeros((self.taps.size, cap * 3))     # ring of the last T raw forces
            self._prev = np.zeros((cap, 3))
            self._forces = np.zeros((cap, 3))
            self._raw = np.zeros((cap, 3))
            self._sat = np.zeros(cap, bool)
            self._cap = c.cap = cap
            c.hist, c.prev = ptr(self._hist, np.float64, "hist"), ptr(self._prev, np.float64, "prev")
            c.raw, c.forces = ptr(self._raw, np.float64, "raw"), ptr(self._forces, np.float64, "forces")
            c.sat = ptr(self._sat, bool, "sat")
        self.n = c.n = n
        self.reset()

    def reset(self) -> None:
        """Forget the filter history and the previous HIP (forces restart from zero)."""
        lib.pf_forces_reset(self.ref)

    @property
    def forces(self) -> np.ndarray:
        return self._forces[: self.n]

    @property
    def raw(self) -> np.ndarray:
        return self._raw[: self.n]

    @property
    def saturated(self) -> np.ndarray:
        return self._sat[: self.n]

    def update(self, proxies, hips, states) -> np.ndarray:
        """Forces (B, 3) on the HIPs for this tick from proxy centres, HIPs (B, 3) and states (B,)."""
        n = self.n
        xp = np.asarray(proxies)
        if xp.dtype not in (np.float32, np.float64) or xp.shape != (n, 3):
            xp = check_points3(proxies, "proxy positions", n)
        xh = np.asarray(hips)
        if xh.dtype != np.float64 or xh.shape != (n, 3):
            xh = check_points3(hips, "hips", n).astype(np.float64)
        st = np.asarray(states)
        if st.shape != (n,):
            raise InputError(f"states shape {st.shape}; expected ({n},)")
        f32 = xp.dtype == np.float32
        rc = lib.pf_forces_update(self.ref, ptr(np.ascontiguousarray(xp), xp.dtype, "proxy positions"), int(f32),
                                  ptr(np.ascontiguousarray(xh), np.float64, "hips"),
                                  ptr(np.ascontiguousarray(st, dtype=np.int32), np.int32, "states"))
        if rc:
            check_points3(xp if rc == 1 else xh, "proxy positions" if rc == 1 else "hips", n)   # raises, naming the row
            raise InputError(f"{'proxy positions' if rc == 1 else 'hips'}: not finite")
        return self.forces

    def update_bound(self, proxies_f32, hips, states) -> int:
        """``update`` on pointers bound once (``native.ptr``: (B, 3) float32 proxies, (B, 3)
        float64 HIPs, (B,) int32 states): the tick's path. Returns the core's code (0: done,
        1: a proxy, 2: a HIP not finite; nothing changed then)."""
        return fast.pf_forces_update(self.ref, proxies_f32, 1, hips, states)


__all__ = ["ForceRenderer", "fir_lowpass"]
