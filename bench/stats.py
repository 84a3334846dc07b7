"""Percentiles of timing samples."""
from __future__ import annotations

import numpy as np


def pct(samples, q: float) -> float:
    return float(np.percentile(np.asarray(samples, dtype=np.float64), q))


def summary(samples, prefix: str, unit_scale: float = 1.0) -> dict:
    s = np.asarray(samples, dtype=np.float64) * unit_scale
    return {f"{prefix}_p50": round(pct(s, 50), 4), f"{prefix}_p99": round(pct(s, 99), 4)}
