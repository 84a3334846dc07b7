"""The C library through ctypes, loaded once, for the few Linux calls the service makes
(``prctl``: service/memory.py, service/osthread.py)."""
from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.lru_cache(maxsize=None)
def libc() -> ctypes.CDLL:
    """The process's C library (``errno`` kept for ``ctypes.get_errno``)."""
    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
