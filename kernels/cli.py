"""`pointfence backends`: which compute backends and OpenCL devices this machine has."""
from __future__ import annotations

from .errors import PointfenceError
from .registry import BACKENDS, get_backend


def add_arguments(p):
    pass


def run(args) -> int:
    for name, (_m, _c, needs, how) in BACKENDS.items():
        try:
            b = get_backend(name)
            print(f"{name:7s} available: {b.device_name}")
        except PointfenceError as e:
            print(f"{name:7s} unavailable: {e}")
    try:
        from .opencl.context import list_devices

        devs = list_devices()
        if devs:
            print("OpenCL devices (select with --device '<part of the name>'):")
            for p, d, t in devs:
                note = ""
                if d.lower().startswith("basic") and ("pocl" in p.lower() or "portable computing" in p.lower()):
                    note = "  (runs kernels in the calling thread: pointfence's haptic ticks of up to 16 proxies)"
                print(f"  {p}: {d} [{t}]{note}")
    except PointfenceError:
        pass
    return 0
