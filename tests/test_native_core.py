"""The compiled tick core (native/): it builds from source on a fresh machine with a clear error
when it cannot, its bindings refuse arrays it cannot read, and its teleoperation computes what
the NumPy array expressions of service/teleop.py's docstring compute, tick after tick, on random
operator input (clutch, invalid samples, re-anchoring, architecture switches)."""
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from pointfence.native import build, ptr
from pointfence.service.teleop import ANCHOR_RELEASE, Teleop
from pointfence.service.tick_io import TickInput


# --- building ----------------------------------------------------------------------------------
def test_builds_into_the_cache_once_and_again_for_a_changed_source(tmp_path, monkeypatch):
    src = tmp_path / "tick_core.c"
    shutil.copy(build.SOURCE, src)
    monkeypatch.setattr(build, "SOURCE", src)
    monkeypatch.setenv("POINTFENCE_NATIVE_CACHE", str(tmp_path / "cache"))
    first = build.library_path()
    assert first.parent == tmp_path / "cache" and first.exists()
    mtime = first.stat().st_mtime_ns
    assert build.library_path() == first and first.stat().st_mtime_ns == mtime      # cached: not rebuilt
    src.write_text(src.read_text() + "\n/* changed */\n")
    second = build.library_path()
    assert second != first and second.exists() and not first.exists()     # the earlier build is gone
    lib = build.load()
    assert hasattr(lib, "pf_step_pre")
    assert [p.name for p in (tmp_path / "cache").iterdir()] == [second.name]     # no temporary left


def test_a_broken_source_or_no_compiler_says_what_to_do(tmp_path, monkeypatch):
    src = tmp_path / "tick_core.c"
    src.write_text("this is not C;\n")
    monkeypatch.setattr(build, "SOURCE", src)
    monkeypatch.setenv("POINTFENCE_NATIVE_CACHE", str(tmp_path / "cache"))
    with pytest.raises(build.NativeBuildError, match="compiling .*tick_core.c.* failed"):
        build.library_path()
    assert not list((tmp_path / "cache").glob("*.so"))            # nothing half-built left behind
    monkeypatch.setenv("CC", "/nonexistent/cc")
    with pytest.raises(build.NativeBuildError, match="needs a C compiler.*apt-get install gcc"):
        build.library_path()


