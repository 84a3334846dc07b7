"""Build and load pointfence's compiled tick core (``tick_core.c``).

The library is compiled once with the machine's C compiler (``$CC``, else ``cc``) the first
time it is needed and kept in a cache named after a hash of the source and the flags, so a
changed source builds again (and the earlier build is removed) and an unchanged one loads at
once. The cache is ``_build/``
beside the source when that is writable (a checkout), else
``$XDG_CACHE_HOME/pointfence/native`` (default ``~/.cache``); ``POINTFENCE_NATIVE_CACHE``
overrides both. Concurrent first imports (several processes) are safe: each builds into its
own temporary file and renames it into place.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

SOURCE = Path(__file__).with_name("tick_core.c")
#: the headers tick_core.c includes (part of the source: hashed with it), found in this folder
HEADERS = (Path(__file__).with_name("tick_quat.h"), Path(__file__).with_name("proxy_out.h"))
#: -ffp-contract=off: every expression is evaluated as written (no fused multiply-add), so the
#: results do not depend on the compiler's choices
CFLAGS = ("-O2", "-fPIC", "-shared", "-std=c99", "-ffp-contract=off", "-fno-fast-math")


class NativeBuildError(RuntimeError):
    """The tick core could not be compiled or loaded (this package imports nothing of pointfence's:
    it is the bottom layer)."""


def _cache_dir() -> Path:
    env = os.environ.get("POINTFENCE_NATIVE_CACHE")
    if env:
        return Path(env)
    local = SOURCE.parent / "_build"
    try:
        local.mkdir(exist_ok=True)
        if os.access(local, os.W_OK):
            return local
    except OSError:
        pass
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "pointfence" / "native"


def _compiler() -> str:
    cc = os.environ.get("CC") or "cc"
    found = shutil.which(cc)
    if found is None:
        raise NativeBuildError(f"pointfence's tick core needs a C compiler and none was found (CC={cc!r}); install "
                               "one (Debian/Ubuntu: 'apt-get install gcc') or point CC at it")
    return found


def library_path() -> Path:
    """The compiled library for this source and platform, built now if it is not cached."""
    src = SOURCE.read_bytes() + b"".join(h.read_bytes() for h in HEADERS)
    tag = hashlib.sha256(src + " ".join(CFLAGS).encode() + platform.machine().encode()).hexdigest()[:16]
    out = _cache_dir() / f"libpf_tick_core-{tag}.so"
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    cc = _compiler()
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
    os.close(fd)
    try:
        r = subprocess.run([cc, *CFLAGS, "-I", str(HEADERS[0].parent), "-o", tmp, str(SOURCE), "-lm"],
                           capture_output=True, text=True)
        if r.returncode != 0:
            raise NativeBuildError(f"compiling {SOURCE} with {cc} failed (exit {r.returncode}):\n{r.stderr.strip()}")
        os.replace(tmp, out)
        for old in out.parent.glob("libpf_tick_core-*.so"):     # builds of earlier sources
            if old != out:
                old.unlink(missing_ok=True)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


def load() -> ctypes.CDLL:
    """Build (if needed) and load the tick core. Its functions run for microseconds inside the
    tick: they are called holding the interpreter lock (``ctypes.PyDLL``), since releasing it
    around each call would let another thread (frame ingest, UDP receiver, recorder) take it and
    keep the tick waiting for it back."""
    path = library_path()
    try:
        return ctypes.PyDLL(str(path))
    except OSError as e:
        raise NativeBuildError(f"loading the tick core {path} failed: {e}; delete it to rebuild") from None


if __name__ == "__main__":      # `python -m pointfence.native.build`: build now, print where
    print(library_path())
    sys.exit(0)
