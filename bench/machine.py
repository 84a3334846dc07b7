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


def process_times(roles: dict) -> dict | None:
    """CPU time so far (s, user + system) of this process and its descendants, summed by role:
    ``roles`` maps a role name to a text its command line contains (the first that matches
    names it; this process is "service", a descendant matching none "other"). None off Linux."""
    me = os.getpid()
    hz = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    procs = {}
    try:
        names = os.listdir("/proc")
    except OSError:
        return None
    for name in names:
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat") as f:
                stat = f.read()
            with open(f"/proc/{name}/cmdline", "rb") as f:
                cmd = f.read().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue          # (ended meanwhile)
        rest = stat.rsplit(")", 1)[1].split()
        procs[int(name)] = (int(rest[1]), (int(rest[11]) + int(rest[12])) / hz, cmd)
    out: dict = {}
    for pid, (_, t, cmd) in procs.items():
        p, seen = pid, 0
        while p not in (me, 0, 1) and p in procs and seen < 64:      # is ``pid`` a descendant of this process?
            p, seen = procs[p][0], seen + 1
        if p != me:
            continue
        role = "service" if pid == me else next((r for r, text in roles.items() if text in cmd), "other")
        out[role] = out.get(role, 0.0) + t
    return out | {"wall": time.monotonic()}


def process_usage(before: dict | None, after: dict | None) -> dict:
    """Each role's share of one core between two ``process_times`` readings (%; processes that
    ended in between are not counted)."""
    if not before or not after:
        return {}
    wall = after["wall"] - before["wall"]
    return {r: round(100 * (after[r] - before.get(r, 0.0)) / wall, 1)
            for r in after if r != "wall" and wall > 0}
