"""C code generation for the hot CasADi functions, with a compiled-library cache.

``compile_functions()`` generates one C file for a set of CasADi functions, compiles it with
the system C compiler into ``<cache>/<prefix>_<hash>.so`` (hash of the generated source, the
compiler command and the CasADi version) and loads it with ``casadi.external``. A second start
with the same functions finds the library and does not recompile. When no C compiler is found,
or compiling fails, it warns (``CodegenFallbackWarning``) and returns the functions unchanged:
CasADi's own virtual machine then evaluates them (slower, same results).

``BufferedCall`` binds preallocated numpy arrays to a function's inputs and outputs through
``casadi.Function.buffer()``, so that a call in the control loop allocates nothing.

Environment: ``POINTFENCE_CC`` (compiler, default ``cc``/``gcc``; an empty value or a
missing program forces the fallback), ``POINTFENCE_CACHE`` (cache root, default
``~/.cache/pointfence``).
"""
from __future__ import annotations

import hashlib
import os
import shlex
import shutil
import subprocess
import tempfile
import threading
import warnings
from pathlib import Path

import casadi as ca
import numpy as np

from pointfence.kernels.errors import InputError

CFLAGS = ("-O2", "-fPIC", "-shared", "-fno-fast-math")
_lock = threading.Lock()
#: Libraries compiled or loaded by this process: hash -> path (for tests and reports).
LAST_BUILD = {"compiled": 0, "cache_hits": 0, "fallbacks": 0}


class CodegenFallbackWarning(RuntimeWarning):
    """No working C compiler: CasADi's interpreter evaluates the functions instead."""


def cache_dir() -> Path:
    root = os.environ.get("POINTFENCE_CACHE") or os.path.join(Path.home(), ".cache", "pointfence")
    return Path(root) / "cable"


def find_compiler() -> list[str] | None:
    env = os.environ.get("POINTFENCE_CC")
    if env is not None:
        parts = shlex.split(env)
        if not parts or shutil.which(parts[0]) is None:
            return None
        return [shutil.which(parts[0])] + parts[1:]
    for cand in ("cc", "gcc", "clang"):
        path = shutil.which(cand)
        if path:
            return [path]
    return None


def generated_source(functions, prefix: str) -> str:
    cg = ca.CodeGenerator(prefix + ".c", {"with_header": False, "casadi_real": "double"})
    for f in functions:
        cg.add(f)
    return cg.dump()


def compile_functions(functions, prefix: str) -> tuple[dict, str]:
    """Compiled versions of ``functions`` (name -> casadi.Function) and how they were obtained.

    The second element is ``"compiled"``, ``"cached"`` or ``"interpreted"`` (fallback).
    """
    functions = list(functions)
    if not functions:
        raise InputError("compile_functions needs at least one CasADi function, got none")
    if not prefix.isidentifier():
        raise InputError(f"library prefix {prefix!r} must be a C identifier")
    cc = find_compiler()
    if cc is None:
        LAST_BUILD["fallbacks"] += 1
        warnings.warn(
            f"no C compiler found (POINTFENCE_CC={os.environ.get('POINTFENCE_CC')!r}); "
            f"evaluating {prefix} with CasADi's interpreter, which is slower",
            CodegenFallbackWarning, stacklevel=2)
        return {f.name(): f for f in functions}, "interpreted"
    src = generated_source(functions, prefix)
    key = hashlib.sha256("\0".join([src, " ".join(cc), " ".join(CFLAGS), ca.__version__]).encode()).hexdigest()[:20]
    out_dir = cache_dir()
    lib = out_dir / f"{prefix}_{key}.so"
    how = "cached"
    with _lock:
        if not lib.exists():
            how = "compiled"
            try:
                out_dir.mkdir(parents=True, exist_ok=True)
                with tempfile.TemporaryDirectory(dir=out_dir) as tmp:
                    c_file = Path(tmp) / f"{prefix}.c"
                    c_file.write_text(src)
                    tmp_lib = Path(tmp) / lib.name
                    proc = subprocess.run([*cc, *CFLAGS, str(c_file), "-o", str(tmp_lib), "-lm"],
                                          capture_output=True, text=True, timeout=600)
                    if proc.returncode != 0:
                        raise RuntimeError(proc.stderr.strip()[-2000:])
                    os.replace(tmp_lib, lib)  # atomic: concurrent starts never see half a file
                    # keep the source next to the library for inspection
                    (out_dir / f"{prefix}_{key}.c").write_text(src)
            except (OSError, RuntimeError, subprocess.SubprocessError) as e:
                LAST_BUILD["fallbacks"] += 1
                warnings.warn(f"compiling {prefix} with {cc[0]} failed ({e}); evaluating it with "
                              "CasADi's interpreter, which is slower", CodegenFallbackWarning, stacklevel=2)
                return {f.name(): f for f in functions}, "interpreted"
            LAST_BUILD["compiled"] += 1
        else:
            LAST_BUILD["cache_hits"] += 1
    return {f.name(): ca.external(f.name(), str(lib)) for f in functions}, how


class BufferedCall:
    """Allocation-free calls of a CasADi function on preallocated numpy buffers.

    ``args[i]`` / ``res[i]`` are float64 arrays shaped like the function's i-th input/output
    (column-major views, as CasADi stores them). Fill ``args`` in place, call, read ``res``.
    """

    def __init__(self, fn: ca.Function):
        self.fn = fn
        self._flat_args, self._flat_res, self.args, self.res = [], [], [], []
        self._buf, self._eval = fn.buffer()
        for i in range(fn.n_in()):
            sp = fn.sparsity_in(i)
            if not sp.is_dense():
                raise InputError(f"{fn.name()} input {i} is sparse; BufferedCall needs dense inputs")
            flat = np.zeros(sp.nnz())
            self._flat_args.append(flat)
            self.args.append(flat.reshape(sp.shape, order="F") if sp.size2() > 1 else flat)
            self._buf.set_arg(i, memoryview(flat))
        for i in range(fn.n_out()):
            sp = fn.sparsity_out(i)
            if not sp.is_dense():
                raise InputError(f"{fn.name()} output {i} is sparse; densify it for BufferedCall")
            flat = np.zeros(sp.nnz())
            self._flat_res.append(flat)
            self.res.append(flat.reshape(sp.shape, order="F") if sp.size2() > 1 else flat)
            self._buf.set_res(i, memoryview(flat))

    def __call__(self) -> None:
        self._eval()