def test_falls_back_to_the_user_cache_where_the_package_is_read_only(tmp_path, monkeypatch):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    src = pkg / "tick_core.c"
    shutil.copy(build.SOURCE, src)
    monkeypatch.setattr(build, "SOURCE", src)
    monkeypatch.delenv("POINTFENCE_NATIVE_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    real = os.access
    monkeypatch.setattr(build.os, "access", lambda p, mode: False if Path(p) == pkg / "_build" else real(p, mode))
    path = build.library_path()
    assert path.parent == tmp_path / "xdg" / "pointfence" / "native" and path.exists()


def test_bindings_refuse_arrays_the_core_cannot_read():
    with pytest.raises(TypeError, match="hip: .*float64.*got float32"):
        ptr(np.zeros((2, 3), np.float32), np.float64, "hip")
    with pytest.raises(TypeError, match="strided"):
        ptr(np.zeros((2, 6))[:, ::2], np.float64, "hip")
    ptr(np.zeros(3, bool), bool, "mask")


# --- teleoperation against the array expressions -----------------------------------------------------
class _ArrayTeleop:
    """service/teleop.py's docstring as NumPy array expressions (the implementation before the
    compiled core), for the per-tick methods."""

    def __init__(self, tp: Teleop):
        self.R, self.scale, self.step = tp.R, tp.scale, tp.vmax * tp.dt
        self.arch = tp.arch
        for name in ("dev_prev", "X_m", "hip", "e_hip", "cmd", "goal", "live", "anchored"):
            setattr(self, name, getattr(tp, name).copy())
        self.moved = np.zeros(tp.n)
        self.rebase, self.target = True, tp.X_m.copy()

    def map_masters(self, dev, pedal, ok):
        act = pedal & ok
        both = act & self.live
        self.live = act.copy()
        d = np.where(both[:, None], dev - self.dev_prev, 0.0)
        w = (d @ self.R.T) * self.scale
        self.moved += np.linalg.norm(w, axis=1)
        self.anchored &= self.moved < ANCHOR_RELEASE
        w[self.anchored] = 0.0
        self.X_m += w
        self.dev_prev = np.where(ok[:, None], dev, self.dev_prev)

    def update_hip(self, xr):
        self.target = (xr if self.arch == 2 else self.X_m).copy()
        if self.rebase:
            self.e_hip, self.rebase = self.hip - self.target, False
        n = np.maximum(np.linalg.norm(self.e_hip, axis=1), 1e-12)
        self.e_hip *= np.maximum(1.0 - self.step / n, 0.0)[:, None]
        self.hip = self.target + self.e_hip

    def reanchor(self, mask):
        self.X_m += np.where(mask[:, None], self.cmd - self.goal, 0.0)
        self.goal = np.where(mask[:, None], self.cmd, self.goal)
        self.anchored |= mask
        self.moved[mask] = 0.0
        self.rebase = True

    def limit_command(self, coupled, goal):
        self.goal = goal.copy()
        d = np.where((coupled & ~self.anchored)[:, None], self.goal - self.cmd, 0.0)
        n = np.linalg.norm(d, axis=1)
        d *= np.minimum(self.step / np.maximum(np.maximum(n, self.step), 1e-12), 1.0)[:, None]
        self.cmd += d


def test_teleop_core_matches_the_array_expressions_on_random_operation():
    rng = np.random.default_rng(5)
    n = 4
    T = np.eye(4)
    T[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    tp = Teleop(n, T, scale=0.4, max_robot_speed=0.2, dt=1e-3, architecture="III")
    tp.start(rng.normal(0, 0.01, (n, 3)), rng.normal(0, 0.05, (n, 3)))
    ref = _ArrayTeleop(tp)
    dev = rng.normal(0, 0.01, (n, 3))
    seen = {"anchored": 0, "invalid": 0, "limited": 0}
    for k in range(3000):
        if k % 500 == 250:                            # an architecture switch re-bases the HIP
            tp.set_architecture(("I", "II", "III")[k // 500 % 3])
            ref.arch, ref.rebase = tp.arch, True
        dev = dev + rng.normal(0, 2e-4, (n, 3))
        pedal = rng.random(n) > 0.05
        ok = rng.random(n) > 0.02
        sample = np.where(ok[:, None], dev, np.nan)   # an invalid sample is NaN: it must not leak
        tp.map_masters(sample, pedal, ok)
        ref.map_masters(sample, pedal, ok)
        if k % 97 == 0:
            mask = rng.random(n) > 0.5
            tp.reanchor(mask)
            ref.reanchor(mask)
        xr = tp.cmd + rng.normal(0, 1e-4, (n, 3))
        tp.update_hip(xr)
        ref.update_hip(xr)
        proxies = (tp.target + rng.normal(0, 3e-3, (n, 3))).astype(np.float32)
        goal = tp.command_goal(proxies, True).copy()
        assert np.array_equal(goal, proxies.astype(float) if tp.arch == 3 else tp.X_m)
        coupled = pedal & ok
        tp.limit_command(coupled)
        ref.limit_command(coupled, goal)
        for name in ("X_m", "hip", "e_hip", "cmd", "goal", "dev_prev"):
            np.testing.assert_allclose(getattr(tp, name), getattr(ref, name), rtol=1e-12, atol=1e-15, err_msg=name)
        assert np.array_equal(tp.anchored, ref.anchored) and np.array_equal(tp.live, ref.live)
        assert np.isfinite(tp.X_m).all()
        seen["anchored"] += int(tp.anchored.sum())
        seen["invalid"] += int((~ok).sum())
        seen["limited"] += int((np.linalg.norm(goal - tp.cmd, axis=1) > 1e-9).sum())
    assert all(v > 0 for v in seen.values()), seen


# --- the service binds its input's own arrays ------------------------------------------------------------
def test_step_reads_arrays_replaced_in_its_input(tmp_path):
    """A TickInput whose arrays are replaced (not written in place) between ticks, or given with
    other dtypes, is read as it is now: the core never reads an array the input no longer holds."""
    from test_tick_io import _input, _service

    svc, _ = _service(tmp_path)
    inp = _input(svc, 1, np.zeros(3))
    svc.step(inp)
    for k in range(2, 40):
        inp = _input(svc, k, np.zeros(3))
        svc.step(inp)
    assert svc.out.coupled.all()
    inp.k, inp.t = 40, 0.040
    inp.master_ok = np.zeros(1, np.int64)           # replaced, another dtype: the master is invalid
    out = svc.step(inp)
    assert out.arm_hold[0] & 8 and not out.coupled[0]          # MASTER hold, decoupled
    inp.k, inp.t = 41, 0.041
    inp.master_ok = [True]                           # a list: converted, and read again next tick
    inp.pedal = np.zeros(1, bool)                    # pedal up: decoupled for that reason now
    out = svc.step(inp)
    assert not out.coupled[0]
    assert isinstance(TickInput.zeros(1).master_pos, np.ndarray)


def test_the_core_is_the_bottom_layer():
    """native/ imports nothing of pointfence's: kernels/ builds on it, and it on nothing."""
    import ast

    for f in Path(build.__file__).parent.glob("*.py"):
        for node in ast.walk(ast.parse(f.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else []
            assert not any(n.startswith("pointfence") for n in names), f"{f.name} imports {names}"


def test_the_core_is_called_holding_the_interpreter_lock():
    """A tick's core calls must not hand the interpreter lock to another thread (each such hand
    -over can keep the tick waiting for up to the switch interval): the library is a PyDLL."""
    import ctypes

    from pointfence.native import lib

    assert isinstance(lib, ctypes.PyDLL)
    assert lib.pf_step_pre._flags_ & ctypes._FUNCFLAG_PYTHONAPI


def test_the_published_copy_is_the_ticks_output(tmp_path):
    """``publish`` copies every position, force and state of the tick's output (one core call)
    into what ``snapshot`` hands to other threads."""
    from test_tick_io import _input, _service

    svc, _ = _service(tmp_path)
    out = None
    for k in range(1, 60):
        inp = _input(svc, k, np.array([0.0, 0.0, -0.002 * k]))
        out = svc.step(inp)
        svc.publish(inp, out)
    snap = svc.snapshot()
    for key, name in (("xm", "xm"), ("hip", "hip"), ("proxy", "proxy"), ("cmd", "command"), ("xr", "robot_pos"),
                      ("force", "force"), ("state", "state")):
        assert np.array_equal(snap[key], getattr(out, name)), key
    assert snap["tick"] == out.k == 59 and np.abs(snap["force"]).max() > 0      # a real push, not zeros
