"""Force rendering: eq. 2.2 with its dead band, contact damping, the FIR, saturation, fixtures."""
import numpy as np
import pytest

from pointfence.kernels import InputError
from pointfence.kernels.forces import ForceRenderer, fir_lowpass
from pointfence.kernels.haptics import CONTACT, FREE, HapticParams

P = HapticParams()


def settle(r, proxies, hips, states, n=None):
    for _ in range(n or P.fir_taps + 2):
        f = r.update(proxies, hips, states)
    return f.copy()


def test_fir_taps_design():
    h = fir_lowpass(26, 100.0, 1000.0)
    assert h.size == 26 and h.sum() == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(h, h[::-1])  # linear phase
    w = np.fft.rfftfreq(4096, 1e-3)
    H = np.abs(np.fft.rfft(h, 4096))
    assert H[w < 30].min() > 0.9  # passes the haptic band
    assert H[w > 250].max() < 0.02  # stops the proxy's step jitter
    assert np.allclose(fir_lowpass(1, 100.0, 1000.0), [1.0])


def test_spring_eq_2_2_with_dead_band():
    r = ForceRenderer(3, P.replace(max_force=100.0, b=0.0))
    proxies = np.zeros((3, 3))
    hips = np.array([[0, 0, -0.004], [0, 0, -0.02], [0.01, 0, -0.01]])  # inside band, 2 cm, oblique
    f = settle(r, proxies, hips, np.full(3, CONTACT))
    db = (P.r1 + P.r2) / 2
    np.testing.assert_allclose(f[0], 0, atol=1e-12)
    np.testing.assert_allclose(f[1], [0, 0, P.k * (0.02 - db)], rtol=1e-9)
    v = hips[2] - proxies[2]
    np.testing.assert_allclose(f[2], -v / np.linalg.norm(v) * P.k * (np.linalg.norm(v) - db), rtol=1e-9)
    np.testing.assert_allclose(r.raw, f, rtol=1e-9)  # constant input: the FIR passes it unchanged


def test_saturation_keeps_direction():
    r = ForceRenderer(1, P.replace(max_force=2.0, b=0.0))
    f = settle(r, np.zeros((1, 3)), np.array([[0.03, 0.0, -0.04]]), np.array([CONTACT]))
    assert np.linalg.norm(f[0]) == pytest.approx(2.0)
    np.testing.assert_allclose(f[0] / 2.0, [-0.6, 0, 0.8], atol=1e-9)
    assert r.saturated[0]


def test_damping_only_in_contact_and_never_pulls_in():
    p = P.replace(max_force=100.0, fir_taps=1)
    r = ForceRenderer(2, p)
    proxies = np.zeros((2, 3))
    hips = np.array([[0.001, 0, -0.015], [0.001, 0, -0.015]])
    states = np.array([CONTACT, FREE])
    r.update(proxies, hips, states)
    f = r.update(proxies, hips + [0.0, 0, -0.0001], states)  # pressing in at 0.1 m/s
    spring = p.k * (np.linalg.norm(hips[0] + [0, 0, -0.0001]) - p.dead_band)
    assert f[0, 2] > f[1, 2] == pytest.approx(spring * 0.99, rel=0.02)
    assert f[0, 2] - f[1, 2] == pytest.approx(p.b * 0.1, rel=0.02)  # -B xdot, only in contact
    f = r.update(proxies, hips + [0.0, 0, 0.003], states)  # pulled out at 3 m/s: damping clipped
    v = hips[0] + [0.0, 0, 0.003]
    assert f[0] @ (-v) >= -1e-12  # never pulls the HIP inwards along the spring
    assert f[0] @ (-v) < 1e-3 * np.linalg.norm(v)  # the damper cancelled the spring


def test_fixture_form_k_s():
    p = P.replace(mode="fixture", max_force=100.0, b=0.0)
    r = ForceRenderer(1, p)
    prox, hip = np.array([[0.0, 0.0, 0.02]]), np.array([[0.0, 0.003, 0.01]])
    f = settle(r, prox, hip, np.array([CONTACT]))
    v = hip[0] - prox[0]
    want = p.k_s * (prox[0] - hip[0]) * (1 - p.dead_band / np.linalg.norm(v))
    np.testing.assert_allclose(f[0], want, rtol=1e-9)
    assert p.dead_band == pytest.approx((p.r2 - p.r1) / 2)


def test_never_nan_and_bad_inputs_raise():
    r = ForceRenderer(2, P)
    x = np.zeros((2, 3))
    f = r.update(x, x, np.array([CONTACT, FREE]))  # HIP exactly on the proxy
    assert np.all(f == 0)
    for bad in (np.array([[np.nan, 0, 0], [0, 0, 0]]), np.array([[0, 0, 0], [np.inf, 0, 0]])):
        with pytest.raises(InputError, match="not finite"):
            r.update(x, bad, np.zeros(2))
        with pytest.raises(InputError, match="not finite"):
            r.update(bad, x, np.zeros(2))
    with pytest.raises(InputError, match="states"):
        r.update(x, x, np.zeros(3))
    assert np.all(np.isfinite(r.forces))
    with pytest.raises(InputError):
        fir_lowpass(0, 100.0, 1000.0)


