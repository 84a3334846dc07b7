"""The haptic loop's deadline accounting on a fake clock (deterministic, no wall-clock timing)."""
import numpy as np
import pytest

from pointfence.service.clock import FakeClock
from pointfence.service.loop import HapticLoop


class ScriptedWork:
    """A tick target that 'computes' for scripted durations by advancing the fake clock."""

    def __init__(self, clock, durations, fail_at=()):
        self.clock = clock
        self.durations = list(durations)
        self.calls = []
        self.safe = []
        self.fail_at = set(fail_at)

    def tick(self, k, t, dt, overrun, now):
        self.calls.append((k, t, dt, overrun, now))
        if k in self.fail_at:
            raise RuntimeError("boom")
        self.clock.advance(self.durations[len(self.calls) - 1] if len(self.calls) <= len(self.durations) else 1e-4)

    def safe_tick(self, k, t, dt, now):
        self.safe.append(k)


def test_deadlines_misses_skips_and_lateness():
    clock = FakeClock()
    ms = 1e-3
    work = ScriptedWork(clock, [0.2 * ms, 1.5 * ms, 0.2 * ms, 3.5 * ms, 0.2 * ms, 0.2 * ms])
    loop = HapticLoop(work, clock, rate_hz=1000.0, max_lateness_s=3e-3)
    loop.run_ticks(6)
    ks = [c[0] for c in work.calls]
    assert ks == [0, 1, 2, 3, 6, 7]                      # periods 4 and 5 were skipped, not burst
    np.testing.assert_allclose([c[2] for c in work.calls], [ms, ms, ms, ms, 3 * ms, ms])
    np.testing.assert_allclose([c[1] for c in work.calls], [k * ms for k in ks])   # loop time is k * period
    tm = loop.timing()
    assert tm.ticks == 6 and tm.periods == 8
    assert tm.misses == 4                                # tick 1 and 3 ended late, periods 4 and 5 lost
    assert tm.missed_ticks == 3                          # ticks 1 and 3 ran long, tick 4 started 2.5 ms late
    np.testing.assert_allclose(loop.late[:6] * 1e3, [0, 0, 0.5, 0, 2.5, 0], atol=1e-9)
    np.testing.assert_allclose(loop.compute[:6] * 1e3, [0.2, 1.5, 0.2, 3.5, 0.2, 0.2], atol=1e-9)
    assert tm.overruns == 0 and not any(c[3] for c in work.calls)
    assert tm.compute_us_max == pytest.approx(3500, abs=1e-3)


def test_overrun_flag_beyond_max_lateness():
    clock = FakeClock()
    work = ScriptedWork(clock, [0.1e-3, 4.2e-3, 0.1e-3])
    loop = HapticLoop(work, clock, 1000.0, max_lateness_s=3e-3)
    loop.run_ticks(3)
    assert [c[3] for c in work.calls] == [False, False, True]
    assert loop.timing().overruns == 1


def test_no_drift_with_long_ticks():
    clock = FakeClock(t0=5.0)
    work = ScriptedWork(clock, [0.95e-3] * 2000)
    loop = HapticLoop(work, clock, 1000.0)
    loop.run_ticks(2000)
    starts = np.array([c[4] for c in work.calls]) - 5.0
    np.testing.assert_allclose(starts, np.arange(2000) * 1e-3, atol=1e-9)
    assert loop.timing().misses == 0 and loop.timing().late_us_max < 1e-3


def test_exception_is_surfaced_and_safe_ticks_follow():
    clock = FakeClock()
    work = ScriptedWork(clock, [1e-4] * 10, fail_at={3})
    loop = HapticLoop(work, clock, 1000.0)
    loop.run_ticks(6)
    assert loop.error is not None and "boom" in loop.error and loop.errors == 1
    assert work.safe == [3, 4, 5]        # the loop kept running, in its safe mode
    loop.clear_error()
    loop.run_ticks(1)
    assert work.calls[-1][0] == 6


def test_timing_since_mark():
    clock = FakeClock()
    work = ScriptedWork(clock, [2.5e-3] + [1e-4] * 20)
    loop = HapticLoop(work, clock, 1000.0)
    loop.run_ticks(1)
    m = loop.mark()
    loop.run_ticks(10)
    tm = loop.timing(m)
    assert tm.ticks == 10 and tm.compute_us_p99 == pytest.approx(100, abs=1e-6)


