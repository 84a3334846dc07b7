"""How old the master samples are that the haptic tick reads: a histogram of ages.

The tick records, for every master it reads, the age of the sample it got (its kernel arrival
to the tick's start, ns; ``rx_stamps``). ``AgeHistogram`` keeps them in bins of 1/8 octave
(9 % wide) from 1 us to 16 s, so that recording costs a few arithmetic operations and no
buffer, and reports quantiles (the upper edge of the bin that holds them, at most the maximum: never below
the true value) and the exact maximum. ``counts()`` copies the bins so that a part of a run (a
flood) can be summarised from the difference of two copies (``summary(later - earlier)``).
"""
from __future__ import annotations

import math

BINS_PER_OCTAVE = 8
OCTAVES = 24                       # 1 us .. 2^24 us = 16.8 s
NBINS = BINS_PER_OCTAVE * OCTAVES + 1


def _edge_s(i: int) -> float:
    """Upper edge of bin ``i`` (s)."""
    return 2.0 ** ((i + 1) / BINS_PER_OCTAVE) * 1e-6


class AgeHistogram:
    """Sample ages at the tick (see the module docstring)."""

    def __init__(self):
        self._c = [0] * NBINS
        self.n = 0
        self.max_ns = 0

    def record(self, age_ns: int) -> None:
        """One sample's age (ns) when the tick read it."""
        us = age_ns * 1e-3
        i = int(BINS_PER_OCTAVE * math.log2(us)) if us > 1.0 else 0
        self._c[i if i < NBINS else NBINS - 1] += 1
        self.n += 1
        if age_ns > self.max_ns:
            self.max_ns = age_ns

    def counts(self) -> list:
        """A copy of the bins (for ``summary`` of a part of the run)."""
        return list(self._c)

    def summary(self, counts=None) -> dict:
        """``n``, ``p50_ms``, ``p99_ms``, ``max_ms`` of all ages so far, or of ``counts`` (bins as
        ``counts()`` gives them, or a difference of two such copies: its max is a bin's edge)."""
        c = self._c if counts is None else counts
        n = sum(c)
        if n == 0:
            return {"n": 0, "p50_ms": None, "p99_ms": None, "max_ms": None}
        out = {"n": n}
        for name, q in (("p50_ms", 0.5), ("p99_ms", 0.99)):
            need, run = q * n, 0
            for i, k in enumerate(c):
                run += k
                if run >= need:
                    out[name] = round(_edge_s(i) * 1e3, 3)
                    break
        if counts is None:       # the exact maximum, and no quantile above it
            out["max_ms"] = round(self.max_ns * 1e-6, 3)
            for name in ("p50_ms", "p99_ms"):
                out[name] = min(out[name], out["max_ms"])
        else:
            out["max_ms"] = round(_edge_s(max(i for i, k in enumerate(c) if k)) * 1e3, 3)
        return out
