"""Keeping the kernel's memory management out of the haptic loop's way.

Transparent huge pages stall a live service. NumPy asks for huge pages on its large arrays
(``madvise(MADV_HUGEPAGE)``), and the kernel's ``khugepaged`` then collapses the process's
pages into huge ones in the background. A collapse holds the process's memory-map lock for its
whole length and is not preempted in a voluntary-preemption kernel: on the 2-core VM of
bench/HISTORY.md (``perf sched timehist`` over a 4-proxy ``bench loop``), ``khugepaged`` ran
5-14 ms at a time on one core while the SCHED_FIFO loop thread sat off the CPU waiting, a few
times a minute; those were the loop's remaining 4-19 ms stalls and most of its deadline misses.

``small_pages()`` turns that off for the process and the children it starts afterwards: the
kernel's per-process switch (``prctl(PR_SET_THP_DISABLE)``: khugepaged skips the process and no
new huge page is made for it) and NumPy's own request. The pages already huge stay so (no
collapse is needed for them). Live runs call it before anything else (service/runner.py).
"""
from __future__ import annotations

import ctypes
import sys

from .libc import libc

PR_SET_THP_DISABLE = 41
PR_GET_THP_DISABLE = 42


def small_pages() -> str:
    """Transparent huge pages off for this process (and later children) and NumPy's huge-page
    requests off; returns what was done, for the service's status."""
    done = []
    try:
        from numpy._core import multiarray as ma   # NumPy 2
    except ImportError:   # NumPy 1.x
        from numpy.core import multiarray as ma
    setter = getattr(ma, "_set_madvise_hugepage", None)
    if setter is not None:
        setter(False)
        done.append("numpy madvise off")
    if sys.platform.startswith("linux"):
        if libc().prctl(PR_SET_THP_DISABLE, 1, 0, 0, 0) == 0:
            done.append("THP off (prctl)")
        else:
            done.append(f"THP prctl refused (errno {ctypes.get_errno()})")
    return ", ".join(done) or "unchanged (not Linux)"


def huge_pages_disabled() -> bool:
    """Whether the kernel's per-process THP switch is off for this process (Linux)."""
    if not sys.platform.startswith("linux"):
        return False
    return libc().prctl(PR_GET_THP_DISABLE, 0, 0, 0, 0) == 1
