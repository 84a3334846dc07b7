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
renderer is made (and when B grows), none per tick. Up to ``SCALAR_MAX`` proxies, steps 1-2
run as plain float arithmetic per proxy (a NumPy call costs about a microsecond whatever the
size, and these steps take some twenty of them); larger batches run them as array operations.
Both compute the same float64 expressions.
"""
from __future__ import annotations

import math

import numpy as np

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


#: batches up to this size compute spring and damping per proxy in plain floats
SCALAR_MAX = 8


class ForceRenderer:
    """Forces for B proxies, one ``update`` per tick; see the module docstring.

    Attributes after ``update``: ``forces`` (B, 3) N (filtered, saturated), ``raw`` (B, 3)
    before the filter, ``saturated`` (B,) bool.
    """

    def __init__(self, n: int, params: HapticParams | None = None):
        self.params = params if params is not None else HapticParams()
        p = self.params
        self.taps = fir_lowpass(p.fir_taps, p.fir_cutoff_hz, p.rate_hz)
        self._taps_oldest_first = np.ascontiguousarray(self.taps[::-1])
        self.n = 0
        self._cap = 0
        self.resize(n)

    def resize(self, n: int) -> None:
        """Change the number of proxies (filter history and HIP velocity restart)."""
        if not isinstance(n, (int, np.integer)) or n < 0:
            raise InputError(f"number of proxies = {n!r}; expected an integer >= 0")
        n = int(n)
        if n > self._cap:
            cap = max(n, 2 * self._cap, 1)
            T = self.taps.size
            # each raw force is written twice (rows i and i + T) so that the last T forces are
            # always one contiguous window of rows: the FIR is one matrix-vector product
            self._hist = np.zeros((2 * T, cap * 3))
            self._prev = np.zeros((cap, 3))
            self._v = np.zeros((cap, 3))
            self._vl = np.zeros(cap)
            self._mag = np.zeros(cap)
            self._tmp = np.zeros((cap, 3))
            self._contact = np.zeros(cap, bool)
            self._engaged = np.zeros(cap, bool)
            self._dot = np.zeros(cap)
            self._forces = np.zeros((cap, 3))
            self._raw = np.zeros((cap, 3))
            self._sat = np.zeros(cap, bool)
            self._cap = cap
        self.n = n
        self.reset()

    def reset(self) -> None:
        """Forget the filter history and the previous HIP (forces restart from zero)."""
        self._hist[:] = 0
        self._forces[:] = 0
        self._raw[:] = 0
        self._sat[:] = False
        self._head = 0
        self._have_prev = False

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
        n, p = self.n, self.params
        xp = check_points3(proxies, "proxy positions", n) if not _ok(proxies, n) else proxies
        xh = check_points3(hips, "hips", n) if not _ok(hips, n) else hips
        st = np.asarray(states)
        if st.shape != (n,):
            raise InputError(f"states shape {st.shape}; expected ({n},)")
        if n <= SCALAR_MAX:
            self._spring_damping_scalar(xp, xh, st, n)
        else:
            v, vl, mag, tmp = self._v[:n], self._vl[:n], self._mag[:n], self._tmp[:n]
            raw = self._raw[:n]
            np.subtract(xh, xp, out=v)
            np.einsum("ij,ij->i", v, v, out=vl)
            np.sqrt(vl, out=vl)
            # spring: -(v/|v|) k (|v| - db) beyond the dead band; mag = k (|v| - db) / |v| or 0
            db = p.dead_band
            np.subtract(vl, db, out=mag)
            np.maximum(mag, 0.0, out=mag)
            np.multiply(mag, p.stiffness, out=mag)
            engaged = self._engaged[:n]
            np.greater(vl, db, out=engaged)
            np.maximum(vl, db, out=vl)  # db > 0: no division by zero; mag is 0 inside the band
            np.divide(mag, vl, out=mag)
            np.multiply(v, mag[:, None], out=raw)
            np.negative(raw, out=raw)
            # damping during contact: -b * xdot_hip
            if self._have_prev and p.b > 0:
                contact = self._contact[:n]
                np.not_equal(st, FREE, out=contact)
                np.logical_and(contact, engaged, out=contact)
                np.subtract(xh, self._prev[:n], out=tmp)
                np.multiply(tmp, contact[:, None], out=tmp)
                np.multiply(tmp, p.b * p.rate_hz, out=tmp)
                np.subtract(raw, tmp, out=raw)
                # unilateral contact: damping may cancel the spring but never pull the HIP inwards,
                # i.e. the component along the spring direction -v/|v| stays >= 0
                dot = self._dot[:n]
                np.einsum("ij,ij->i", raw, v, out=dot)  # raw . v  (> 0: pulling inwards)
                np.maximum(dot, 0.0, out=dot)
                np.multiply(dot, engaged, out=dot)
                np.divide(dot, vl, out=dot)
                np.divide(dot, vl, out=dot)
                np.multiply(v, dot[:, None], out=tmp)
                np.subtract(raw, tmp, out=raw)
        self._prev[:n] = xh
        self._have_prev = True
        raw = self._raw[:n]
        tmp, vl = self._tmp[:n], self._vl[:n]
        # FIR over the last T raw forces (ring buffer; taps[0] weighs the newest)
        T, h = self.taps.size, self._head
        flat = raw.reshape(-1)
        self._hist[h, : 3 * n] = flat
        self._hist[h + T, : 3 * n] = flat
        out = self._forces[:n]
        np.matmul(self._taps_oldest_first, self._hist[h + 1: h + T + 1, : 3 * n], out=out.reshape(-1))
        self._head = (h + 1) % T
        # saturation, keeping the direction
        np.einsum("ij,ij->i", out, out, out=vl)
        np.sqrt(vl, out=vl)
        sat = self._sat[:n]
        np.greater(vl, p.max_force, out=sat)
        if sat.any():
            np.maximum(vl, p.max_force, out=vl)
            np.divide(p.max_force, vl, out=vl)
            np.multiply(out, vl[:, None], out=out)
        return out

    def _spring_damping_scalar(self, xp, xh, st, n: int) -> None:
        """Steps 1-2 for a small batch, proxy by proxy in floats, into ``self._raw``."""
        p = self.params
        db, k = p.dead_band, p.stiffness
        damp = self._have_prev and p.b > 0
        bk = p.b * p.rate_hz
        hl, pl, sl = xh.tolist(), xp.tolist(), st.tolist()
        prev = self._prev[:n].tolist() if damp else None
        rows = []
        for i in range(n):
            hx, hy, hz = hl[i]
            qx, qy, qz = pl[i]
            vx, vy, vz = hx - qx, hy - qy, hz - qz
            d = math.sqrt(vx * vx + vy * vy + vz * vz)
            engaged = d > db
            dd = d if engaged else db
            m = (d - db) * k / dd if engaged else 0.0
            fx, fy, fz = -(vx * m), -(vy * m), -(vz * m)
            if damp and engaged and sl[i] != FREE:
                px, py, pz = prev[i]
                fx -= (hx - px) * bk
                fy -= (hy - py) * bk
                fz -= (hz - pz) * bk
                dot = fx * vx + fy * vy + fz * vz          # > 0: the damped force pulls the HIP in
                if dot > 0.0:
                    c = dot / dd / dd
                    fx, fy, fz = fx - vx * c, fy - vy * c, fz - vz * c
            rows.append((fx, fy, fz))
        self._raw[:n] = rows


def _ok(a, n: int) -> bool:
    """Fast path: already a finite float (n, 3) array."""
    return (isinstance(a, np.ndarray) and a.shape == (n, 3) and a.dtype.kind == "f"
            and bool(np.isfinite(a.sum())))
