"""Build and load pointfence's compiled libraries: the tick core (``tick_core.c``, with the robot
process's shared-memory exchange ``shm_exchange.c``), the UDP
receiver (``udp_rx.c``, with the C client's SHA-256 and codec from ``clients/c``) and the
self-filter's pixel test (``selffilter.c``).

Each library is compiled once with the machine's C compiler (``$CC``, else ``cc``) the first
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
from typing import Optional

_HERE = Path(__file__).parent
SOURCE = _HERE / "tick_core.c"
#: the tick core's other source: the robot process's shared-memory exchange
EXCHANGE = _HERE / "shm_exchange.c"
#: and the copy of a tick's structs into a recording's row
ROWS = _HERE / "tick_rows.c"
#: the headers tick_core.c includes (part of the source: hashed with it), found in this folder
HEADERS = (_HERE / "tick_quat.h", _HERE / "neighbor_rows.h")
#: the C client's folder (``pointfence.clients``' ``c/``: a sibling package in a checkout and
#: in an installation alike)
_CLIENT_C = _HERE.parent / "clients" / "c"
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


class _Lib:
    """One library: its name, C sources, the headers they include (hashed with them), include
    folders and linker flags."""

    def __init__(self, name: str, sources, headers, includes, libs):
        self.name, self.sources, self.headers, self.includes, self.libs = name, sources, headers, includes, libs


def _tick_core() -> _Lib:
    return _Lib("libpf_tick_core", (SOURCE, EXCHANGE, ROWS), HEADERS, (HEADERS[0].parent,), ("-lm",))


UDP_RX = _Lib("libpf_udp_rx", (_HERE / "udp_rx.c", _CLIENT_C / "src" / "pf_sha256.c", _CLIENT_C / "src" / "pf_protocol.c"),
              (_HERE / "udp_rx_session.h", _HERE / "udp_tick.h", _CLIENT_C / "include" / "pointfence_client.h"),
              (_HERE, _CLIENT_C / "include"),
              ("-lm", "-pthread"))


#: the robot self-filter's pixel test (kernels/selffilter.py)
SELF_FILTER = _Lib("libpf_selffilter", (_HERE / "selffilter.c",), (), (), ("-lm",))


def library_path(lib: Optional[_Lib] = None) -> Path:
    """The compiled library (default: the tick core) for its sources and this platform, built
    now if it is not cached."""
    lib = lib if lib is not None else _tick_core()
    src = b"".join(p.read_bytes() for p in (*lib.sources, *lib.headers))
    tag = hashlib.sha256(src + " ".join(CFLAGS).encode() + platform.machine().encode()).hexdigest()[:16]
    out = _cache_dir() / f"{lib.name}-{tag}.so"
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    cc = _compiler()
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
    os.close(fd)
    try:
        inc = [a for d in lib.includes for a in ("-I", str(d))]
        r = subprocess.run([cc, *CFLAGS, *inc, "-o", tmp, *map(str, lib.sources), *lib.libs], capture_output=True, text=True)
        if r.returncode != 0:
            raise NativeBuildError(f"compiling {lib.sources[0]} with {cc} failed (exit {r.returncode}):\n{r.stderr.strip()}")
        os.replace(tmp, out)
        for old in out.parent.glob(f"{lib.name}-*.so"):     # builds of earlier sources
            if old != out:
                old.unlink(missing_ok=True)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


def _open(path: Path, what: str, kind):
    """Library ``path`` loaded as ``kind`` (``ctypes.CDLL`` or ``ctypes.PyDLL``); a load that
    fails names ``what`` and the file to delete."""
    try:
        return kind(str(path))
    except OSError as e:
        raise NativeBuildError(f"loading the {what} {path} failed: {e}; delete it to rebuild") from None


def load() -> ctypes.CDLL:
    """Build (if needed) and load the tick core. Its functions run for microseconds inside the
    tick: they are called holding the interpreter lock (``ctypes.PyDLL``), since releasing it
    around each call would let another thread (frame ingest, UDP receiver, recorder) take it and
    keep the tick waiting for it back."""
    return _open(library_path(), "tick core", ctypes.PyDLL)


def load_udp_rx():
    """Build (if needed) and load the UDP receiver twice: ``(waiting, held)``. Calls through
    ``waiting`` (``ctypes.CDLL``) hand the interpreter lock over while they run, for the calls
    that wait for data; calls through ``held`` (``ctypes.PyDLL``) keep it, for the tick's copy of
    a sample and the other calls of microseconds."""
    path = library_path(UDP_RX)
    return _open(path, "UDP receiver", ctypes.CDLL), _open(path, "UDP receiver", ctypes.PyDLL)


def load_self_filter() -> ctypes.CDLL:
    """Build (if needed) and load the self-filter's pixel test. Its calls hand the interpreter
    lock over while they run (``ctypes.CDLL``): it runs on a frame thread, for tens to hundreds
    of microseconds, beside the haptic loop that needs the lock."""
    dll = _open(library_path(SELF_FILTER), "self-filter", ctypes.CDLL)
    P = ctypes.c_void_p
    fn = dll.pf_selffilter_capsule
    fn.restype = ctypes.c_int64
    fn.argtypes = [P, P, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64,
                   ctypes.c_double, P, P, ctypes.c_double, P]
    return dll


if __name__ == "__main__":      # `python -m pointfence.native.build`: build now, print where
    print(library_path())
    print(library_path(UDP_RX))
    print(library_path(SELF_FILTER))
    sys.exit(0)
