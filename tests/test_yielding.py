"""Frame threads step aside for the haptic loop (kernels/yielding.py, service/loop.py)."""
import threading
import time

import numpy as np

from pointfence.kernels import yielding
from pointfence.kernels.camera import Camera
from pointfence.kernels.frame import DepthFrame
from pointfence.service.clock import FakeClock
from pointfence.service.loop import HapticLoop
from pointfence.service.sources.base import DepthSource
from pointfence.service.sources.threaded import CameraReader


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def _in_thread(fn):
    out = {}

    def run():
        t0 = time.perf_counter()
        fn()
        out["s"] = time.perf_counter() - t0

    th = threading.Thread(target=run)
    th.start()
    return th, out


def test_checkpoint_without_a_gate_returns_at_once():
    yielding.install(None)
    t0 = time.perf_counter()
    for _ in range(1000):
        yielding.checkpoint()
    assert time.perf_counter() - t0 < 0.05


def test_a_checkpoint_waits_while_a_tick_runs_and_until_it_ends():
    now = Clock()
    g = yielding.Gate(now=now, guard_s=150e-6, max_wait_s=5.0)
    g.next_due = 1.0
    now.t = 0.5
    assert not g.blocked()                      # the loop sleeps, next tick far away
    g.busy = True                               # a tick starts
    th, out = _in_thread(g.wait)
    time.sleep(0.05)
    assert th.is_alive()                        # the background thread sleeps through the tick
    g.busy = False
    g.next_due = 1.001
    th.join(1.0)
    assert not th.is_alive() and out["s"] >= 0.05 and g.waits == 1 and g.waited_s >= 0.05


def test_a_checkpoint_just_before_the_next_tick_waits_for_it():
    now = Clock()
    g = yielding.Gate(now=now, guard_s=150e-6, max_wait_s=5.0)
    g.next_due = 1.0
    now.t = 1.0 - 100e-6                        # within the guard
    th, _ = _in_thread(g.wait)
    time.sleep(0.03)
    assert th.is_alive()
    now.t = 1.0005                              # the tick ran and the next is 0.5 ms away
    g.next_due = 1.001
    th.join(1.0)
    assert not th.is_alive()


def test_a_stalled_loop_delays_background_work_by_at_most_max_wait():
    g = yielding.Gate(now=Clock(), max_wait_s=0.02)
    g.busy = True                               # never ends
    th, out = _in_thread(g.wait)
    th.join(2.0)
    assert not th.is_alive() and 0.02 <= out["s"] < 1.0


def test_the_loop_thread_itself_never_waits():
    g = yielding.Gate(now=Clock(), max_wait_s=5.0)
    g.busy = True
    g.owner = threading.get_ident()
    t0 = time.perf_counter()
    g.wait()
    assert time.perf_counter() - t0 < 0.01 and g.waits == 0


class _Target:
    def __init__(self):
        self.seen = []

    def tick(self, k, t, dt, overrun, now):
        g = yielding.installed()
        self.seen.append((g is not None and g.busy, g is not None and g.owner == threading.get_ident()))
        yielding.checkpoint()                   # in the loop's own thread: returns at once

    def safe_tick(self, k, t, dt, now):
        pass


def test_the_threaded_loop_installs_its_gate_and_removes_it():
    tgt = _Target()
    loop = HapticLoop(tgt, rate_hz=1000.0)
    loop.start()
    time.sleep(0.2)
    g = loop.gate
    assert yielding.installed() is g and g is not None
    loop.stop()
    assert yielding.installed() is None and loop.gate is None
    assert len(tgt.seen) > 50 and all(busy and own for busy, own in tgt.seen)
    assert not g.busy and g.next_due > 0 and g.waits == 0


def test_offline_loops_install_no_gate():
    loop = HapticLoop(_Target(), FakeClock(), rate_hz=1000.0, switch_interval_s=None)
    loop.run_ticks(10)
    assert loop.gate is None and yielding.installed() is None


class _Frames(DepthSource):
    """Frames on demand: a 4x4 image stamped seq / 30 s."""

    def _frame(self, seq):
        return DepthFrame(self.camera.name, np.full((4, 4), 800, np.uint16), seq / 30.0, seq)


def test_a_camera_readers_python_steps_aside_for_a_running_tick():
    """A camera reader's Python each frame (the source's ``_frame``, then the reader's bookkeeping
    and ``on_frame``, where the live feed fits the camera's clock) passes two checkpoints: with a
    tick running, each waits for it (here a tick that never ends, so each waits max_wait_s)."""
    g = yielding.Gate(now=Clock(), max_wait_s=0.001)
    g.busy = True
    seen = []
    src = _Frames(Camera("c", 4, 4, 4.0, 4.0, 1.5, 1.5), rate_hz=200.0)
    reader = CameraReader(src, on_frame=lambda f: seen.append(g.waits))
    yielding.install(g)
    try:
        reader.start()
        end = time.monotonic() + 5.0
        while len(seen) < 5 and time.monotonic() < end:
            time.sleep(0.01)
    finally:
        reader.stop()
        yielding.install(None)
    assert seen[:5] == [2, 4, 6, 8, 10]


def test_a_camera_reader_without_a_gate_never_waits():
    seen = []
    src = _Frames(Camera("c", 4, 4, 4.0, 4.0, 1.5, 1.5), rate_hz=500.0)
    reader = CameraReader(src, on_frame=lambda f: seen.append(f.seq))
    yielding.install(None)
    reader.start()
    try:
        end = time.monotonic() + 5.0
        while len(seen) < 5 and time.monotonic() < end:
            time.sleep(0.01)
    finally:
        reader.stop()
    assert seen[:5] == [0, 1, 2, 3, 4]


def test_a_snapshots_consumers_run_after_a_checkpoint(monkeypatch):
    """What the feed hands a built snapshot to (``on_snapshot``: the recorder's frame copy, the
    telemetry's cloud) is Python of the frame thread: a checkpoint comes right before it."""
    from pointfence.kernels import PipelineParams, Workspace, get_backend
    from pointfence.service import frames as frames_mod

    from pointfence.kernels import backend as backend_mod

    events = []
    monkeypatch.setattr(frames_mod, "checkpoint", lambda: events.append("checkpoint"))
    monkeypatch.setattr(backend_mod, "checkpoint", lambda: events.append("build's checkpoint"))
    cam = Camera("c", 4, 4, 4.0, 4.0, 1.5, 1.5)
    params = PipelineParams(workspace=Workspace((-1, -1, 0.1), (1, 1, 2.0)), cell_size=0.05)
    feed = frames_mod.SimFrames(get_backend("numpy").pipeline([cam], params), [_Frames(cam, rate_hz=30.0)])
    feed.on_snapshot = lambda seq, built: events.append("on_snapshot")
    assert feed.poll(0.0)
    assert events == ["checkpoint", "build's checkpoint", "checkpoint", "on_snapshot"] and feed.snapshots == 1
