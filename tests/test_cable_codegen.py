"""C generation, the compiled-library cache, the no-compiler fallback, allocation-free calls."""
import shutil
import tracemalloc
import warnings

import casadi as ca
import numpy as np
import pytest

from pointfence.service.cable import codegen
from pointfence.service.cable.codegen import BufferedCall, CodegenFallbackWarning, compile_functions
from pointfence.service.cable.model import implicit_step
from pointfence.service.cable.params import GrasperParams


def _fn():
    return implicit_step()


@pytest.mark.skipif(shutil.which("gcc") is None and shutil.which("cc") is None, reason="no C compiler")
def test_compile_then_cache_hit(tmp_path, monkeypatch):
    monkeypatch.setenv("POINTFENCE_CACHE", str(tmp_path))
    monkeypatch.delenv("POINTFENCE_CC", raising=False)
    f = _fn()
    fns, how = compile_functions([f], "test_step")
    assert how == "compiled"
    libs = list((tmp_path / "cable").glob("test_step_*.so"))
    assert len(libs) == 1
    mtime = libs[0].stat().st_mtime_ns
    n_compiled = codegen.LAST_BUILD["compiled"]
    fns2, how2 = compile_functions([_fn()], "test_step")  # a "second start"
    assert how2 == "cached"
    assert codegen.LAST_BUILD["compiled"] == n_compiled
    assert libs[0].stat().st_mtime_ns == mtime
    x, p = np.array([0.1, 0.05, 0.3, -0.2]), GrasperParams().vector()
    ref = np.array(f(x, 0.02, p)).ravel()
    for g in (fns["cable_step"], fns2["cable_step"]):
        assert np.allclose(np.array(g(x, 0.02, p)).ravel(), ref, rtol=1e-12, atol=1e-14)


def test_fallback_without_compiler(tmp_path, monkeypatch):
    monkeypatch.setenv("POINTFENCE_CACHE", str(tmp_path))
    monkeypatch.setenv("POINTFENCE_CC", "no-such-compiler-xyz")
    f = _fn()
    with pytest.warns(CodegenFallbackWarning, match="no C compiler"):
        fns, how = compile_functions([f], "test_fb")
    assert how == "interpreted"
    assert not list(tmp_path.glob("**/*.so"))
    x, p = np.array([0.1, 0.05, 0.3, -0.2]), GrasperParams().vector()
    assert np.allclose(np.array(fns["cable_step"](x, 0.0, p)), np.array(f(x, 0.0, p)))


def test_fallback_when_compile_fails(tmp_path, monkeypatch):
    monkeypatch.setenv("POINTFENCE_CACHE", str(tmp_path))
    monkeypatch.setenv("POINTFENCE_CC", "false")  # exists, always fails
    with pytest.warns(CodegenFallbackWarning, match="failed"):
        _, how = compile_functions([_fn()], "test_fail")
    assert how == "interpreted"


def test_buffered_call_does_not_allocate():
    x = ca.SX.sym("x", 3)
    f = ca.Function("f", [x], [ca.densify(ca.vertcat(ca.sin(x), x.T @ x))])
    call = BufferedCall(f)
    call.args[0][:] = [0.1, 0.2, 0.3]
    call()
    assert np.allclose(call.res[0], np.r_[np.sin([0.1, 0.2, 0.3]), 0.14])
    tracemalloc.start()
    for _ in range(200):
        call()
    before = tracemalloc.get_traced_memory()[0]
    for _ in range(5000):
        call.args[0][0] += 1e-6
        call()
    after = tracemalloc.get_traced_memory()[0]
    tracemalloc.stop()
    assert after - before < 2048
    with pytest.raises(Exception, match="sparse"):
        BufferedCall(ca.Function("g", [x], [ca.SX(3, 1)]))
