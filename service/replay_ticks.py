"""The ticks of a replay, kept as the recording keeps them (``mcap_replay``).

A replayed tick is copied once, after it ran, into a row of the recording's own layout
(``tick_cdr.TickLayout``: every ``TickInput`` and ``TickOutput`` field and the tick's compute
time, float64, exact): one ``TickRows.fill`` per tick, the only per-tick cost of keeping it.
From these rows, after the run and in whole-array operations:

* ``compare(recorded_rows)``: the exactness report of an exact replay (every ``TickOutput``
  field of every tick against the recorded one, bit for bit, NaN equal to NaN; the wall-clock
  fields ``kernel_us`` and ``tick_us`` aside);
* ``recorder()``: the in-memory ``record.Recorder`` that ``ticks.csv``, ``inputs.npz`` and
  ``summary.json`` are written from, holding exactly what its ``write`` and ``note_tick_us``
  would have put there tick by tick.
"""
from __future__ import annotations

import numpy as np

from .record import C, Recorder
from .tick_cdr import TickLayout, TickRows

#: fields of TickOutput that are wall-clock measurements, not results
TIMING = ("kernel_us", "tick_us")


class ReplayTicks:
    """Room for ``count`` replayed ticks of layout ``layout``; ``take`` after each tick."""

    def __init__(self, layout: TickLayout, count: int):
        self.layout = layout
        self.rows = np.zeros((int(count), layout.width))
        self.count = 0
        self._fill = TickRows(layout, self.rows)
        self._us = self._fill.tick_us_col

    def take(self, inp, out, tick_us: float) -> None:
        """Keep tick ``inp`` -> ``out`` and its compute time (us)."""
        i = self.count
        self._fill.fill(inp, out, i)
        self.rows[i, self._us] = tick_us
        self.count = i + 1

    def col(self, part: str, name: str) -> np.ndarray:
        """Field ``name`` of ``part`` ("in" or "out") of every kept tick: (N,) or (N, columns)."""
        c, k = self.layout.cols[(part, name)]
        return self.rows[: self.count, c] if k == 1 else self.rows[: self.count, c: c + k]

    def compare(self, recorded: np.ndarray) -> dict:
        """The exactness report against ``recorded`` rows (same layout, tick for tick):
        ``exact``, ``ticks_compared``, ``mismatched_ticks``, ``first_mismatch`` (tick, field,
        recorded and replayed values) or None."""
        lay, n = self.layout, self.count
        cols = np.concatenate([np.arange(c, c + k) for (part, name), (c, k) in lay.cols.items()
                               if part == "out" and name not in TIMING])
        a, b = self.rows[:n][:, cols], recorded[:n][:, cols]
        same = (a == b) | (np.isnan(a) & np.isnan(b))
        bad = np.flatnonzero(~same.all(axis=1))
        report = {"exact": not len(bad), "ticks_compared": n, "mismatched_ticks": int(len(bad)), "first_mismatch": None}
        if len(bad):
            i = int(bad[0])
            col = int(cols[np.flatnonzero(~same[i])[0]])
            name = next(nm for (part, nm), (c, k) in lay.cols.items() if part == "out" and c <= col < c + k)
            report["first_mismatch"] = {"tick": int(self.rows[i, lay.cols[("out", "k")][0]]), "field": name,
                                        "recorded": float(recorded[i, col]), "replayed": float(self.rows[i, col])}
        return report

    def recorder(self) -> Recorder:
        """An in-memory ``record.Recorder`` of the kept ticks (see the module docstring)."""
        n, b = self.count, self.layout.n
        rec = Recorder(max(2, n), b)
        for _ in range(n):
            rec.next_row()
        out = lambda name: self.col("out", name)      # noqa: E731
        inp = lambda name: self.col("in", name)       # noqa: E731
        arm0 = lambda a: a.reshape(n, b, -1)[:, 0]    # noqa: E731  (arm 0 of an (N, B*3) or (N, B) field)
        rows = rec.rows[:n]
        rows[:, C["t"]] = out("t")
        for col, name in (("xm_x", "xm"), ("hip_x", "hip"), ("proxy_x", "proxy"), ("xr_cmd_x", "command"),
                          ("xr_x", "robot_pos"), ("f_x", "force")):
            rows[:, C[col]: C[col] + 3] = arm0(out(name))
        rows[:, C["state"]] = arm0(out("state"))[:, 0]
        rows[:, C["frame_seq"]] = out("frame_seq")
        rows[:, C["tick_us"]] = self.rows[:n, self._us]
        v = rec.inputs[:n]
        v[:, 0], v[:, 1], v[:, 2], v[:, 3] = inp("k"), inp("dt"), inp("overrun"), np.minimum(inp("frame_age"), 1e9)
        v[:, 4], v[:, 5], v[:, 6], v[:, 7] = inp("architecture"), inp("haptics"), inp("teleop"), inp("frame_time")
        m = rec.masters[:n]
        m[:, :, :3] = inp("master_pos").reshape(n, b, 3)
        m[:, :, 3] = inp("pedal").reshape(n, b)
        m[:, :, 4] = inp("master_ok").reshape(n, b)
        rec.robots[:n, :, :3] = out("robot_pos").reshape(n, b, 3)
        rec.robots[:n, :, 3:] = out("command").reshape(n, b, 3)
        rec.masters_world[:n] = out("xm").reshape(n, b, 3)
        rec.holds[:n, 0] = out("hold")
        rec.holds[:n, 1:] = out("arm_hold").reshape(n, b)
        return rec


__all__ = ["ReplayTicks", "TIMING"]
