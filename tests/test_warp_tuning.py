"""The Warp kernels' tuning: a frozen dataclass passed in, checked, never read at import."""
import ast
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from pointfence.kernels.errors import InputError

wp = pytest.importorskip("warp", reason="warp-lang is not installed: pip install 'pointfence[warp]'")

from pointfence.kernels.warp.resident_protocol import RESIDENT_CAP  # noqa: E402
from pointfence.kernels.warp.tuning import ANY, ENVIRONMENT, WarpTuning  # noqa: E402

KERNELS = Path(__file__).resolve().parents[1] / "kernels"


def test_defaults_pick_by_batch_size():
    t = WarpTuning()
    assert [t.block_dim_for(n) for n in (1, 64, 65, 4096, 4097, 10**6)] == [256, 256, 128, 128, 32, 32]
    assert [t.ws_capacity_for(n) for n in (1, 64, 65, 4096, 4097)] == [2496, 2496, 1536, 1536, 768]
    assert t.maxreg_for(256) == 0 and t.maxreg_for(512) == 128 and t.maxreg_for(1024) == 64
    # the default tables' launched block sizes: one block an SM more than uncapped
    assert t.maxreg_for(128) == 168 and t.maxreg_for(32) == 152 and t.maxreg_for(64) == 0
    assert 3 * 128 * t.maxreg_for(128) <= 65536 and 13 * 32 * t.maxreg_for(32) <= 65536
    assert WarpTuning(maxregs=((64, 96),)).maxreg_for(64) == 96 and WarpTuning(maxregs=()).maxreg_for(128) == 0
    one = WarpTuning(block_dim=512, maxreg=96)
    assert one.block_dim_for(1) == one.block_dim_for(10**6) == 512 and one.maxreg_for(512) == 96
    # the GPU skin: wider where the sets have room (up to 64 proxies), unless one is given for all
    assert [t.gather_skin_for(n) for n in (1, 64, 65, 10**6)] == [2.5e-3, 2.5e-3, 1.5e-3, 1.5e-3]
    assert WarpTuning(gather_skin=0.0).gather_skin_for(1) == 0.0 == WarpTuning(gather_skin=0).gather_skin_for(10**6)
    assert WarpTuning(gather_skins=((ANY, 0.002),)).gather_skin_for(7) == 0.002
    with pytest.raises(dataclasses.FrozenInstanceError):
        t.gather_skin = 0.0


@pytest.mark.parametrize("field, value, words", [
    ("block_dim", 48, "block_dim = 48"),
    ("block_dim", 2048, "multiple of 32 from 32 to 1024"),
    ("block_dims", ((64, 256), (4096, 100), (ANY, 32)), "100 threads"),
    ("block_dims", ((4096, 128), (64, 256)), "ascending"),
    ("ws_caps", ((64, 2496),), "every batch"),
    ("ws_caps", "lots", "largest batch"),
    ("resident_max", RESIDENT_CAP + 1, f"resident_max = {RESIDENT_CAP + 1}; expected an integer from 0 to {RESIDENT_CAP}"),
    ("resident_max", -1, "resident_max = -1"),
    ("zero_copy_max", 1.5, "zero_copy_max = 1.5"),
    ("stage_min", -2, "stage_min = -2; expected an integer from 0"),
    ("ws_cache_max", True, "ws_cache_max = True"),
    ("maxreg", 300, "maxreg = 300"),
    ("maxregs", ((48, 128),), "maxregs = ((48, 128),)"),
    ("maxregs", ((128, 300),), "caps from 32 to 255"),
    ("maxregs", "many", "maxregs = 'many'"),
    ("run_pixels", 0, "run_pixels = 0; expected an integer from 1"),
    ("gather_skin", float("nan"), "gather_skin = nan"),
    ("gather_skin", -1e-3, "gather_skin = -0.001"),
    ("gather_skins", ((64, 2e-3),), "gather_skins = ((64, 0.002),); expected rows of (largest batch, skin"),
    ("gather_skins", ((64, -1.0), (ANY, 1e-3)), "skin >= 0 m"),
    ("gather_skins", "wide", "gather_skins = 'wide'"),
])
def test_bad_tuning_is_an_input_error_naming_the_field(field, value, words):
    with pytest.raises(InputError, match=words.replace("(", r"\(").replace(")", r"\)")):
        WarpTuning(**{field: value})


def test_environment_overrides_only_the_documented_switches():
    env = {"POINTFENCE_WARP_RESIDENT_MAX": "0", "POINTFENCE_WARP_WS_CACHE_MAX": " 16 ",
           # no longer read: tuning is passed in (WarpTuning), not taken from the environment
           "POINTFENCE_WARP_BLOCK_DIM": "512", "POINTFENCE_WARP_SKIN": "0.01", "POINTFENCE_WARP_RUN_PIXELS": "4"}
    t = WarpTuning.from_environment(env)
    assert t == WarpTuning(resident_max=0, ws_cache_max=16)
    assert WarpTuning.from_environment({}) == WarpTuning()
    base = WarpTuning(gather_skin=0.002)
    assert WarpTuning.from_environment({"POINTFENCE_WARP_RESIDENT_MAX": "4"}, base) == WarpTuning(gather_skin=0.002,
                                                                                                  resident_max=4)
    assert set(ENVIRONMENT) == {"POINTFENCE_WARP_RESIDENT_MAX", "POINTFENCE_WARP_WS_CACHE_MAX"}
    with pytest.raises(InputError, match="POINTFENCE_WARP_RESIDENT_MAX = 'many': not an integer"):
        WarpTuning.from_environment({"POINTFENCE_WARP_RESIDENT_MAX": "many"})
    with pytest.raises(InputError, match="POINTFENCE_WARP_RESIDENT_MAX = '99'.*expected an integer from 0 to 62"):
        WarpTuning.from_environment({"POINTFENCE_WARP_RESIDENT_MAX": "99"})


