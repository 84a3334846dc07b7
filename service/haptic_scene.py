"""The haptic scene: depth frames in, proxies and forces out.

It owns the frame pipeline (snapshots of the protected points, built by the frame feeder's
thread or, offline, inside the tick), the publish gate that lets a tick query one snapshot
whole, the batch of B proxies (ONE kernel launch per tick for all of them), the force renderer
(dead band, contact damping, FIR, saturation: ``kernels.forces``) and the robot self-filter
(``toolpose``). Per tick: ``sense`` (the tick's time on the frames' clock, the robots' joints
into the self-filter's ring, the newest snapshot's age) and ``render`` (proxies toward their
targets, then the forces on the HIPs).

``prepare_reconfiguration`` changes the snapshots' radius or selection at runtime: a new
pipeline is built and warmed up outside the tick, and ``Reconfiguration.commit`` swaps it in
between two ticks.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Callable, Optional

import numpy as np

from pointfence.kernels.errors import ConflictError, InputError, PointfenceError
from pointfence.kernels.forces import ForceRenderer
from pointfence.kernels.haptics import haptic_pipeline_params
from pointfence.kernels.params import PipelineParams
from pointfence.native import ptr

from .frames import PublishGate
from .tick_io import TickInput, TickOutput

#: the proxy's outer band used for the hash cell size (m, as in config.py)
_DEFAULT_R3 = 0.010


class HapticScene:
    """Frames -> proxies -> forces for ``n`` arms; see the module docstring.

    Args:
        cfg: the parsed ``config.SceneConfig``.
        params: the haptic parameters (``HapticParams``) at the service's rate.
        backend: the compute backend (``kernels.get_backend``).
        robots: one robot per arm (None: ideal), for the self-filter.
    """

    def __init__(self, cfg, params, backend, robots, n: int):
        self.cfg = cfg
        self.params = params
        self.n = int(n)
        pp = cfg.pipeline if cfg.cell_size_given else haptic_pipeline_params(params, cfg.pipeline)
        self.backend = backend
        self.pipeline = backend.pipeline([c.camera for c in cfg.cameras], pp)
        self.gate = PublishGate(self.pipeline)
        from .toolpose import self_filter_for

        #: the robot self-filter, where every robot's tool is known (S5); else ``self_filter_off`` says why
        self.tool_poses, self.frame_filter, self.self_filter_off = self_filter_for(cfg, pp, robots)
        self.predict = bool(pp.motion.enabled)
        self.feeder = None
        self._frame_time = None
        self._poll_tick = self._poll = False
        self.batch = None
        self.renderer = ForceRenderer(n, params)
        #: whether the proxies ran on the last tick (haptic rendering engaged)
        self.running = False
        self.frame_seq = 0
        #: the first tick that saw each snapshot number
        self.snapshot_first_tick: dict = {}
        self._reseat_pos = np.zeros((n, 3))
        self._bound_batch: tuple = (None, None)      # (storage, (positions, states) pointers)
        self._bound_hip: tuple = (None, None)         # (array, pointer)

    # --- set-up ----------------------------------------------------------------------------------
    def attach_frames(self, feeder) -> None:
        """The frame feeder (``frames.LiveFrames``/``SimFrames``/``ScheduledFrames``) whose
        ``max_age(now)`` the ticks check (offline feeders are polled inside the tick)."""
        self.feeder = feeder
        if self.frame_filter is not None:
            feeder.frame_filter = self.frame_filter
        self._frame_time = getattr(feeder, "frame_time", None)
        self._poll_tick = hasattr(feeder, "poll_tick")
        self._poll = hasattr(feeder, "poll")

    def start(self, hip: np.ndarray, running: bool) -> None:
        """The proxies start on ``hip`` (B, 3; world, m); forces restart from zero."""
        if self.batch is not None:
            self.batch.close()
        self.batch = self.pipeline.proxies(hip, self.params)
        self.renderer.reset()
        self.running = running

    def warm_up(self, hip: np.ndarray) -> None:
        """Launch the proxy kernel once on a throw-away batch (same program and batch size), so
        that a just-in-time compiling runtime (PoCL) compiles it before the loop's first tick."""
        probe = self.pipeline.proxies(hip, self.params)
        with self.gate.lock:
            probe.step(hip)
        probe.close()

    # --- per tick --------------------------------------------------------------------------------
    def sense(self, inp: TickInput) -> None:
        """The tick's frame time, age and the self-filter's pose ring (into ``inp``); an offline
        feeder builds its due snapshots here."""
        feeder = self.feeder
        if feeder is None:
            inp.frame_time, inp.frame_age, inp.frames_too_old = math.nan, 0.0, False
            return
        tf = self._frame_time(inp.t, inp.now) if self._frame_time is not None else None
        inp.frame_time = math.nan if tf is None else tf
        inp.frame_age = self._advance_frames(inp)
        self._judge_age(inp)

    def sense_recorded(self, inp: TickInput) -> None:
        """A replayed tick (``inp`` holds the recorded frame time and age): the self-filter's
        pose ring at the recorded frame time, the offline feeder's due snapshots, and whether an
        old snapshot is a camera problem (STALE) or an ingest one, as ``sense`` decides it."""
        self._advance_frames(inp)
        self._judge_age(inp)

    def _advance_frames(self, inp: TickInput) -> float:
        """The robots' joints into the self-filter's ring at the tick's frame time, an offline
        feeder's due snapshots built; returns the newest published snapshot's age (s)."""
        feeder = self.feeder
        if self.tool_poses is not None and inp.frame_time == inp.frame_time:     # (not NaN)
            self.tool_poses.record(inp.frame_time)
        if self._poll_tick:
            feeder.poll_tick(inp.k, inp.t)
        elif self._poll:
            feeder.poll(inp.t)
        return feeder.max_age(inp.now)

    def _judge_age(self, inp: TickInput) -> None:
        """Whether a snapshot past ``max_frame_age_s`` is a camera problem (frames stopped: STALE)
        or an ingest one (frames arrive, no snapshot: INGEST)."""
        inp.frames_too_old = (inp.frame_age > self.cfg.service.max_frame_age_s
                              and self.feeder.frames_too_old(inp.now))

    def reseat(self, mask: np.ndarray, at: np.ndarray) -> None:
        """Proxies of arms in ``mask`` (B,) start again from ``at`` (B, 3); the others stay."""
        np.copyto(self._reseat_pos, self.batch.positions)
        np.copyto(self._reseat_pos, at, where=mask[:, None])
        self.batch.reset(self._reseat_pos)

    def batch_pointers(self) -> tuple:
        """The proxies' positions ((B, 3) float32, world, m) and states ((B,) int32) as pointers
        for the compiled tick core, and their surface normals ((B, 3) float32, the batch's own
        array, updated in place every tick; the same object until the batch changes), bound
        again only when the batch (or its storage) changes."""
        pos = self.batch.positions
        key = pos.base if pos.base is not None else pos
        if key is not self._bound_batch[0]:
            self._bound_batch = (key, (ptr(pos, np.float32, "proxy positions"),
                                       ptr(self.batch.states, np.int32, "proxy states"), self.batch.normals))
        return self._bound_batch[1]

    def render(self, inp: TickInput, out: TickOutput, targets: np.ndarray, hip: np.ndarray) -> None:
        """ONE kernel launch: every proxy toward ``targets`` (B, 3) in the published snapshot
        (predicted to the tick's frame time with ``[motion] enabled``), then the forces on the
        HIPs ``hip`` (B, 3) into ``renderer.forces``. Raises ``KernelError``."""
        w0 = time.perf_counter()
        with self.gate.lock:
            seq = self.gate.front_seq()
            if self.predict and inp.frame_time == inp.frame_time:      # (not NaN)
                self.batch.step(targets, now=inp.frame_time)
            else:
                self.batch.step(targets)
        out.kernel_us = (time.perf_counter() - w0) * 1e6
        if seq != self.frame_seq:
            self.frame_seq = seq
            self.snapshot_first_tick.setdefault(seq, inp.k)
        if hip is not self._bound_hip[0]:
            self._bound_hip = (hip, ptr(hip, np.float64, "hip"))
        proxies, states, _ = self.batch_pointers()
        if self.renderer.update_bound(proxies, self._bound_hip[1], states):
            # a proxy or HIP that is not finite: the renderer changed nothing; name the row
            self.renderer.update(self.batch.positions, hip, self.batch.states)

    @property
    def forces(self) -> np.ndarray:
        """(B, 3) this tick's rendered forces (world, N) before the hold ramp."""
        return self.renderer.forces

    # --- runtime reconfiguration ------------------------------------------------------------------
    def prepare_reconfiguration(self, hip: np.ndarray, radius=None, selection=None) -> Optional["Reconfiguration"]:
        """A new pipeline with this radius (``RadiusModel``) and/or selection, built on the
        current frames and warmed up here (not in a tick), the feeder already building into it;
        None if nothing changes. ``hip``: where the warm-up batch's proxies start. Raises
        InputError for parameters that cannot be, ConflictError for a change the current state
        refuses (nothing changed then)."""
        if self.cfg.mode != "fixture":
            raise ConflictError(f"has no effect in rendering mode ([fixture] mode = {self.cfg.mode!r}: every point "
                                "is rendered, none carries a fixture radius)")
        feeder = self.feeder
        if feeder is None or not hasattr(feeder, "swap_pipeline"):
            raise ConflictError("cannot be changed at runtime here: the service has no frame feeder that can move "
                                "to a rebuilt pipeline")
        pp = self._new_params(radius, selection)
        old = self.pipeline
        if pp == old.params:
            return None
        try:
            new = self.backend.pipeline(list(old.rig.cameras), pp)
        except PointfenceError as e:
            raise InputError(str(e)) from None
        gate = PublishGate(new)
        # A first snapshot in the new pipeline (feeder paused for that one build) so the batch
        # can be compiled and launched once off the tick thread.
        with feeder.ingest_lock:
            latest = list(feeder.latest)
            if any(f is None for f in latest):
                raise ConflictError("not applied: not every camera has delivered a frame yet")
            try:
                new.ingest(latest)
            except PointfenceError as e:
                raise ConflictError(f"not applied: the frames do not build with the new parameters: {e}") from None
            protected_new = int(np.count_nonzero(new.host_snapshot().protected))
            protected_old = int(np.count_nonzero(old.host_snapshot().protected))
        if protected_new == 0 and protected_old > 0:
            raise ConflictError(f"not applied: with the new parameters no point of the current frames is protected "
                                f"(now {protected_old}): the fixture would vanish; choose a selection that covers the "
                                "protected anatomy (nothing changed)")
        batch = new.proxies(hip, self.params)
        with gate.lock:
            batch.step(hip)           # compiles / warms the kernels now, not in a tick
        if not feeder.swap_pipeline(new):
            batch.close()
            raise ConflictError(f"not applied: the latest frames did not build a snapshot with the new parameters "
                                f"({feeder.last_error})")
        cfg = replace(self.cfg, pipeline=replace(self.cfg.pipeline, radius=pp.radius, selection=pp.selection,
                                                 cell_size=pp.cell_size))
        return Reconfiguration(self, cfg, new, gate, batch, old)

    def _new_params(self, radius, selection) -> PipelineParams:
        cur = self.pipeline.params
        pp = replace(cur, radius=radius if radius is not None else cur.radius,
                     selection=selection if selection is not None else cur.selection)
        if self.cfg.cell_size_given:
            reach = PipelineParams.reach(max(_DEFAULT_R3, self.params.r3), pp.radius)
            if reach > cur.cell_size + 1e-12:
                raise ConflictError(f"radius_max {pp.radius.r_max} m cannot be applied at runtime: the configuration "
                                    f"fixes [hash] cell_size = {cur.cell_size} m, below the reach it needs "
                                    f"({reach:.4f} m = R3 + radius_max); restart with a larger [hash] cell_size "
                                    "(or none: it then follows the radius)")
            return pp
        return haptic_pipeline_params(self.params, pp)

    def install(self, cfg, pipeline, gate, batch) -> tuple:
        """Swap in a prepared pipeline (between two ticks); returns the previous (pipeline, gate, batch)."""
        prev = (self.pipeline, self.gate, self.batch)
        batch.reset(self.batch.positions)     # the proxies carry on from where they are
        self.pipeline, self.gate, self.batch, self.cfg = pipeline, gate, batch, cfg
        return prev

    def close(self) -> None:
        if self.batch is not None:
            self.batch.close()   # (Warp: lets a resident proxy kernel go)
        if self.feeder is not None:
            stop = getattr(self.feeder, "stop", None)
            if stop is not None:
                stop()
            self.feeder.close()

    def status(self, now: Optional[float]) -> dict:
        st = {"frame_seq": self.frame_seq, "backend": self.backend.name, "device": self.backend.device_name,
              "proxy_device": getattr(self.batch, "device_kind", None) if self.batch is not None else None}
        if self.feeder is not None and now is not None:
            st["frames"] = self.feeder.status(now)
        st["self_filter"] = ({"on": False, "why": self.self_filter_off} if self.frame_filter is None
                             else {"on": True, **self.frame_filter.status()})
        if self.pipeline.params.motion.enabled:  # per-cell velocities of the last snapshot (kernels/motion.py)
            st["motion"] = self.pipeline.motion.summary()
        return st


@dataclass
class Reconfiguration:
    """A prepared change of the snapshots' parameters (``HapticScene.prepare_reconfiguration``):
    ``commit`` in the tick thread, between two ticks; ``abort`` if that fails (the feeder goes
    back to the pipeline the ticks still query); ``release`` after a commit, outside the tick
    (closes the old batch)."""

    scene: HapticScene
    cfg: object
    pipeline: object
    gate: PublishGate
    batch: object
    old_pipeline: object
    #: called with the new configuration after the swap (the service re-anchors every arm: S1)
    on_commit: Optional[Callable] = None
    _old: Optional[tuple] = None

    def commit(self) -> None:
        self._old = self.scene.install(self.cfg, self.pipeline, self.gate, self.batch)
        if self.on_commit is not None:
            self.on_commit(self.cfg)

    def abort(self) -> None:
        self.scene.feeder.swap_pipeline(self.old_pipeline)
        self.batch.close()

    def release(self) -> None:
        if self._old is not None and self._old[2] is not None:
            self._old[2].close()      # (Warp: the old batch's resident kernel goes)
        self._old = None


__all__ = ["HapticScene", "Reconfiguration"]
