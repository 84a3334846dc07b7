"""The operating system's name of the calling thread, so that ``top -H``, ``perf sched`` and
``ps -L`` tell the service's threads apart (Python 3.13 and older leave every thread named after
the process). Linux keeps 15 bytes of it."""
from __future__ import annotations

import ctypes
import sys
import threading

from .libc import libc

PR_SET_NAME = 15


def name_this_thread(name: str) -> bool:
    """Give the calling thread ``name`` (cut to 15 bytes) at the OS level; whether it took."""
    if not sys.platform.startswith("linux"):
        return False
    return libc().prctl(PR_SET_NAME, ctypes.c_char_p(name.encode()[:15]), 0, 0, 0) == 0


def os_thread_name(native_id: int | None = None) -> str | None:
    """The OS name of thread ``native_id`` of this process (default: the calling thread)."""
    tid = threading.get_native_id() if native_id is None else native_id
    try:
        with open(f"/proc/self/task/{tid}/comm") as f:
            return f.read().strip()
    except OSError:
        return None