def test_documented_switches_are_the_ones_read():
    """README.md documents exactly the environment switches ``from_environment`` reads."""
    readme = (KERNELS.parent / "README.md").read_text()
    for var in ENVIRONMENT:
        assert var in readme, var
    for gone in ("POINTFENCE_WARP_BLOCK_DIM", "POINTFENCE_WARP_MAXREG", "POINTFENCE_WARP_SKIN",
                 "POINTFENCE_WARP_ZERO_COPY_MAX", "POINTFENCE_WARP_RUN_PIXELS"):
        assert gone not in readme, gone


def test_backend_reads_the_environment_when_made_and_passes_its_tuning_on(monkeypatch):
    from pointfence.kernels import get_backend
    from pointfence.kernels.haptics import HapticParams
    from pointfence.kernels.warp.backend import WarpBackend

    from kernel_cases import params_for, random_rig

    monkeypatch.setenv("POINTFENCE_WARP_WS_CACHE_MAX", "3")
    assert get_backend("warp", "cpu").tuning.ws_cache_max == 3
    monkeypatch.setenv("POINTFENCE_WARP_WS_CACHE_MAX", "-3")
    with pytest.raises(InputError, match="POINTFENCE_WARP_WS_CACHE_MAX"):
        get_backend("warp", "cpu")
    with pytest.raises(InputError, match="expected a WarpTuning"):
        WarpBackend("cpu", tuning={"gather_skin": 0.0})

    mine = WarpTuning(gather_skin=0.004, run_pixels=3)
    backend = get_backend("warp", "cpu", tuning=mine)   # (the environment is not read: a tuning is given)
    assert backend.tuning is mine and WarpBackend("cpu", tuning=mine).tuning is mine
    with pytest.raises(InputError, match="backend 'warp' has no option tunning; its options: tuning"):
        get_backend("warp", "cpu", tunning=mine)
    cams, frames = random_rig(np.random.default_rng(2), n_cams=1)
    pipe = backend.pipeline(cams, params_for("all"))
    pipe.ingest(frames)   # (the build's counting pass takes run_pixels)
    p = HapticParams()
    batch = pipe.proxies(np.zeros((2, 3)) + [0, 0, 0.8], p)
    assert batch.tuning is mine and batch.skin == pytest.approx(max(p.skin, 0.004))
    other = WarpTuning(gather_skin=0.0)
    batch = pipe.proxies(np.zeros((2, 3)) + [0, 0, 0.8], p, tuning=other)
    assert batch.tuning is other and batch.skin == pytest.approx(p.skin)
    # by batch size: the skin follows the batch through resets across a row of gather_skins
    batch = pipe.proxies(np.zeros((2, 3)) + [0, 0, 0.8], p, tuning=WarpTuning(gather_skins=((4, 0.003), (ANY, 0.001))))
    skins = []
    for n in (2, 5, 4, 9):
        batch.reset(np.zeros((n, 3)) + [0, 0, 0.8])
        batch.step(np.zeros((n, 3)) + [0, 0.004, 0.8])   # (free motion: 4 mm along y)
        np.testing.assert_allclose(batch.positions[:, 1], 0.004, atol=1e-6)
        skins.append(batch.skin)
    assert skins == pytest.approx([0.003, 0.001, 0.003, 0.001])
    with pytest.raises(InputError, match="expected a WarpTuning"):
        pipe.proxies(np.zeros((2, 3)), p, tuning=0.004)


def _module_level_environment_reads(tree: ast.Module) -> list:
    """Lines where ``tree`` touches ``os.environ`` / ``os.getenv`` outside any function body."""
    out = []

    def walk(node, in_function):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            in_function = True
        if (not in_function and isinstance(node, ast.Attribute) and node.attr in ("environ", "getenv")
                and isinstance(node.value, ast.Name) and node.value.id == "os"):
            out.append(node.lineno)
        for child in ast.iter_child_nodes(node):
            walk(child, in_function)

    walk(tree, False)
    return out


def test_no_kernels_module_reads_the_environment_at_import():
    found = {}
    for f in sorted(KERNELS.rglob("*.py")):
        lines = _module_level_environment_reads(ast.parse(f.read_text()))
        if lines:
            found[str(f.relative_to(KERNELS.parent))] = lines
    assert not found, f"environment read at import (pass tuning in instead): {found}"
    assert _module_level_environment_reads(ast.parse("import os\nX = os.environ.get('A')\n")) == [2]
    assert _module_level_environment_reads(ast.parse("import os\ndef f():\n    return os.getenv('A')\n")) == []
