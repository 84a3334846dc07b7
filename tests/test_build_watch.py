"""Snapshot builds yield to the loop but never starve (service/build_watch.py): a build running
past its bound puts PoCL's pool back under the normal scheduler, calm builds put it back under
SCHED_IDLE; the OpenCL context's functions move the pool's threads."""
from __future__ import annotations

import os

import pytest

from pointfence.service.build_watch import BuildWatch

from service_cases import needs_opencl


class _Frames:
    def __init__(self):
        self.build_started = None
        self.ingest_ms = []


class _Pool:
    def __init__(self, ok=True):
        self.moves, self.ok = [], ok

    def up(self):
        self.moves.append("normal")
        return self.ok

    def down(self):
        self.moves.append("idle")
        return self.ok


def _watch(frames, pool):
    return BuildWatch(frames, pool.up, pool.down, starve_s=0.12, calm_builds=3, hold_s=0.5)


def test_a_starving_build_raises_the_pool_and_calm_builds_lower_it_again():
    f, pool = _Frames(), _Pool()
    w = _watch(f, pool)
    f.build_started = 100.0
    w.check(100.05)                         # a build of 50 ms: nothing to do
    assert pool.moves == [] and w.idle
    w.check(100.13)                         # past 120 ms: the pool gets the normal scheduler
    assert pool.moves == ["normal"] and not w.idle and w.raised == 1
    w.check(100.5)                          # still running: stays raised, no second move
    assert pool.moves == ["normal"]
    f.build_started = None
    f.ingest_ms += [600.0, 12.0, 11.0]      # the slow build ended; two calm ones are not three
    w.check(101.0)
    assert pool.moves == ["normal"] and not w.idle
    f.ingest_ms += [13.0]                   # three calm builds (each < 40 ms) since the raise
    w.check(101.1)                          # (and its 0.5 s hold is over)
    assert pool.moves == ["normal", "idle"] and w.idle
    assert w.status()["pool"] == "SCHED_IDLE" and w.status()["raised"] == 1


def test_the_pool_stays_raised_for_its_hold_and_longer_when_it_starves_again_soon():
    f, pool = _Frames(), _Pool()
    w = _watch(f, pool)
    f.build_started = 0.0
    w.check(0.2)                                            # raised at 0.2 s for 0.5 s at least
    f.build_started = None
    f.ingest_ms += [150.0, 10.0, 10.0, 10.0]
    w.check(0.5)
    assert not w.idle                                       # calm, but its hold is not over
    w.check(0.71)
    assert w.idle and pool.moves == ["normal", "idle"]
    f.build_started = 1.0                                   # starving again 0.3 s later: hold doubles
    w.check(1.2)
    assert not w.idle and w.hold_s == 1.0
    f.build_started = None
    f.ingest_ms += [10.0] * 3
    w.check(2.1)
    assert not w.idle                                       # 0.9 s < 1.0 s
    w.check(2.21)
    assert w.idle
    f.build_started = 10.0                                  # starving long after: the base hold again
    w.check(10.2)
    assert w.hold_s == 0.5


def test_a_slow_build_among_the_last_keeps_the_pool_raised():
    f, pool = _Frames(), _Pool()
    w = _watch(f, pool)
    f.build_started = 0.0
    w.check(0.2)
    f.build_started = None
    f.ingest_ms += [200.0, 10.0, 90.0, 10.0]     # 90 ms is not calm (> 40 ms)
    w.check(5.0)
    assert not w.idle and pool.moves == ["normal"]


def test_a_refused_move_is_counted_and_tried_again():
    f, pool = _Frames(), _Pool(ok=False)
    w = _watch(f, pool)
    f.build_started = 0.0
    w.check(0.2)
    w.check(0.3)
    assert w.idle and w.refused == 2 and pool.moves == ["normal", "normal"]


def test_the_thread_watches_until_stopped():
    f, pool = _Frames(), _Pool()
    w = BuildWatch(f, pool.up, pool.down, starve_s=0.01, poll_s=0.005).start()
    try:
        import time

        f.build_started = time.monotonic()
        end = time.monotonic() + 5.0
        while w.idle and time.monotonic() < end:
            time.sleep(0.005)
    finally:
        w.stop()
    assert not w.idle and pool.moves[:1] == ["normal"]


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="SCHED_IDLE is a Linux feature")
def test_the_pool_moves_between_sched_idle_and_normal():
    from pointfence.kernels.opencl.context import lower_pool_priority, pool_threads, restore_pool_priority

    tids = set(pool_threads())
    if not tids:
        pytest.skip("no OpenCL worker pool in this process")
    changed = set(lower_pool_priority(10, idle=True))
    try:
        assert changed and all(os.sched_getscheduler(t) == os.SCHED_IDLE for t in changed)
        back = set(restore_pool_priority(0))
        if back:   # (leaving SCHED_IDLE needs privilege or RLIMIT_NICE)
            assert all(os.sched_getscheduler(t) == os.SCHED_OTHER and os.getpriority(os.PRIO_PROCESS, t) == 0
                       for t in back)
    finally:
        restore_pool_priority(0)


@needs_opencl
@pytest.mark.parametrize("max_age_s, want_s", [(0.5, 1 / 30), (0.1, 0.025)], ids=["frame-period", "quarter-max-age"])
def test_a_live_run_starves_a_build_past_a_frame_period_or_a_quarter_of_the_max_age(max_age_s, want_s):
    """A build longer than the cameras' frame period loses frames (two arrive while it runs): the
    live run's watch raises the pool then, or at a quarter of ``max_frame_age_s`` if that is
    sooner (with 125 ms, the default's quarter, a ROS 2 rig lost up to 82 of 300 frames)."""
    from pointfence.bench.loop import circling_master
    from pointfence.service import config as config_mod
    from pointfence.service.canned import canned_sources
    from pointfence.service.runner import LiveRun

    cfg = config_mod.load(None)
    cfg.service.max_frame_age_s = max_age_s
    sources = canned_sources(cfg, 5, {})
    assert max(s.rate_hz for s in sources) == 30.0
    run = LiveRun(cfg, [circling_master(0, 1, 10.0)], sources=sources, backend="opencl")
    try:
        run.start()
        assert run.frames.build_watch is not None
        assert run.frames.build_watch.starve_s == pytest.approx(want_s)
    finally:
        run.stop()
