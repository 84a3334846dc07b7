"""The `pointfence` command.

Each subcommand lives in the module named in COMMANDS, which provides
``add_arguments(parser)`` and ``run(args) -> int``; modules are imported only when used.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys

from pointfence.kernels.errors import PointfenceError

#: subcommand -> (module, one-line help)
COMMANDS = {
    "demo": ("pointfence.service.demo", "run the main job on the embedded defaults (PoCL CPU, synthetic scene)"),
    "bench": ("pointfence.bench.cli", "benchmarks (frames, query, stress, ...) printing JSON"),
    "serve": ("pointfence.service.serve", "the live service with authenticated UDP haptic clients (clients/PROTOCOL.md); --new-key FILE makes a key"),
    "ctl": ("pointfence.service.ctl", "control a running `pointfence serve` through its local HTTP JSON API (status, metrics, architecture, engage/disengage, radius, selection)"),
    "device-sim": ("pointfence.clients.device_sim", "a simulated haptic device (trajectory CSV or scripted motion) against a live service"),
    "replay": ("pointfence.service.replay", "deterministic offline run of the whole service (scripted master or a recording): ticks.csv, summary.json"),
    "inspect": ("pointfence.service.inspect_cmd", "what an MCAP recording holds (topics, rates, cameras, arms, faults, holds) "
                "and the run's measures; --json, --plot DIR"),
    "ros2": ("pointfence.service.ros2.cli", "ROS 2 nodes (optional extra pointfence[ros2]): camera-node, sim-arm, ..."),
    "backends": ("pointfence.kernels.cli", "list compute backends and devices available here"),
    "calib": ("pointfence.calib.cli", "camera calibration: intrinsics, extrinsics, multi (ICP), noise; cable tension"),
    "cable": ("pointfence.service.cable.cli", "cable-driven grasper: demo, identify, calib-tension, run (simulated plant)"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pointfence", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=_version())
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="show the OpenCL compiler's log of every program build (sets PYOPENCL_COMPILER_OUTPUT=1); "
                             "a failed build always shows it")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        p.set_defaults(_module=module)
        # Sub-parsers are filled in lazily only for the chosen command (fast start).
        if name in sys.argv[1:2]:
            importlib.import_module(module).add_arguments(p)
    return parser


def _version() -> str:
    from pointfence import __version__

    return f"pointfence {__version__}"


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    saved = sys.argv
    sys.argv = [saved[0]] + list(argv)
    try:
        parser = build_parser()
    finally:
        sys.argv = saved
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    if args.verbose:
        os.environ["PYOPENCL_COMPILER_OUTPUT"] = "1"   # read by kernels/opencl/context.py at each build
    try:
        return int(importlib.import_module(args._module).run(args) or 0)
    except PointfenceError as e:
        print(f"pointfence {args.command}: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
