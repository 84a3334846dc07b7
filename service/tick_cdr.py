"""Every tick's ``TickInput`` and ``TickOutput``, lossless: a float64 ring row the tick fills, and
the ``pointfence_msgs/TickInput`` / ``TickOutput`` messages (``ros2_schemas``) the writer process
encodes from those rows and a replay decodes back into the structs.

A row holds every field of both structs (``n`` excepted: the recording's arm count) and the
loop's compute time of the tick (``tick_us``): float64 holds every value exactly (bools, the
int32 contact states, int64 hold bits below 2^53, tick numbers). The tick's side
(``TickRows.fill``) copies both structs into a row in one compiled call: no allocation, no
encoding.
"""
from __future__ import annotations

import ctypes
import operator
import struct

import numpy as np

from pointfence.native import ROW_KINDS, RowField, fast, ptr

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


def _getter(names: list):
    """A function of an object giving the tuple of its attributes ``names`` (one C call)."""
    if len(names) > 1:
        return operator.attrgetter(*names)
    return (lambda obj: (getattr(obj, names[0]),)) if names else (lambda obj: ())


class TickRows:
    """The tick's side: ``fill(inp, out, i)`` copies both structs into row ``i`` of ``rows`` (a
    C-contiguous float64 array (N, ``layout.width``): the ring) in one compiled call
    (``native/tick_rows.c``).

    The array fields are bound once: the copy reads them where they are. A struct whose field is
    another array than the bound one (a new struct, a field assigned anew) is bound again. The
    scalars (k, t, hold, ...) are packed into a staging array first (``struct.pack_into``). The
    row's ``tick_us`` is 0 (the recorder's ``note_tick_us`` and the replay's ``take`` set it)."""

    def __init__(self, layout: TickLayout, rows: np.ndarray):
        if not (isinstance(rows, np.ndarray) and rows.dtype == np.float64 and rows.ndim == 2
                and rows.shape[1] == layout.width and rows.flags.c_contiguous):
            raise TypeError(f"TickRows: rows must be a C-contiguous float64 array (N, {layout.width}); got "
                            f"{getattr(rows, 'dtype', type(rows).__name__)} {getattr(rows, 'shape', '')}")
        self.layout = layout
        self.rows = rows
        arrays = {"in": [], "out": []}    # (field, first column, values)
        scalars = {"in": [], "out": []}   # (field, column)
        for part in ("in", "out"):
            for name, _, _, per_arm in layout.fields[part]:
                c, k = layout.cols[(part, name)]
                if per_arm:
                    arrays[part].append((name, c, k))
                else:
                    scalars[part].append((name, c))
        self.tick_us_col = layout.cols[("out", TICK_US)][0]
        self._arrays = arrays
        self._get_arrays = {p: _getter([f[0] for f in arrays[p]]) for p in arrays}
        self._get_scalars = {p: _getter([f[0] for f in scalars[p]]) for p in scalars}
        n_in, n_out = len(scalars["in"]), len(scalars["out"])
        # the scalars' staging: in's, out's, then a 0.0 for tick_us
        self._stage = np.zeros(n_in + n_out + 1)
        self._pack_in, self._pack_out = struct.Struct(f"={n_in}d"), struct.Struct(f"={n_out}d")
        self._out_at = 8 * n_in
        n_arrays = len(arrays["in"]) + len(arrays["out"])
        self._fields = (RowField * (n_arrays + n_in + n_out + 1))()
        base = self._stage.ctypes.data
        for j, (_, c) in enumerate(scalars["in"] + scalars["out"] + [(TICK_US, self.tick_us_col)]):
            self._fields[n_arrays + j] = RowField(base + 8 * j, c, 1, ROW_KINDS[np.dtype(np.float64)])
        self._bound = {"in": None, "out": None}   # the arrays the descriptors point into
        self._nf = ctypes.c_int64(len(self._fields))
        self._base = ptr(rows, np.float64, "ring rows")
        self._width = ctypes.c_int64(layout.width)
        self._n = len(rows)

    def _bind(self, part: str, got: tuple) -> None:
        self._bound[part] = None           # (until every descriptor of ``part`` points into ``got``)
        j0 = 0 if part == "in" else len(self._arrays["in"])
        for (name, c, k), a in zip(self._arrays[part], got):
            kind = ROW_KINDS.get(getattr(a, "dtype", None))
            if not isinstance(a, np.ndarray) or kind is None or not a.flags.c_contiguous or a.size != k:
                raise TypeError(f"Tick{'Input' if part == 'in' else 'Output'}.{name}: a recorded field must be a "
                                f"C-contiguous NumPy array of {k} values (float64, bool, int32/64 or float32); got "
                                f"{type(a).__name__} {getattr(a, 'dtype', '')} {getattr(a, 'shape', '')}")
        for j, ((_, c, k), a) in enumerate(zip(self._arrays[part], got)):
            self._fields[j0 + j] = RowField(a.ctypes.data, c, k, ROW_KINDS[a.dtype])
        self._bound[part] = got            # (kept: the descriptors point into these arrays)

    def fill(self, inp, out, i: int) -> None:
        """Row ``i`` := ``inp``, ``out`` (and ``tick_us`` 0)."""
        if not 0 <= i < self._n:
            raise IndexError(f"TickRows.fill: row {i} of {self._n}")
        for part, obj in (("in", inp), ("out", out)):
            got = self._get_arrays[part](obj)
            bound = self._bound[part]
            if bound is None or not all(map(operator.is_, got, bound)):
                self._bind(part, got)
        self._pack_in.pack_into(self._stage, 0, *self._get_scalars["in"](inp))
        self._pack_out.pack_into(self._stage, self._out_at, *self._get_scalars["out"](out))
        fast.pf_row_gather(self._fields, self._nf, self._base, self._width, i)


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
