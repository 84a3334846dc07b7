"""The Warp tick kernels' generated code: no function calls, and the register caps in force.

A call that the compiler does not inline makes the kernel keep, around the call, the values
live across it and the callee's registers on top (kernels/warp/steps.py): the tick kernel went
from about 130 to 240 registers a thread that way, and so from three blocks of 128 threads an
SM to two. The kernels are compiled for sm_90 with Warp's NVRTC, which needs no GPU, and their
PTX is read: no ``call`` instruction, and the ``.maxnreg`` of ``WarpTuning.maxreg_for``.
"""
import re

import pytest

wp = pytest.importorskip("warp", reason="warp-lang is not installed: pip install 'pointfence[warp]'")

from pointfence.kernels.warp.tick_kernels import tick_kernel  # noqa: E402
from pointfence.kernels.warp.tuning import WarpTuning  # noqa: E402


def ptx_of(kernel, tmp_path):
    # (asked before compiling: a kernel that fails to compile fails the test, never skips it)
    if 90 not in wp.get_cuda_supported_archs():
        pytest.skip("this Warp build has no NVRTC for sm_90 (wp.get_cuda_supported_archs)")
    wp.compile_aot_module(kernel.module, arch=90, module_dir=str(tmp_path), use_ptx=True)
    ptx = "".join(p.read_text() for p in tmp_path.glob("*.ptx"))
    assert ".entry" in ptx
    return ptx


@pytest.mark.parametrize("resident", [False, True])
@pytest.mark.parametrize("n", [1, 1024, 65536])
def test_tick_kernels_call_no_function_and_carry_their_register_cap(tmp_path, n, resident):
    """The default tuning's kernel for each batch-size row (256, 128 and 32 threads a proxy),
    launched and resident."""
    t = WarpTuning()
    bd = t.block_dim_for(n)
    maxreg = t.maxreg_for(bd)
    ptx = ptx_of(tick_kernel(t.ws_capacity_for(n), maxreg, bd, resident=resident), tmp_path)
    calls = re.findall(r"^\s*call(?:\.uni)?\s.*$", ptx, re.M)
    assert not calls, f"{len(calls)} calls in the tick kernel, e.g. {calls[0].strip()[:120]}"
    assert re.findall(r"\.maxnreg\s+(\d+)", ptx) == ([str(maxreg)] if maxreg else [])
