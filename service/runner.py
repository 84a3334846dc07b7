"""Running the service live: the haptic loop in its own thread on the real clock, frames from
camera reader threads, for a fixed time with timed control events (the demo and the loop
benchmark use it; ``pointfence serve`` will wrap the same pieces)."""
from __future__ import annotations

import gc
import time
from typing import Optional

import numpy as np

from .app import Service, reason_names
from .clock import RealClock
from .frames import LiveFrames
from .loop import HapticLoop
from .memory import small_pages


class LiveRun:
    """Service + live frames + loop thread. ``start()``, then ``wait(seconds)`` or control the
    service from this thread, then ``stop()``. The loop's timing excludes the start-up ticks
    before ``mark()``."""

    def __init__(self, cfg, masters, *, architecture: Optional[str] = None, backend: Optional[str] = None,
                 device: Optional[str] = None, record_s: float = 0.0, robots=None, sources=None,
                 rt_priority: Optional[int] = None, record_path=None, ros2_telemetry: Optional[bool] = None,
                 robot_rt_priority: int = 0):
        """``ros2_telemetry``: publish ROS 2 telemetry (``ros2/telemetry.py``, the ``[ros2]``
        table's rates and names; None: ``[ros2] telemetry``). ``robot_rt_priority``: SCHED_FIFO
        priority of the hosted robot process (``robot.hosted.RobotHost``; 0, the default: normal)."""
        self.cfg = cfg
        self.clock = RealClock()
        sc = cfg.service
        # before the robot process starts (it inherits the switch): see service/memory.py
        self.memory = small_pages()
        self.robot_host = None
        if robots is None and sc.robot_process and cfg.robot.model != "none":
            from .robot.hosted import RobotHost

            # normal priority by default: a SCHED_FIFO child would preempt the service's threads
            # that run at normal priority (a simulated arm stands for hardware with its own
            # controller; a bench that shares the cores with it may raise it, robot_rt_priority)
            # its watchdog: [service] robot_watchdog_s (checked against its hard limit by config)
            self.robot_host = RobotHost([cfg.robot.table()] * len(masters), timeout_s=sc.robot_watchdog_s,
                                        rt_priority=robot_rt_priority)
            robots = self.robot_host.robots
        try:
            self.service = Service(cfg, masters, robots=robots, backend=backend, device=device,
                                   record=int(record_s * sc.rate_hz), architecture=architecture,
                                   record_path=record_path)
        except BaseException:
            self.close_robots()
            raise
        self.sources = sources if sources is not None else cfg.open_sources(realtime=True)
        self.frames = LiveFrames(self.service.pipeline, self.sources, self.clock, cfg.service.stale_s,
                                 cfg.service.max_frame_age_s)
        self.service.attach_frames(self.frames)
        rec = self.service.recorder
        if rec is not None and rec.streaming:
            from .holds import REASONS

            rec.describe({"architecture": self.service.architecture, "backend": self.service.backend.name,
                          "device_spec": cfg.device, "rate_hz": self.service.rate_hz, "cameras": self.frames.names,
                          "hold_reasons": {str(int(b)): {"name": r.name, "invariant": r.invariant, "latched": r.latched}
                                           for b, r in REASONS.items()}},  # (int: str(IntFlag) differs across Pythons)
                         self.frames.snapshot_frames)
            if hasattr(rec, "attach"):   # MCAP: the frames themselves, the cameras, the clock (mcap_record.py)
                from .mcap_record import config_text

                rec.attach(self.frames, cfg, self.clock.now, config_text(cfg))
        self.telemetry = None
        if cfg.ros2.telemetry if ros2_telemetry is None else ros2_telemetry:
            from .ros2.telemetry import start_telemetry

            try:   # (after the recorder: its frames callback stays first; the same stamps as its)
                self.telemetry = start_telemetry(cfg, self.service.n)
                self.telemetry.attach(self.frames, cfg, self.clock.now, getattr(rec, "epoch_ns", None))
            except BaseException:
                self._close_telemetry()
                self.close_robots()
                raise
            self.service.telemetry = self.telemetry
        self.loop = HapticLoop(self.service, self.clock, cfg.service.rate_hz, cfg.service.max_lateness_s,
                               rt_priority=cfg.service.rt_priority if rt_priority is None else rt_priority)
        self._mark = (0, 0, 0, 0)

    def _receivers(self) -> list:
        """The masters' receiver objects with a thread of their own (``udp_server.UdpHub``,
        ``itp.ItpReceiver``: a master's ``hub`` or ``receiver``), each once."""
        out = []
        for m in self.service.masters:
            rx = getattr(m, "hub", None) or getattr(m, "receiver", None)
            if callable(getattr(rx, "set_rt_priority", None)) and all(rx is not r for r in out):
                out.append(rx)
        return out

    def start(self, first_frame_timeout: float = 20.0) -> None:
        sc = self.cfg.service
        if self.service.backend.name == "opencl" and (sc.build_idle or sc.build_nice):
            from pointfence.kernels.opencl.context import lower_pool_priority

            lower_pool_priority(sc.build_nice, idle=sc.build_idle)
        self.frames.start()
        self.frames.set_rt_priority(sc.frames_rt_priority if sc.rt_priority else 0)
        for rx in self._receivers():     # the masters' receiver threads feed every tick: as the frames'
            rx.set_rt_priority(sc.frames_rt_priority if sc.rt_priority else 0)
        if not self.frames.wait_first_snapshot(first_frame_timeout):
            self.stop()
            raise RuntimeError(f"no snapshot within {first_frame_timeout} s: {self.frames.status(self.clock.now())}")
        if self.service.backend.name == "opencl" and sc.build_idle:
            # ... but never starved by a busy machine (build_watch.py); watched from the first
            # snapshot on: the first builds compile the kernels, slow by nature, and raising the
            # pool for them only takes the cores from the rest of the start-up
            from pointfence.kernels.opencl.context import lower_pool_priority, restore_pool_priority

            from .build_watch import BuildWatch

            # a build longer than a frame period loses frames (the next two arrive while it runs):
            # it starves, as one past a quarter of max_frame_age_s does
            period = 1.0 / max(s.rate_hz for s in self.sources)
            self.frames.build_watch = BuildWatch(
                self.frames, raise_pool=lambda: bool(restore_pool_priority(0)),
                idle_pool=lambda: bool(lower_pool_priority(sc.build_nice, idle=True)),
                starve_s=min(sc.max_frame_age_s / 4, period)).start()
        self.service.start()
        if hasattr(self.service.recorder, "note_start"):
            self.service.recorder.note_start(self.service)
        self.service.warm_up()
        # Everything made so far (modules, kernels, buffers) lives as long as the run: frozen, a
        # full collection no longer scans it. Unfrozen, one took 12-17 ms in whichever thread
        # triggered it (the loop, or the ingest thread holding the interpreter lock), about once
        # in 25 s (2-core VM, 4 Raven II); frozen, none over 0.3 ms in 25 s.
        gc.collect()
        gc.freeze()
        self.loop.start()
        while self.loop.t0 is None and self.loop.running:
            time.sleep(0.001)
        # scene time of loop time 0 (for ground-truth measures on moving synthetic scenes)
        self.service.scene_time_offset = self.loop.t0 - (self.frames.clock_minus_stamp if self.frames.clock_minus_stamp is not None
                                                       else self.loop.t0)

    def wait_ticks(self, n: int, timeout: float = 30.0) -> None:
        """Wait until the loop has run ``n`` ticks in all (or ``timeout`` s)."""
        end = time.monotonic() + timeout
        while self.loop.ticks < n and time.monotonic() < end:
            if not self.loop.running:
                raise RuntimeError(f"haptic loop thread ended: {self.loop.error}")
            time.sleep(0.005)

    def mark(self) -> None:
        self._mark = self.loop.mark()

    def wait(self, seconds: float) -> None:
        """Let the loop run ``seconds`` (s); RuntimeError as soon as its thread ends. The calling
        thread sleeps the whole time: a thread of normal priority that woke to poll would take
        the interpreter lock, and the loop's thread, waking for a tick while such a thread holds
        it (or was preempted holding it), starts the tick late."""
        loop = self.loop
        if not loop.running or loop.finished.wait(max(0.0, float(seconds))) or not loop.running:
            raise RuntimeError(f"haptic loop thread ended: {loop.error}")

    def wait_clear(self, clear_s: float, timeout: float = 10.0) -> None:
        """Wait until no arm has held for ``clear_s`` seconds on end (start-up holds such as an
        old first snapshot have cleared); RuntimeError after ``timeout`` s, naming what still
        holds. Reads the last tick's hold masks (``Service.hold_mask``, ``arm_hold``), not
        ``status()``, which would take the interpreter lock from the loop every poll."""
        svc = self.service
        end = time.monotonic() + timeout
        since = None
        while True:
            now = time.monotonic()
            if svc.hold_mask or svc.arm_hold.any():
                since = None
            elif since is None:
                since = now
            elif now - since >= clear_s:
                return
            if now > end:
                raise RuntimeError(f"the service still holds after {timeout:g} s: "
                                   f"{reason_names(int(svc.hold_mask) | int(np.bitwise_or.reduce(svc.arm_hold)))}")
            self.wait(0.005)

    def timing(self):
        return self.loop.timing(self._mark)

    def status(self) -> dict:
        st = self.service.status(self.clock.now())
        st["loop"] = self.loop.timing(self._mark).as_dict()
        st["loop_error"] = self.loop.error
        st["memory"] = self.memory
        return st

    def _close_telemetry(self) -> None:
        if self.telemetry is not None:
            self.telemetry.close()

    def close_robots(self) -> None:
        """End the robot process of a live run with hosted robots (idempotent)."""
        if self.robot_host is not None:
            self.robot_host.close()

    def stop(self, before_close=None) -> None:
        """End the run; ``before_close(recorder)`` runs after the loop, the frames and the robots
        stopped, before the recording is closed (the run's measures go into it)."""
        self.loop.stop()
        self._close_telemetry()
        if self.frames.build_watch is not None:
            self.frames.build_watch.stop()
        self.frames.stop()
        for s in self.sources:
            s.close()
        self.close_robots()
        if self.service.recorder is not None:
            if before_close is not None:
                before_close(self.service.recorder)
            self.service.recorder.close()   # (streamed: the last rows reach the file)
        gc.unfreeze()   # what this run kept alive may be collected again