def test_thread_keeps_the_interpreter_lock_for_a_whole_tick():
    """In its own thread the loop runs each tick with a 5 ms switch interval (no other Python
    thread can force it out mid-tick) and sleeps with 0.1 ms (the lock comes back fast at the
    deadline); stop() restores the process's interval."""
    import sys
    import time

    from pointfence.service.clock import RealClock

    seen = []

    class Probe:
        def tick(self, k, t, dt, overrun, now):
            seen.append(sys.getswitchinterval())

        def safe_tick(self, k, t, dt, now):
            pass

    before = sys.getswitchinterval()
    loop = HapticLoop(Probe(), RealClock(), rate_hz=1000.0)
    loop.start()
    try:
        end = time.monotonic() + 10.0
        while len(seen) < 20 and time.monotonic() < end:
            time.sleep(0.01)
        between = sys.getswitchinterval()   # read while the loop thread mostly sleeps
    finally:
        loop.stop()
    assert len(seen) >= 20 and all(s == pytest.approx(0.005) for s in seen)
    assert between in (pytest.approx(0.0001), pytest.approx(0.005))
    assert sys.getswitchinterval() == pytest.approx(before)


def test_bench_loop_machine_floor_runs_the_same_loop_on_a_spinning_tick():
    """`bench loop --floor`: the HapticLoop with a tick that only spins busy_s; its figures
    are the loop's own accounting (every tick spun at least busy_s; periods = ticks + skipped)."""
    from pointfence.bench.loop import machine_floor
    from pointfence.service import config as config_mod

    f = machine_floor(config_mod.load(None), 0.5, 200e-6, load=1)
    assert f["busy_us"] == 200.0 and f["ticks"] > 50 and f["load_processes"] == 1
    assert f["tick_us_max"] >= 200.0
    assert f["periods"] >= f["ticks"] and 0 <= f["loop_misses"] <= f["periods"]
    assert f["loop_miss_ratio"] == round(f["loop_misses"] / f["periods"], 5)
    assert 0 <= f["loop_missed_ticks"] <= min(f["loop_misses"], f["ticks"])
    if f.get("busy_pct") is not None:   # Linux: the cores were busy (the spinning tick, the busy process)
        assert 0 < f["busy_pct"] <= 100 and f["steal_ms"] >= 0


class _DiesAfterTicks:
    """A target whose per-tick note raises after a few ticks: the loop's thread ends."""

    def __init__(self, n):
        self.n = n

    def tick(self, k, t, dt, overrun, now):
        pass

    def safe_tick(self, k, t, dt, now):
        pass

    def note_tick_us(self, us):
        self.n -= 1
        if self.n == 0:
            raise RuntimeError("note failed")


def test_a_run_wait_sleeps_through_and_ends_as_soon_as_the_loops_thread_does():
    """``LiveRun.wait`` blocks on the loop's ``finished`` event (no polling that would take the
    interpreter lock from the ticks): it returns after its time while the loop runs, and raises
    as soon as the loop's thread ends, not at the end of its time."""
    import threading
    import time
    from types import SimpleNamespace

    from pointfence.service.runner import LiveRun

    loop = HapticLoop(_DiesAfterTicks(10 ** 9), rate_hz=1000.0)
    loop.start()
    try:
        LiveRun.wait(SimpleNamespace(loop=loop), 0.05)      # the loop runs on: returns
        assert loop.running and not loop.finished.is_set()
    finally:
        loop.stop()
    assert loop.finished.is_set()
    with pytest.raises(RuntimeError, match="haptic loop thread ended"):
        LiveRun.wait(SimpleNamespace(loop=loop), 30.0)      # stopped: at once

    old = threading.excepthook
    threading.excepthook = lambda args: None                # (the dying thread's traceback)
    try:
        loop = HapticLoop(_DiesAfterTicks(50), rate_hz=1000.0)
        loop.start()
        t0 = time.monotonic()
        with pytest.raises(RuntimeError, match="haptic loop thread ended"):
            LiveRun.wait(SimpleNamespace(loop=loop), 30.0)
        assert time.monotonic() - t0 < 10.0 and loop.finished.is_set() and not loop.running
        loop.stop()
    finally:
        threading.excepthook = old
