"""The product never imports the benchmarks: bench/ measures the product, so it may import any of
it, but no module of kernels/, service/, clients/, calib/ or pointfence/ may import
``pointfence.bench`` (a scene the demo runs lives in the product: service/dynamic_scenes.py).
The CLI names ``pointfence.bench.cli`` as a string for ``pointfence bench``: that is the
command's entry, loaded on demand, not an import of the product's."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: the product's folders and the package each one is (pyproject.toml's package-dir)
PRODUCT = {"pointfence": "pointfence", "kernels": "pointfence.kernels", "service": "pointfence.service",
           "clients": "pointfence.clients", "calib": "pointfence.calib"}


def _imports(path: Path, package: str) -> list:
    """(line, absolute module name) of every import statement of ``path`` (in ``package``)."""
    tree = ast.parse(path.read_text(), str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:   # relative: resolve against the module's package
                parts = package.split(".")
                base = parts[: len(parts) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.append((node.lineno, mod))
            out += [(node.lineno, f"{mod}.{a.name}") for a in node.names]
    return out


def bench_imports() -> list:
    """'file:line imports module' for every product module that imports pointfence.bench."""
    bad = []
    for folder, pkg in PRODUCT.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT / folder).with_suffix("")
            package = ".".join([pkg, *rel.parts[:-1]])
            for line, mod in _imports(path, package):
                if mod == "pointfence.bench" or mod.startswith("pointfence.bench."):
                    bad.append(f"{path.relative_to(ROOT)}:{line} imports {mod}")
    return bad


def test_no_product_module_imports_the_benchmarks():
    bad = bench_imports()
    assert not bad, ("the product imports the benchmarks (bench measures, never serves; move what the product "
                     "needs into it):\n" + "\n".join(bad))


def test_the_check_sees_absolute_and_relative_bench_imports(tmp_path):
    """The checker itself: both spellings of an import of bench are caught, a string is not."""
    src = tmp_path / "m.py"
    src.write_text("from ..bench import dynamic\nimport pointfence.bench.loop\nX = 'pointfence.bench.cli'\n"
                   "from . import frames\n")
    mods = [m for _, m in _imports(src, "pointfence.service")]
    assert "pointfence.bench.dynamic" in mods and "pointfence.bench.loop" in mods
    assert "pointfence.service.frames" in mods
    assert not any("cli" in m for m in mods)
