"""The robot's tool in the live service's frames: a ring of joint positions per tick, and the
frame filter that drops the tool from every frame at the frame's capture time (dissertation
6.4; ``kernels/selffilter.py``).

* ``ToolPoseRing``: the haptic tick writes every robot's measured joints with the tick's time on
  the frames' clock (``Service.frame_time``) into a preallocated ring (no allocation per tick;
  a lock held for a few microseconds). Any thread looks a pose up at a time (linear
  interpolation between the two ticks around it; the oldest kept pose for older times, the
  newest for later ones; before the first tick the robots' poses at construction).
* ``ToolFilter``: called by the frame feeder on every snapshot's frames before ingest (in the
  ingest thread for live runs, in the tick for offline ones): per frame, the robots' joints at
  its capture time (timestamp minus the camera latency ``[motion] latency`` that the timestamps
  do not include), the tool capsules (``robot.tool.tool_capsules``) and ``SelfFilter.apply``.
  A frame already filtered (the same frame object: LiveFrames re-ingests every camera's latest
  frame when one camera delivers) is not filtered again.
"""
from __future__ import annotations

import ctypes
import math
import threading
from typing import Optional, Sequence

import numpy as np

from pointfence.kernels.errors import InputError
from pointfence.kernels.selffilter import Capsule, SelfFilter
from pointfence.kernels.yielding import checkpoint
from pointfence.native import ROW_KINDS, RowField, fast, ptr

from .robot.tool import ToolModel, tool_capsules


def _joint_reader(robot):
    """A call that writes ``robot``'s measured joints into an array (robot/base.py's
    ``measured_jp_into``, else the positions of ``measured_js()``)."""
    fill = getattr(robot, "measured_jp_into", None)
    if fill is not None:
        return fill

    def read(out: np.ndarray) -> None:
        q = robot.measured_js().position
        out[: len(q)] = q
    return read


class ToolPoseRing:
    """Joint positions of ``robots`` (None entries: no robot) over the last ``capacity`` ticks."""

    def __init__(self, robots: Sequence, capacity: int = 1024):
        self.robots = list(robots)
        self.capacity = int(max(2, capacity))
        self.dof = max([r.dof for r in self.robots if r is not None] or [1])
        n = len(self.robots)
        self.times = np.full(self.capacity, -math.inf)
        self.q = np.zeros((self.capacity, n, self.dof))
        self.q0 = np.zeros((n, self.dof))           # poses at construction: frames before the first tick
        for b, r in enumerate(self.robots):
            if r is not None:
                _joint_reader(r)(self.q0[b])
        self.count = 0
        self.misses = 0        # look-ups older than the oldest kept pose (the oldest was used)
        self._lock = threading.Lock()
        # robots whose measured joints are a live array (a hosted arm's row of the shared block,
        # ``measured_jp_view``) are copied into the slot's row by one compiled call
        views = [(b, getattr(r, "measured_jp_view", None)) for b, r in enumerate(self.robots) if r is not None]
        self._gather = None
        if views and all(v is not None for _, v in views):
            rows = [(b, v()) for b, v in views]
            if all(isinstance(a, np.ndarray) and a.dtype == np.float64 and a.flags.c_contiguous
                   and a.size <= self.dof for _, a in rows):
                fields = (RowField * len(rows))(*(RowField(a.ctypes.data, b * self.dof, a.size, ROW_KINDS[a.dtype])
                                                  for b, a in rows))
                self._gather = (fields, ctypes.c_int64(len(rows)), ptr(self.q.reshape(self.capacity, -1), np.float64,
                                "pose ring"), ctypes.c_int64(n * self.dof), rows)
        # otherwise, per ring slot, each robot's joint reader and its row of that slot, made once:
        # a tick's record is then the readers' calls alone
        self._slots = None
        if self._gather is None:
            readers = [(b, _joint_reader(r)) for b, r in enumerate(self.robots) if r is not None]
            self._slots = [tuple((read, self.q[i, b]) for b, read in readers) for i in range(self.capacity)]

    def record(self, t: float) -> None:
        """The robots' measured joints now, at time ``t`` (frames' clock; increasing)."""
        with self._lock:
            i = self.count % self.capacity
            g = self._gather
            if g is not None:
                fast.pf_row_gather(g[0], g[1], g[2], g[3], i)
            else:
                for read, row in self._slots[i]:
                    read(row)
            self.times[i] = t
            self.count += 1

    def at(self, t: float, out: Optional[np.ndarray] = None) -> np.ndarray:
        """Joints (B, dof) at time ``t`` (see the module docstring)."""
        out = np.empty_like(self.q0) if out is None else out
        with self._lock:
            n, cap = self.count, self.capacity
            if n == 0:
                out[:] = self.q0
                return out
            newest = (n - 1) % cap
            oldest = 0 if n <= cap else n % cap
            if t >= self.times[newest]:
                out[:] = self.q[newest]
                return out
            if t <= self.times[oldest]:   # before the first tick the robot held its first recorded pose
                if n > cap and t < self.times[oldest]:
                    self.misses += 1
                out[:] = self.q[oldest]
                return out
            # two sorted segments: [oldest, cap) and [0, newest]
            if n > cap and oldest > 0 and t >= self.times[0]:
                j = int(np.searchsorted(self.times[: newest + 1], t, side="right")) - 1
            else:
                hi = cap if n > cap else newest + 1
                j = oldest + int(np.searchsorted(self.times[oldest:hi], t, side="right")) - 1
            k = (j + 1) % cap
            t0, t1 = self.times[j], self.times[k]
            w = 0.0 if t1 <= t0 else (t - t0) / (t1 - t0)
            np.multiply(self.q[j], 1.0 - w, out=out)
            out += w * self.q[k]
        return out


