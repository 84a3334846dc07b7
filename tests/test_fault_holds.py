"""Issue 18, failure 3 and the tick watchdog: a failing or dead frame ingest and a stalled tick
hold the arms (SAFETY.md S2, S9), and each hold names its cause and invariant.

Before the fix an exception other than PointfenceError ended the ingest thread silently, a build
that failed every time was only counted, and the frame age was counted from frame arrival, so
``max_age`` stayed fresh while no snapshot was published; nothing watched a tick that hung."""
import threading
import time

import numpy as np

from pointfence.service.clock import RealClock
from pointfence.service.frames import LiveFrames, SimFrames
from pointfence.service.holds import INGEST, WATCHDOG, describe
from pointfence.service.loop import HapticLoop
from pointfence.service.replay import simulate
from pointfence.service.watchdog import TickWatchdog

from service_cases import balloon_config, needs_opencl, push

pytestmark = needs_opencl


class Broken:
    """A frame filter that fails every build: an ordinary exception, or the thread's death."""

    class Death(BaseException):
        pass

    def __init__(self, die=False):
        self.die, self.calls = die, 0

    def __call__(self, frames):
        self.calls += 1
        if self.die:
            raise Broken.Death("injected")
        raise RuntimeError("injected build failure")


def test_failing_builds_age_the_snapshot_and_hold_the_arms(tmp_path):
    cfg = balloon_config(tmp_path, arch="III")          # max_frame_age_s 0.3 s in the test configuration
    seen = {}
    broken = Broken()

    def brk(svc):
        svc.feeder.frame_filter = broken

    events = {600: brk, 800: lambda s: seen.update(s800=s.status()), 1000: lambda s: seen.update(s1000=s.status())}
    svc, loop, sources = simulate(cfg, [push(0.10, t_end=0.5, hold=1.0)], 1.2, events=events)
    for s in sources:
        s.close()
    rec = svc.recorder
    age = rec.inputs[: rec.count, 3]
    assert broken.calls > 10 and svc.feeder.ingest_errors == broken.calls        # counted, never fatal
    assert "RuntimeError: injected" in svc.feeder.last_error
    # frames kept arriving, but the age is that of the last published snapshot: it grows from tick 600
    assert age[590] < 0.05 and age[1100] > 0.45
    assert seen["s800"]["hold"] == []                                            # the last snapshot is kept...
    assert seen["s1000"]["hold"] == ["snapshots not published"]                  # ... until max_frame_age_s
    assert seen["s1000"]["hold_causes"] == describe(INGEST)
    assert describe(INGEST)[0]["invariant"] == "S2"
    held = np.flatnonzero(rec.holds[: rec.count, 1].astype(np.int64) & INGEST)
    first = int(held[0])
    assert age[first] > cfg.service.max_frame_age_s >= age[first - 1]            # within the tick it passed
    f = np.linalg.norm(rec.rows[first:first + 200, 16:19], axis=1)
    assert f[0] > 0 and f[int(cfg.service.force_ramp_s * 1000) + 1:].max() == 0.0   # ramped out


def test_a_dead_ingest_thread_is_reported_and_restarted(tmp_path):
    cfg = balloon_config(tmp_path, arch="III")
    from pointfence.kernels import get_backend

    pipe = get_backend("opencl").pipeline([c.camera for c in cfg.cameras], cfg.pipeline)
    clock = RealClock()
    live = LiveFrames(pipe, cfg.open_sources(), clock, 0.1, 0.3)
    live.start()
    try:
        assert live.wait_first_snapshot(20.0)
        live.frame_filter = Broken(die=True)
        end = time.monotonic() + 10
        while live.status(clock.now())["ingest"] == "running" and time.monotonic() < end:
            time.sleep(0.01)
        st = live.status(clock.now())
        assert st["ingest"].startswith("dead: Death: injected"), st["ingest"]
        time.sleep(0.4)
        assert live.max_age(clock.now()) > 0.3 and not live.frames_too_old(clock.now())   # an ingest problem
        live.frame_filter = None
        assert live.restart_ingest()
        n = live.snapshots
        end = time.monotonic() + 10
        while live.snapshots == n and time.monotonic() < end:
            time.sleep(0.01)
        assert live.snapshots > n and live.max_age(clock.now()) < 0.3
        assert live.status(clock.now())["ingest"] == "running"
    finally:
        live.stop()
        live.close()


