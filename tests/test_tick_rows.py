"""The recording's row of a tick (``service/tick_cdr.TickRows``, ``native/tick_rows.c``): every
field of ``TickInput`` and ``TickOutput`` lands in its columns exactly (a round trip through
``row_into``, the Python reading of the layout), for random values of every type; a field
assigned a new array is followed; a field the compiled copy cannot read is refused by name."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pointfence.service.tick_cdr import TickLayout, TickRows, row_into
from pointfence.service.tick_io import TickInput, TickOutput


def _randomise(obj, rng, n):
    for f in dataclasses.fields(obj):
        if f.name == "n":
            continue
        v = getattr(obj, f.name)
        if isinstance(v, np.ndarray):
            if v.dtype == bool:
                v[...] = rng.random(v.shape) < 0.5
            elif v.dtype.kind == "i":
                v[...] = rng.integers(-2 ** 31, 2 ** 31 - 1, v.shape) if v.dtype.itemsize == 4 else \
                    rng.integers(0, 2 ** 52, v.shape)
            else:
                v[...] = rng.normal(size=v.shape) * 10.0 ** rng.integers(-6, 6, v.shape)
        elif isinstance(v, bool):
            setattr(obj, f.name, bool(rng.random() < 0.5))
        elif isinstance(v, int):
            setattr(obj, f.name, int(rng.integers(0, 2 ** 40)))
        elif isinstance(v, float):
            setattr(obj, f.name, float(rng.normal() * 1e3))


def _same(a, b):
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=f.name)
        else:
            assert x == y or (x != x and y != y), (f.name, x, y)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_every_field_round_trips_exactly(n):
    rng = np.random.default_rng(n)
    lay = TickLayout(n)
    rows = np.full((5, lay.width), np.nan)
    fill = TickRows(lay, rows)
    inp, out = TickInput.zeros(n), TickOutput.zeros(n)
    for i in range(5):
        _randomise(inp, rng, n)
        _randomise(out, rng, n)
        inp.master_pos[0, 1] = np.nan              # a NaN is copied as a NaN
        fill.fill(inp, out, i)
        got_in, got_out = TickInput.zeros(n), TickOutput.zeros(n)
        row_into(lay, rows[i], got_in, got_out)
        _same(inp, got_in)
        _same(out, got_out)
        assert rows[i, fill.tick_us_col] == 0.0
    assert not np.isnan(np.delete(rows, [lay.cols[("in", "master_pos")][0] + 1], axis=1)).any()


def test_a_field_assigned_a_new_array_is_followed():
    lay = TickLayout(2)
    rows = np.zeros((2, lay.width))
    fill = TickRows(lay, rows)
    inp, out = TickInput.zeros(2), TickOutput.zeros(2)
    fill.fill(inp, out, 0)
    inp.master_pos = np.full((2, 3), 7.0)          # not in place: the copy must read the new array
    out.force = np.full((2, 3), -3.0)
    fill.fill(inp, out, 1)
    c, k = lay.cols[("in", "master_pos")]
    assert (rows[1, c: c + k] == 7.0).all() and (rows[0, c: c + k] == 0.0).all()
    c, k = lay.cols[("out", "force")]
    assert (rows[1, c: c + k] == -3.0).all()


def test_fields_and_rows_the_copy_cannot_read_are_refused_by_name():
    lay = TickLayout(2)
    rows = np.zeros((3, lay.width))
    fill = TickRows(lay, rows)
    inp, out = TickInput.zeros(2), TickOutput.zeros(2)
    inp.robot_pos = np.zeros((2, 4))[:, :3]         # 6 values, but a view that is not contiguous
    with pytest.raises(TypeError, match="TickInput.robot_pos"):
        fill.fill(inp, out, 0)
    inp.robot_pos = np.zeros((2, 3))
    out.state = [0, 0]
    with pytest.raises(TypeError, match="TickOutput.state"):
        fill.fill(inp, out, 0)
    out.state = np.zeros(3, np.int32)               # one arm too many
    with pytest.raises(TypeError, match="TickOutput.state"):
        fill.fill(inp, out, 0)
    out.state = np.zeros(2, np.int32)
    with pytest.raises(IndexError):
        fill.fill(inp, out, 3)
    with pytest.raises(TypeError, match="C-contiguous float64"):
        TickRows(lay, np.zeros((3, lay.width), np.float32))
    fill.fill(inp, out, 2)
