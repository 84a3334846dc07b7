"""``pointfence calib <step> ...``: camera calibration steps, each printing residuals and writing
``[[camera]]`` keys (a snippet on stdout, ``--out FILE``, or merged into ``--config scene.toml``).

Each step is a module with ``add_arguments(parser)`` and ``run(args) -> int``, listed in
``SUBCOMMANDS``; another step (e.g. ``tension`` from the cable-instrument service) plugs in by
adding one entry there. Modules are imported only for the chosen step.
"""
from __future__ import annotations

import importlib
import sys

#: step -> (module, one-line help)
SUBCOMMANDS = {
    "intrinsics": ("pointfence.calib.intrinsics", "fx, fy, cx, cy and distortion from checkerboard images (OpenCV)"),
    "extrinsics": ("pointfence.calib.extrinsics",
                   "camera -> robot base from ArUco/AprilTag markers at known poses (low-pass filtered) or point pairs (Kabsch)"),
    "multi": ("pointfence.calib.multi", "refine one camera's pose against another by ICP on overlapping depth"),
    "noise": ("pointfence.calib.noise", "fit sigma_z = a + b Z^2 from depth captures of a plane at several distances"),
    "hand-eye": ("pointfence.calib.handeye",
                 "a fixed camera's T_world_cam from the robot moving a tip ball or an ArUco marker through logged poses"),
    "master": ("pointfence.calib.master_reg",
               "[teleop] T_world_master and scale from recorded master/robot positions (Umeyama) or a guided motion"),
    "tension": ("pointfence.service.cable.calib_tension",
                "cable tension = a + b ln(k_e) from identification at known tensions (chapter 5)"),
}


def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest="calib_step", metavar="STEP")
    chosen = _chosen_step()
    for name, (module, help_) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_ + "\n\n" + (_doc(module) if name == chosen else ""),
                           formatter_class=__import__("argparse").RawDescriptionHelpFormatter)
        p.set_defaults(_calib_module=module)
        if name == chosen:
            importlib.import_module(module).add_arguments(p)


def _chosen_step():
    """The step named on the command line (``pointfence calib STEP``), so only its module loads."""
    argv = sys.argv[1:]
    for i, a in enumerate(argv):
        if a == "calib" and i + 1 < len(argv):
            return argv[i + 1]
    return argv[0] if argv and argv[0] in SUBCOMMANDS else None


def _doc(module: str) -> str:
    return (importlib.import_module(module).__doc__ or "").strip()


def run(args) -> int:
    module = getattr(args, "_calib_module", None)
    if module is None:
        print("usage: pointfence calib {" + ",".join(SUBCOMMANDS) + "} ...", file=sys.stderr)
        for name, (_, help_) in SUBCOMMANDS.items():
            print(f"  {name:<11} {help_}", file=sys.stderr)
        return 2
    return int(importlib.import_module(module).run(args) or 0)


def main(argv=None) -> int:
    """``python -m pointfence.calib.cli STEP ...`` (the same as ``pointfence calib STEP ...``)."""
    import sys

    from pointfence.cli import main as pointfence_main

    return pointfence_main(["calib", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
