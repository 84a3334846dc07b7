"""OpenCL program builds are quiet (kernels/opencl/context.build_source): a successful build keeps
the compiler's log in the program and shows it only when asked (``verbose``,
``PYOPENCL_COMPILER_OUTPUT=1``, ``pointfence --verbose``); a failed build raises ``KernelError``
carrying the log."""
import os
import warnings

import numpy as np
import pytest

from pointfence.cli import main
from pointfence.kernels.errors import KernelError
from pointfence.kernels.haptics import HapticParams
from pointfence.kernels.opencl.backend import OpenCLBackend
from pointfence.kernels.opencl.context import _cl, build_log, build_source

from kernel_cases import params_for, random_rig

#: every OpenCL compiler warns on ``#warning``: a build that succeeds with a non-empty log
NOISY = '#warning "pointfence-noisy-build"\n__kernel void f(__global int *a) { a[0] = 1; }\n'
#: and fails on ``#error``
BROKEN = '#error "pointfence-broken-build"\n__kernel void f(__global int *a) { a[0] = 1; }\n'


@pytest.fixture
def quiet_env(monkeypatch):
    """Builds with the compiler output switch off (whatever the caller's shell says)."""
    monkeypatch.setenv("PYOPENCL_COMPILER_OUTPUT", "0")


@pytest.fixture(scope="module")
def ctx():
    return OpenCLBackend().context


def _recorded(fn):
    """(result of fn(), every Python warning it emitted, none filtered away)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = fn()
    return out, caught


def test_a_build_with_compiler_output_emits_no_warning_and_keeps_the_log(ctx, quiet_env):
    prg, caught = _recorded(lambda: build_source(ctx, NOISY, "noisy.cl"))
    assert caught == [], [str(w.message) for w in caught]
    assert "pointfence-noisy-build" in build_log(prg)
    assert prg.f is not None   # built and usable


def test_the_product_programs_build_without_a_python_warning(quiet_env):
    """Everything the OpenCL backend builds (zero-copy check, frame pipeline, proxy kernel on both
    PoCL devices) on a fresh backend: no warning reaches the console."""
    def make():
        rng = np.random.default_rng(3)
        cams, frames = random_rig(rng, n_cams=1)
        backend = OpenCLBackend()
        pipe = backend.pipeline(cams, params_for("mask", adaptive=False, cell=0.02))
        pipe.ingest(frames)
        start = pipe.host_snapshot().points[:2, :3].astype(np.float64)
        p = HapticParams(mode="rendering")
        batches = [pipe.proxies(start, p), pipe.proxies(start, p, inline=False)]
        for b in batches:
            b.step(start)
        return pipe, batches

    (pipe, batches), caught = _recorded(make)
    assert caught == [], [f"{w.category.__name__}: {w.message}" for w in caught]
    assert {b.device_kind for b in batches} == ({"in-thread", "pool"} if pipe.inline_ctx is not None else {"pool"})


@pytest.mark.parametrize("how", ["argument", "environment"])
def test_verbose_shows_the_log_as_a_compiler_warning(ctx, monkeypatch, how):
    cl = _cl()
    if how == "environment":
        monkeypatch.setenv("PYOPENCL_COMPILER_OUTPUT", "1")
        kw = {}
    else:
        monkeypatch.setenv("PYOPENCL_COMPILER_OUTPUT", "0")
        kw = {"verbose": True}
    _, caught = _recorded(lambda: build_source(ctx, NOISY, "noisy.cl", **kw))
    assert len(caught) == 1 and issubclass(caught[0].category, cl.CompilerWarning)
    text = str(caught[0].message)
    assert "noisy.cl" in text and "pointfence-noisy-build" in text


def test_a_failed_build_raises_with_the_compilers_log(ctx, quiet_env):
    with pytest.raises(KernelError) as e:
        build_source(ctx, BROKEN, "broken.cl", ["-cl-fp32-correctly-rounded-divide-sqrt"])
    msg = str(e.value)
    assert "broken.cl" in msg and "pointfence-broken-build" in msg   # which program, and the compiler's words
    assert "-cl-fp32-correctly-rounded-divide-sqrt" in msg and "POINTFENCE_OPENCL_DEVICE" in msg


def test_the_cli_verbose_flag_turns_compiler_output_on(monkeypatch, capsys):
    monkeypatch.setenv("PYOPENCL_COMPILER_OUTPUT", "0")
    assert main(["--verbose", "backends"]) == 0
    assert os.environ["PYOPENCL_COMPILER_OUTPUT"] == "1"
    monkeypatch.setenv("PYOPENCL_COMPILER_OUTPUT", "0")
    assert main(["backends"]) == 0
    assert os.environ["PYOPENCL_COMPILER_OUTPUT"] == "0"