def test_no_allocation_per_tick():
    """The arrays returned are the preallocated ones, tick after tick."""
    r = ForceRenderer(4, P)
    x = np.zeros((4, 3))
    h = np.full((4, 3), -0.01)
    a = r.update(x, h, np.full(4, CONTACT))
    b = r.update(x, h, np.full(4, CONTACT))
    assert np.shares_memory(a, b) and np.shares_memory(a, r.forces)


def test_fir_is_the_convolution_of_the_raw_forces_over_the_last_taps():
    """A varying input: every tick's force is sum_k taps[k] * raw[t - k] (zero before the first)."""
    rng = np.random.default_rng(3)
    p = P.replace(b=0.0, max_force=1e6)
    r = ForceRenderer(3, p)
    T = r.taps.size
    proxies = np.zeros((3, 3), np.float32)
    raws, outs = [], []
    for _ in range(3 * T):
        hips = rng.normal(0.0, 0.01, (3, 3)).astype(np.float32)
        out = r.update(proxies, hips, np.ones(3, np.int32)).copy()
        raws.append(r.raw.copy())
        outs.append(out)
    raws = np.array(raws)
    for t in (0, 1, T - 1, T, 2 * T + 5, 3 * T - 1):
        want = sum(r.taps[k] * raws[t - k] for k in range(min(T, t + 1)))
        np.testing.assert_allclose(outs[t], want, rtol=1e-12, atol=1e-15)


class _Oracle:
    """The module docstring's four steps as NumPy array expressions (the implementation before
    the compiled tick core): what the core must compute, tick after tick."""

    def __init__(self, n, p):
        self.p, self.taps = p, fir_lowpass(p.fir_taps, p.fir_cutoff_hz, p.rate_hz)
        self.prev, self.raws = None, []

    def update(self, xp, xh, st):
        p = self.p
        xp, xh = np.asarray(xp, float), np.asarray(xh, float)
        v = xh - xp
        vl = np.sqrt(np.einsum("ij,ij->i", v, v))
        engaged = vl > p.dead_band
        dd = np.maximum(vl, p.dead_band)
        raw = -v * (np.maximum(vl - p.dead_band, 0.0) * p.stiffness / dd)[:, None]
        if self.prev is not None and p.b > 0:
            contact = (st != FREE) & engaged
            raw = raw - (xh - self.prev) * contact[:, None] * (p.b * p.rate_hz)
            dot = np.maximum(np.einsum("ij,ij->i", raw, v), 0.0) * engaged / dd / dd
            raw = raw - v * dot[:, None]
        self.prev = xh.copy()
        self.raws.append(raw)
        out = sum(self.taps[k] * self.raws[-1 - k] for k in range(min(len(self.raws), self.taps.size)))
        norm = np.linalg.norm(out, axis=1)
        sat = norm > p.max_force
        out[sat] *= (p.max_force / norm[sat])[:, None]
        return out, raw, sat


@pytest.mark.parametrize("mode", ["rendering", "fixture"])
@pytest.mark.parametrize("n", [1, 5, 37])
def test_compiled_core_matches_the_array_expressions(mode, n):
    """Spring, damping (unilateral), FIR and saturation in the compiled tick core give the NumPy
    array expressions' forces, tick after tick, on random motion in and out of the dead band and
    of contact, for float32 proxies (the kernels') and float64 ones."""
    rng = np.random.default_rng(11 + n)
    p = P.replace(mode=mode, max_force=2.0 if mode == "rendering" else 0.4)
    r, oracle = ForceRenderer(n, p), _Oracle(n, p)
    proxies = rng.normal(0.0, 0.01, (n, 3)).astype(np.float32)
    seen_zero = seen_sat = seen_damped = 0
    for tick in range(200):
        hips = proxies + rng.normal(0.0, 0.003 if mode == "rendering" else 0.0005, (n, 3))
        states = rng.integers(0, 3, n).astype(np.int32)
        xp = proxies if tick % 2 else proxies.astype(np.float64)
        f = r.update(xp, hips, states).copy()
        want, raw, sat = oracle.update(proxies, hips, states)
        np.testing.assert_allclose(f, want, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(r.raw, raw, rtol=1e-12, atol=1e-14)
        assert np.array_equal(r.saturated, sat)
        seen_sat += int(sat.sum())
        seen_zero += int((np.linalg.norm(raw, axis=1) == 0).sum())
        seen_damped += int(((states != FREE) & (np.linalg.norm(raw, axis=1) > 0)).sum())
    if n > 1:      # every branch seen (one proxy is too few draws for all of them)
        assert seen_sat > 0 and seen_damped > 0 and (seen_zero > 0 or mode == "fixture")
