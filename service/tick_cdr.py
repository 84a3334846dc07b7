"""Every tick's ``TickInput`` and ``TickOutput``, lossless: a float64 ring row the tick fills, and
the ``pointfence_msgs/TickInput`` / ``TickOutput`` messages (``ros2_schemas``) the writer process
encodes from those rows and a replay decodes back into the structs.

A row holds every field of both structs (``n`` excepted: the recording's arm count) and the
loop's compute time of the tick (``tick_us``): float64 holds every value exactly (bools, the
int32 contact states, int64 hold bits below 2^53, tick numbers). The tick's side
(``TickRows.fill``) copies into preallocated views of one staging row: no allocation, no
encoding.
"""
from __future__ import annotations

import numpy as np

from .cdr import FixedLayout
from .ros2_schemas import TICK_US, tick_fields
from .tick_io import TickInput, TickOutput

_CODE = {np.dtype(np.float64): "f8", np.dtype(bool): "?", np.dtype(np.int32): "i4", np.dtype(np.int64): "i8"}


class TickLayout:
    """Column layout of a ring row for ``n`` arms and the CDR layouts of the two messages."""

    def __init__(self, n: int):
        self.n = int(n)
        self.cols: dict = {}          # (struct, field) -> (first column, values)
        c = 0
        self.fields = {"in": tick_fields(TickInput), "out": tick_fields(TickOutput)}
        for part, fields in self.fields.items():
            for name, _, _, per_arm in fields:
                k = per_arm * self.n if per_arm else 1
                self.cols[(part, name)] = (c, k)
                c += k
        self.cols[("out", TICK_US)] = (c, 1)
        self.width = c + 1
        self.cdr = {part: self._layout(part) for part in ("in", "out")}

    def _layout(self, part: str) -> FixedLayout:
        lay = FixedLayout().header("world")
        for name, _, dtype, per_arm in self.fields[part]:
            code = _CODE[np.dtype(dtype)]
            if per_arm:
                lay.array(name, code, per_arm * self.n)
            else:
                lay.scalar(name, code)
        if part == "out":
            lay.scalar(TICK_US, "f8")
        return lay

    def names(self, part: str) -> list:
        return [f[0] for f in self.fields[part]] + ([TICK_US] if part == "out" else [])

    def encode(self, part: str, rows: np.ndarray, stamp_ns: np.ndarray) -> list:
        """CDR messages (bytes) of ``part`` ("in" or "out") for ring rows ``rows`` (N, width)."""
        lay = self.cdr[part]
        rec = lay.blank(len(rows))
        rec["stamp_sec"] = stamp_ns // 1_000_000_000
        rec["stamp_nanosec"] = stamp_ns % 1_000_000_000
        for name in self.names(part):
            c, k = self.cols[(part, name)]
            rec[name] = rows[:, c] if k == 1 and rec[name].ndim == 1 else rows[:, c: c + k]
        buf, size = rec.tobytes(), lay.size
        return [buf[i * size: (i + 1) * size] for i in range(len(rows))]

    def decode(self, part: str, messages: list, rows: np.ndarray) -> None:
        """Messages of ``part`` into ring rows ``rows`` (N, width), the inverse of ``encode``.
        Raises ValueError if a message is not of this layout (another arm count, a damaged one)."""
        lay = self.cdr[part]
        size = lay.size
        bad = [i for i, m in enumerate(messages) if len(m) != size]
        if bad:
            raise ValueError(f"{part} tick message {bad[0]} is {len(messages[bad[0]])} bytes; expected {size} "
                             f"for {self.n} arm(s)")
        rec = np.frombuffer(b"".join(messages), lay.dtype)
        for name in self.names(part):
            c, k = self.cols[(part, name)]
            v = rec[name]
            rows[:, c: c + k] = v.reshape(len(rec), k)


class TickRows:
    """The tick's side: ``fill(inp, out, row)`` copies both structs into ring row ``row`` (a float64
    array of ``layout.width``) through a staging row's preallocated views."""

    def __init__(self, layout: TickLayout):
        self.layout = layout
        self.stage = np.zeros(layout.width)
        self._arrays = {"in": [], "out": []}   # (field, view of the staging row)
        self._scalars = {"in": [], "out": []}  # (field, column)
        for part in ("in", "out"):
            for name, _, _, per_arm in layout.fields[part]:
                c, k = layout.cols[(part, name)]
                if per_arm:
                    shape = (layout.n, per_arm) if per_arm > 1 else (layout.n,)
                    self._arrays[part].append((name, self.stage[c: c + k].reshape(shape)))
                else:
                    self._scalars[part].append((name, c))
        self.tick_us_col = layout.cols[("out", TICK_US)][0]
        self._out_cols = []     # (field, first column, columns, per-arm shape or None)
        for name, _, _, per_arm in layout.fields["out"]:
            c, k = layout.cols[("out", name)]
            self._out_cols.append((name, c, k, ((layout.n, per_arm) if per_arm > 1 else (layout.n,)) if per_arm
                                   else None))

    def fill(self, inp, out, row: np.ndarray) -> None:
        # (``view[...] = x``: NumPy's own assignment, about 3x cheaper than ``np.copyto``'s dispatch)
        st = self.stage
        for obj, part in ((inp, "in"), (out, "out")):
            for name, view in self._arrays[part]:
                view[...] = getattr(obj, name)
            for name, c in self._scalars[part]:
                st[c] = getattr(obj, name)
        st[self.tick_us_col] = 0.0
        row[:] = st

    def fill_out(self, out, row: np.ndarray) -> None:
        """Only the ``TickOutput`` columns of ``row`` (straight into it, no staging row)."""
        for name, c, k, shape in self._out_cols:
            if shape is None:
                row[c] = getattr(out, name)
            else:
                row[c: c + k].reshape(shape)[...] = getattr(out, name)


def row_into(layout: TickLayout, row: np.ndarray, inp: TickInput, out=None) -> None:
    """Ring row ``row`` into the structs ``inp`` (and ``out``), each field in its own type."""
    for obj, part in ((inp, "in"), (out, "out")):
        if obj is None:
            continue
        for name, _, dtype, per_arm in layout.fields[part]:
            c, k = layout.cols[(part, name)]
            if per_arm:
                dst = getattr(obj, name)
                dst[...] = row[c: c + k].reshape(dst.shape).astype(dst.dtype)
            else:
                kind = np.dtype(dtype)
                v = row[c]
                setattr(obj, name, bool(v) if kind == bool else int(v) if kind.kind == "i" else float(v))


__all__ = ["TickLayout", "TickRows", "row_into"]
