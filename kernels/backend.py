"""What every compute backend provides: a frame pipeline owning double-buffered snapshots."""
from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .camera import Camera
from .motion import MotionEstimator
from .neighbors import Neighbors, check_queries
from .params import PipelineParams
from .rig import Rig
from .snapshot import HostSnapshot
from .yielding import checkpoint


@dataclass(frozen=True)
class IngestInfo:
    """What one ingest produced: snapshot number, point counts, and wall time in ms."""

    seq: int
    n_points: int
    per_camera: tuple
    ms: float


def run_steps(steps):
    """Run a generator of ``ingest_steps``' kind (or what is left of it) to its end; its return
    value."""
    try:
        while True:
            next(steps)
    except StopIteration as e:
        return e.value


class FramePipeline(ABC):
    """Frames in, snapshots out.

    ``ingest(frames)`` validates one frame per camera, builds the snapshot (deproject,
    transform, noise, radius, selection, crop, counting sort) into the back slot and publishes
    it; on any error nothing is published and the previous snapshot stays current.
    Queries (``neighbors``, the proxy kernel) always run against the published snapshot.
    """

    backend: "Backend"

    def __init__(self, cameras: Sequence[Camera], params: PipelineParams):
        self.rig = Rig(cameras)
        self.params = params
        self.grid = params.grid()
        self.motion = MotionEstimator(params.motion, self.grid)
        self.seq = 0

    def _estimate_motion(self, moments_fn, timestamps):
        """Per-cell velocities of the snapshot being built: (cell velocities (n_cells, 3) float32
        or None, largest speed m/s). ``moments_fn()`` returns its cell moments (count, sum x, y,
        z) per cell; it is not called while motion estimation is off."""
        if not self.params.motion.enabled:
            return None, 0.0
        from .motion import snapshot_time

        return self.motion.update(moments_fn(), snapshot_time(timestamps))

    def ingest(self, frames) -> IngestInfo:
        return run_steps(self.ingest_steps(frames))

    def ingest_steps(self, frames):
        """``ingest`` as a generator in two parts. The first (up to the one ``yield``, of None)
        validates the frames and, on a backend that builds on a device (OpenCL, Warp on CUDA),
        enqueues the build's device work into the back slot and submits it; the second waits for
        it, publishes the snapshot and returns its ``IngestInfo`` (as ``StopIteration.value``).
        Nothing is published before the yield. Between the two parts the caller may run other
        work (a replay's ticks, on the front snapshot) while the device builds, but must not
        ingest again nor write a ``depth_staging`` array. ``run_steps`` runs both parts at once.
        An error raises in either part and publishes nothing; a generator closed at its yield
        waits for the submitted work."""
        t0 = time.perf_counter()
        ordered = self.rig.order(frames)
        packed = self.rig.pack(ordered, self.params.lateral_px)  # validates per-frame poses
        checkpoint()
        n, per_cam = yield from self._build_steps(ordered, packed)
        self.seq += 1
        return IngestInfo(self.seq, n, per_cam, (time.perf_counter() - t0) * 1e3)

    def depth_staging(self, camera) -> np.ndarray | None:
        """A host array (H, W) uint16 that camera ``camera`` (name or index)'s next depth image
        can be written into, or None where the backend has none.

        A frame whose ``depth`` is this array is ingested without the host copy into the
        backend's upload buffer (on CUDA: pinned memory the build's graph uploads from), so a
        camera driver that writes its image here saves a copy of every frame. Write it only
        between ingests (``ingest`` has finished with it when it returns)."""
        return None

    def neighbors(self, queries, radius: float, max_neighbors: int = 64, protected_only: bool = False) -> Neighbors:
        """Points within ``radius`` (m) of each query (B, 3) in the current snapshot."""
        q = check_queries(queries, radius, max_neighbors)
        return self._neighbors(q, float(radius), int(max_neighbors), bool(protected_only))

    @abstractmethod
    def _build_steps(self, frames: list, packed):
        """Build into the back slot and publish, as ``ingest_steps``' generator: device work
        submitted before its one yield, the wait and the publication after it; returns
        (n_points, per_camera counts)."""

    @abstractmethod
    def _neighbors(self, q, radius: float, max_neighbors: int, protected_only: bool) -> Neighbors: ...

    @abstractmethod
    def host_snapshot(self) -> HostSnapshot:
        """A host copy of the current snapshot (for tests, visualisation and export)."""


class Backend(ABC):
    """A compute backend: a name, a device, and factories for its kernels."""

    name: str = "?"

    @property
    @abstractmethod
    def device_name(self) -> str: ...

    @abstractmethod
    def pipeline(self, cameras: Sequence[Camera], params: PipelineParams) -> FramePipeline: ...
