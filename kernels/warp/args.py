"""The Warp proxy kernels' argument structs: the batch's constants and a tick's values.

Lengths in m, times in s, in the world (robot base) frame; spans in hash cells.
"""
from __future__ import annotations

import warp as wp

from ..neighbors import search_span


@wp.struct
class ProxyArgs:
    """A batch's constants (HapticParams and the working-set skin), set once per batch."""

    r1: float
    band: float  # r2 - r1
    nreach: float  # r3 - r1
    step: float
    tol: float
    slack: float
    margin: float
    turn_back: float  # turn_back_cos
    skin: float  # regather when the proxy is further than this from where its set was gathered
    gather_r: float  # reach + skin: the working set's radius
    skin_min: float  # the same for a set that does not fit with ``skin`` (HapticParams.skin)
    gather_r_min: float
    rclip: float  # no step can be shortened by a point with clearance >= rclip (kernels/warp/steps.py)
    fixture: int
    max_steps: int
    span: int  # cells searched on each side (reach, without motion)


@wp.struct
class TickArgs:
    """Per-tick values, read by the kernel from pinned host memory (or copied in the graph)."""

    dt: float  # prediction time: points are taken at p + v dt (kernels/motion.py)
    span: int  # cells searched on each side: reach plus the motion's extra reach
    grad: float  # a gather's reach in the hash: reach + skin plus the motion's extra reach
    build: int  # the snapshot's build number (slot.seq): the working-set cache's key


def proxy_args(p, reach: float, gather_skin: float, h: float) -> ProxyArgs:
    """The ``ProxyArgs`` of a batch with HapticParams ``p``, query reach ``reach`` (m), working-set
    skin ``gather_skin`` on the GPU (m; at least ``p.skin`` is used) and hash cells of ``h`` m."""
    a = ProxyArgs()
    a.r1, a.band, a.nreach, a.step = p.r1, p.band, p.r3 - p.r1, p.step
    a.tol, a.slack, a.fixture, a.max_steps = p.tolerance, p.slack, int(p.mode == "fixture"), p.max_steps
    a.margin = p.margin
    a.turn_back = p.turn_back_cos
    a.skin_min = p.skin
    a.gather_r_min = reach + p.skin
    a.skin = max(p.skin, gather_skin)
    a.gather_r = reach + a.skin
    # no step can be shortened by a point with clearance >= rclip (kernels/warp/steps.py)
    a.rclip = 0.5 * p.band + p.margin + p.step * 1.0001 + 1.0e-6
    a.span = search_span(reach, h)
    return a
