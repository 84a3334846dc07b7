"""Each camera's clock against the service's: an online estimate of offset and drift.

A camera stamps its frames on its own clock (a device counter, the host's clock of the machine
it hangs on, a recording's clock); the service sees each frame arrive on its own clock (the
loop's, ``time.monotonic``). Arrival = capture + transport delay, and the delay is never
negative, so the service-clock time of a capture is the lower envelope of ``arrival - stamp``
over recent frames: ``CameraClock`` fits that envelope as a line in the stamp (its slope the
drift of the camera's clock against the service's, its height at a stamp the offset) over a
sliding window (the offset: the least gap of the last 2 s; the drift: a line through the
least gap of each quarter second of the last 30 s), and maps a stamp to the service clock with
it. The residual error is the smallest transport delay in the window (microseconds on USB, a
frame interval at worst when every frame is late by at least that much) plus the drift over
the window while the drift is not yet known (10 s at 100 ppm: 0.2 ms).

Cameras that share one clock (a synthetic scene's cameras, a hardware-synchronised rig: their
sources say so with a common ``clock_domain``) share one ``CameraClock``; the service maps every
other camera's stamps onto the first camera's clock (service/frames.py ``LiveFrames``), so a
snapshot's frames, motion prediction and the self-filter's tool poses all read one clock.
"""
from __future__ import annotations

import math

import numpy as np


#: the largest drift believed (s/s): quartz clocks drift by tens of ppm; a larger slope is jitter
MAX_DRIFT = 1e-3


def _slope(x: np.ndarray, y: np.ndarray) -> float:
    """The least-squares slope of ``y`` in ``x`` (the closed form: ``np.polyfit``'s result in a
    third of its time; a camera's reader thread runs this once a frame, holding the interpreter
    lock)."""
    dx = x - x.mean()
    return float(np.dot(dx, y - y.mean()) / np.dot(dx, dx))


class CameraClock:
    """The service clock minus a camera's clock, estimated from (stamp, arrival) pairs (s).

    Args:
        window_s: the offset is the least ``arrival - stamp`` (drift removed) over the frames of
            the last ``window_s`` camera seconds.
        drift_window_s: the drift is the slope of a least-squares line through the least gap of
            each ``bin_s`` of the last ``drift_window_s`` seconds, once they span at least a third
            of it (before that the drift is taken as 0: over a few seconds the delays' jitter
            hides a quartz clock's tens of ppm, and a wrong slope costs more than none).
        capacity: the most frames kept for the offset (a ring).
    """

    def __init__(self, window_s: float = 2.0, drift_window_s: float = 30.0, bin_s: float = 0.25,
                 capacity: int = 256):
        for key, v in (("window_s", window_s), ("drift_window_s", drift_window_s), ("bin_s", bin_s)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{key} = {v!r}; expected a positive number of seconds")
        self.window_s, self.drift_window_s, self.bin_s = float(window_s), float(drift_window_s), float(bin_s)
        self._stamp = np.zeros(int(capacity))
        self._gap = np.zeros(int(capacity))      # arrival - stamp
        nb = int(math.ceil(drift_window_s / bin_s)) + 1
        self._bin_key = np.full(nb, -1, np.int64)   # bin number (stamp // bin_s) of each slot
        self._bin_s = np.zeros(nb)                # stamp of each bin's least gap
        self._bin_g = np.zeros(nb)                # each bin's least gap
        self._n = 0                               # pairs ever seen
        self._a = math.nan                        # offset at the newest stamp
        self._b = 0.0                             # slope of the gap in the stamp (= -drift)
        self._ref = 0.0

    @property
    def samples(self) -> int:
        return self._n

    def update(self, stamp: float, arrival: float) -> None:
        """Take one frame: its ``stamp`` (camera clock, s) and ``arrival`` (service clock, s).
        Non-finite values are ignored."""
        stamp, arrival = float(stamp), float(arrival)
        if not (math.isfinite(stamp) and math.isfinite(arrival)):
            return
        gap = arrival - stamp
        cap = len(self._stamp)
        i = self._n % cap
        self._stamp[i], self._gap[i] = stamp, gap
        self._n += 1
        key = int(stamp // self.bin_s)
        j = key % len(self._bin_key)
        if self._bin_key[j] != key or gap < self._bin_g[j]:
            self._bin_key[j], self._bin_s[j], self._bin_g[j] = key, stamp, gap
        used = (self._bin_key >= 0) & (self._bin_s >= stamp - self.drift_window_s)
        b = 0.0
        if used.sum() >= 8:
            bs = self._bin_s[used] - stamp
            if np.ptp(bs) >= self.drift_window_s / 3:
                b = min(max(_slope(bs, self._bin_g[used]), -MAX_DRIFT), MAX_DRIFT)
        k = min(self._n, cap)
        s, g = self._stamp[:k] - stamp, self._gap[:k]
        keep = s >= -self.window_s
        self._a = float(np.min(g[keep] - b * s[keep]))   # (stamps relative to the newest: no epoch-sized numbers)
        self._b = b
        self._ref = stamp

    def offset(self, stamp: float | None = None) -> float:
        """Service clock minus camera clock at ``stamp`` (default: the newest frame's); NaN
        before the first frame."""
        if stamp is None:
            return self._a
        return self._a + self._b * (float(stamp) - self._ref)

    def to_service(self, stamp: float) -> float:
        """``stamp`` (camera clock, s) on the service clock (s)."""
        return float(stamp) + self.offset(stamp)

    @property
    def drift(self) -> float:
        """How much faster the camera clock runs than the service clock (s/s; 1e-4 = 100 ppm)."""
        return -self._b

    def status(self) -> dict:
        return {"offset_s": None if math.isnan(self._a) else round(self._a, 6),
                "drift_ppm": round(-self._b * 1e6, 2), "frames": self._n}
