"""``pointfence calib tension``: the chapter-5 tension calibration under the calib command.

Follows the ``add_arguments(parser)`` / ``run(args) -> int`` convention of the command tables
and forwards to the same code as ``pointfence cable calib-tension``.
"""
from __future__ import annotations

from .cli import add_calib_arguments as add_arguments
from .cli import run_calib as run

__all__ = ["add_arguments", "run"]