def clip_capsule(c: Capsule, lo, hi) -> Optional[Capsule]:
    """The part of capsule ``c`` that can touch the box ``lo``-``hi`` (its segment clipped to the
    box grown by the radius; None if none): points outside the workspace never reach a snapshot,
    and a short capsule's bounding sphere covers far fewer pixels."""
    a, b = np.asarray(c.a), np.asarray(c.b)
    lo, hi = np.asarray(lo) - c.radius, np.asarray(hi) + c.radius
    d = b - a
    s0, s1 = 0.0, 1.0
    for i in range(3):
        if abs(d[i]) < 1e-15:
            if a[i] < lo[i] or a[i] > hi[i]:
                return None
            continue
        u, v = (lo[i] - a[i]) / d[i], (hi[i] - a[i]) / d[i]
        s0, s1 = max(s0, min(u, v)), min(s1, max(u, v))
        if s0 > s1:
            return None
    if s0 == 0.0 and s1 == 1.0:
        return c
    return Capsule(tuple(a + s0 * d), tuple(a + s1 * d), c.radius)


def self_filter_for(cfg, pp, robots: Sequence) -> tuple:
    """(ToolPoseRing, ToolFilter, None) for the service of configuration ``cfg`` (pipeline
    parameters ``pp``) where every robot's tool is known (S5: ``robot.tool.tool_model_for``);
    else (None, None, why there is none). An explicit ``self_filter = true`` without a known
    tool is an InputError."""
    from .robot.tool import tool_model_for

    sc = cfg.service
    present = [r for r in robots if r is not None]
    if not present:
        return None, None, "no robot model: nothing to filter"
    if not cfg.self_filter:
        return None, None, "off in the configuration ([service] self_filter = false)"
    models = [tool_model_for(r, cfg.robot.tool) for r in present]
    unknown = [why for model, why in models if model is None]
    if unknown:
        if sc.self_filter:
            raise InputError(f"[service] self_filter = true, but {unknown[0]}")
        return None, None, unknown[0]
    horizon = sc.max_frame_age_s + pp.motion.latency + 0.25
    ring = ToolPoseRing(robots, int(math.ceil(horizon * sc.rate_hz)))
    flt = ToolFilter([c.camera for c in cfg.cameras], robots, ring, latency=pp.motion.latency,
                     margin=sc.self_filter_margin, model=models[0][0], workspace=(pp.workspace.min, pp.workspace.max))
    return ring, flt, None


class ToolFilter:
    """The feeder's frame filter: every frame without the robots' tools at its capture time.
    ``workspace`` ((min, max) corners, m): the capsules are clipped to it (plus the margin)."""

    def __init__(self, cameras: Sequence, robots: Sequence, ring: ToolPoseRing, latency: float = 0.0,
                 margin: float = 0.003, model: Optional[ToolModel] = None, workspace=None):
        self.filter = SelfFilter(cameras, margin=margin)
        self.box = None if workspace is None else (np.asarray(workspace[0], float) - margin,
                                                   np.asarray(workspace[1], float) + margin)
        self.robots = list(robots)
        self.ring = ring
        self.latency = float(latency)
        self.model = model if model is not None else ToolModel()
        self._q = np.empty_like(ring.q0)
        self._done: dict = {}          # camera -> (input frame, filtered frame)
        self.frames = 0                # frames filtered
        self.removed = 0               # tool pixels dropped, in all
        self.last_removed = 0

    def capsules_at(self, t: float) -> list:
        """Every robot's tool capsules at time ``t`` (frames' clock)."""
        q = self.ring.at(t, self._q)
        caps = []
        for b, r in enumerate(self.robots):
            if r is not None:
                checkpoint()
                caps += tool_capsules(r, q[b, : r.dof], self.model)
        if self.box is not None:
            caps = [c for c in (clip_capsule(c, *self.box) for c in caps) if c is not None]
        return caps

    def __call__(self, frames: Sequence) -> list:
        out = []
        for f in frames:
            done = self._done.get(f.camera)
            if done is not None and done[0] is f:
                out.append(done[1])
                continue
            caps = self.capsules_at(float(f.timestamp) - self.latency)
            g = self.filter.apply([f], caps)[0]
            self.frames += 1
            self.last_removed = self.filter.removed
            self.removed += self.filter.removed
            self._done[f.camera] = (f, g)
            out.append(g)
        return out

    def status(self) -> dict:
        return {"frames": self.frames, "removed_pixels": self.removed, "last_removed_pixels": self.last_removed,
                "pose_misses": self.ring.misses}