def test_sim_frames_count_age_from_the_published_snapshot(tmp_path):
    cfg = balloon_config(tmp_path, arch="III")
    from pointfence.kernels import get_backend

    pipe = get_backend("numpy").pipeline([c.camera for c in cfg.cameras], cfg.pipeline)
    fe = SimFrames(pipe, cfg.open_sources(), 0.1, 0.3)
    assert fe.max_age(0.0) == np.inf
    fe.poll(0.0)
    assert fe.max_age(0.01) == 0.01 and fe.snapshots == 1
    fe.frame_filter = Broken()
    fe.poll(0.2)                                  # new frames arrived: the build fails
    assert fe.snapshots == 1 and fe.ingest_errors >= 1
    assert fe.max_age(0.2) == 0.2                 # still the age of the snapshot from t = 0
    fe.close()


class FakeLoop:
    def __init__(self):
        self.tick_started = None
        self.t = 0.0
        self.clock = self

    def now(self):
        return self.t


def test_watchdog_sees_a_stall_once_per_tick():
    loop, calls = FakeLoop(), []
    target = type("T", (), {"on_stall": lambda self, s, n: calls.append((s, n))})()
    wd = TickWatchdog(loop, target, limit_s=0.003)
    assert not wd.check()                        # between ticks
    loop.tick_started, loop.t = 1.0, 1.002
    assert not wd.check()                        # running, within the limit
    loop.t = 1.0035
    assert wd.check() and calls == [(1.0, 1.0035)] and abs(wd.last_stall_s - 0.0035) < 1e-12
    loop.t = 1.05
    assert not wd.check() and len(calls) == 1    # the same stalled tick: once
    loop.tick_started, loop.t = 2.0, 2.01
    assert wd.check() and len(calls) == 2


def test_a_hung_tick_is_seen_while_it_hangs():
    """A threaded loop whose tick 300 (or the first after it) blocks for 60 ms: the watchdog calls on_stall during the
    hang (not after it), within a few milliseconds."""
    state = {"stall_at": None, "hang_end": None}

    class Target:
        def tick(self, k, t, dt, overrun, now):
            if k >= 300 and state["hang_end"] is None:    # (k == 300 itself may be a skipped period)
                time.sleep(0.06)
                state["hang_end"] = time.perf_counter()

        def safe_tick(self, *a):
            pass

        def on_stall(self, started, now):
            state["stall_at"] = time.perf_counter()
            state["after"] = now - started

    loop = HapticLoop(Target(), RealClock(), 1000.0, max_lateness_s=0.003, switch_interval_s=None)
    loop.start()
    try:
        end = time.monotonic() + 10
        while state["hang_end"] is None and time.monotonic() < end:
            time.sleep(0.01)
    finally:
        loop.stop()
    assert state["stall_at"] is not None and state["stall_at"] < state["hang_end"]
    assert 0.003 < state["after"] < 0.05


def test_a_stalled_tick_zeroes_the_force_at_once_and_holds(tmp_path):
    cfg = balloon_config(tmp_path, arch="III")
    seen = {}

    def stall(svc):              # as the watchdog's thread calls it while tick 900 hangs
        seen["before"] = svc.f_master.copy()
        svc.on_stall(0.9, 0.904)

    svc, loop, sources = simulate(cfg, [push(0.10, t_end=0.8, hold=0.6)], 1.2, events={900: stall})
    for s in sources:
        s.close()
    rows = svc.recorder.ticks()
    hold = svc.recorder.holds[: svc.recorder.count, 1].astype(np.int64)
    assert np.linalg.norm(seen["before"]) > 1.0 and np.linalg.norm(rows[899, 16:19]) > 1.0
    assert hold[900] & WATCHDOG and np.linalg.norm(rows[900, 16:19]) == 0.0     # zero in the same tick
    assert svc.watchdog_trips == 1 and "tick watchdog" in svc.last_error
    recover = int(cfg.service.recover_s * 1000)
    assert not hold[900 + recover + 5:].any()                                     # a condition: it clears
    assert svc.status()["hold"] == []


def test_threads_reach_on_stall_without_the_tick(tmp_path):
    """on_stall is called from another thread while the tick thread is stuck: it must not wait
    for the tick (a tick stuck inside a send keeps the send lock; the watchdog skips the send)."""
    cfg = balloon_config(tmp_path, arch="III")
    svc, loop, sources = simulate(cfg, [push(0.10, t_end=0.2, hold=0.1)], 0.3)
    for s in sources:
        s.close()
    with svc.devices.tx_lock:             # the tick stuck inside its send
        th = threading.Thread(target=svc.on_stall, args=(0.0, 0.01))
        th.start()
        th.join(timeout=2.0)
        assert not th.is_alive()
    assert svc.watchdog_trips == 1
