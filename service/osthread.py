"""The operating system's view of the service's threads: the calling thread's name, so that
``top -H``, ``perf sched`` and ``ps -L`` tell them apart (Python 3.13 and older leave every thread
named after the process; Linux keeps 15 bytes of it), and a thread's real-time scheduling
(``set_fifo``)."""
from __future__ import annotations

import ctypes
import os
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


def set_fifo(native_id: int, priority: int) -> str:
    """``SCHED_FIFO`` ``priority`` for thread ``native_id`` of this process where the OS allows it
    (0: leave it as it is); returns what applies, for a status: ``"SCHED_FIFO <p>"``, ``"normal"``
    or ``"normal (SCHED_FIFO refused: <why>)"``."""
    if priority <= 0:
        return "normal"
    try:
        os.sched_setscheduler(int(native_id), os.SCHED_FIFO, os.sched_param(int(priority)))
    except (AttributeError, OSError) as e:
        return f"normal (SCHED_FIFO refused: {e})"
    return f"SCHED_FIFO {int(priority)}"
