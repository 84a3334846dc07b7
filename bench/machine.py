"""What machine a benchmark ran on, for bench/RESULTS.md."""
from __future__ import annotations

import datetime
import os
import platform
import time


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict:
    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "date": datetime.date.today().isoformat(),
    }


#: the fields of /proc/stat's "cpu" line, in order (jiffies; USER_HZ = 100 on Linux)
_FIELDS = ("user", "nice", "system", "idle", "iowait", "irq", "softirq", "steal")


def cpu_times() -> dict | None:
    """This machine's CPU time so far, summed over cores (s), from /proc/stat; None where the
    file does not exist (not Linux)."""
    try:
        with open("/proc/stat") as f:
            first = f.readline().split()
    except OSError:
        return None
    hz = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    vals = [int(x) for x in first[1:1 + len(_FIELDS)]]
    return {k: v / hz for k, v in zip(_FIELDS, vals)} | {"wall": time.monotonic()}


def cpu_usage(before: dict | None, after: dict | None) -> dict:
    """What the machine's cores did between two ``cpu_times()`` readings: ``busy_pct`` (of all
    cores' time), ``steal_ms`` (time the hypervisor gave a virtual core to someone else: the
    virtual machine stood still; every core counted) and ``steal_pct``. Empty off Linux."""
    if not before or not after:
        return {}
    d = {k: after[k] - before[k] for k in _FIELDS}
    total = sum(d.values())
    if total <= 0:
        return {}
    busy = total - d["idle"] - d["iowait"] - d["steal"]
    return {"busy_pct": round(100 * busy / total, 1), "steal_ms": round(1e3 * d["steal"], 1),
            "steal_pct": round(100 * d["steal"] / total, 2)}
