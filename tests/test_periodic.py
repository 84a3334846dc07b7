"""The one periodic loop (service/periodic.py) on a simulated clock: absolute deadlines, skipped
periods counted as misses, dt after a skip, lateness, overruns, stop; and its three users."""
import threading
import time

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service.clock import FakeClock
from pointfence.service.periodic import PeriodicLoop

MS = 1e-3


def run(loop, clock, work_s):
    """One tick per entry of ``work_s``: the tick 'computes' that long. Returns (k, dt, elapsed,
    late, overrun) of each tick."""
    out = []
    for w in work_s:
        k = loop.begin()
        out.append((k, loop.dt, loop.elapsed, loop.late_s, loop.overrun))
        clock.advance(w)
        loop.end()
    return out


def test_deadlines_are_absolute_and_never_drift():
    clock = FakeClock(t0=2.0)
    loop = PeriodicLoop(MS, clock)
    starts = []
    for _ in range(1000):
        loop.begin()
        starts.append(loop.started)
        clock.advance(0.9 * MS)
        loop.end()
    np.testing.assert_allclose(np.array(starts) - 2.0, np.arange(1000) * MS, atol=1e-9)
    assert loop.misses == 0 and loop.periods == 1000 and loop.ticks == 1000


def test_lost_periods_are_skipped_counted_as_misses_and_dt_spans_them():
    clock = FakeClock()
    loop = PeriodicLoop(MS, clock)
    got = run(loop, clock, [0.2 * MS, 3.4 * MS, 0.2 * MS, 0.2 * MS])
    # tick 1 ends at 4.4 ms: a miss itself; periods 2 and 3 are lost (skipped, not run in a burst)
    assert [g[0] for g in got] == [0, 1, 4, 5]
    np.testing.assert_allclose([g[1] for g in got], [MS, MS, 3 * MS, MS])
    assert [g[2] for g in got] == [1, 1, 3, 1]
    # tick 2 is late against period 2's deadline (before the skip)
    np.testing.assert_allclose([g[3] for g in got], [0.0, 0.0, 2.4 * MS, 0.0], atol=1e-12)
    assert loop.misses == 3 and loop.periods == 6 and loop.ticks == 4
    np.testing.assert_allclose(loop.late[:4], [0.0, 0.0, 2.4 * MS, 0.0], atol=1e-12)
    np.testing.assert_allclose(loop.compute[:4], [0.2 * MS, 3.4 * MS, 0.2 * MS, 0.2 * MS], atol=1e-12)


def test_a_late_start_within_the_period_is_lateness_not_a_skip():
    clock = FakeClock()
    loop = PeriodicLoop(MS, clock, max_lateness_s=0.5 * MS)
    got = run(loop, clock, [1.7 * MS, 0.1 * MS, 0.1 * MS])
    assert [g[0] for g in got] == [0, 1, 2]           # tick 1 starts 0.7 ms late: no period lost
    assert [g[2] for g in got] == [1, 1, 1]
    assert got[1][3] == pytest.approx(0.7 * MS) and [g[4] for g in got] == [False, True, False]
    assert loop.overruns == 1 and loop.misses == 1    # tick 0 ended past its period


class _WakeClock(FakeClock):
    """A wait that sees its deadline pass ``wake_late`` s after it, then ``after`` s of Python
    before the caller's next clock reading."""

    def __init__(self, wake_late, after):
        super().__init__()
        self.wake_late, self.after = wake_late, after

    def sleep_until(self, t):
        self.t = max(self.t, t + self.wake_late)
        woke = self.t
        self.t += self.after
        return woke


def test_lateness_is_measured_where_the_wait_saw_the_deadline_pass():
    """A tick starts when the wait saw its deadline pass (the clock reading the wait returns):
    the Python between the wait and the tick is the tick's (compute), not lateness."""
    clock = _WakeClock(2e-6, 0.7e-6)
    loop = PeriodicLoop(MS, clock)
    for k in range(3):
        loop.begin()
        assert loop.late_s == pytest.approx(2e-6, abs=1e-12) and loop.started == pytest.approx(k * MS + 2e-6)
        clock.advance(10e-6)
        loop.end()
    np.testing.assert_allclose(loop.compute[:3], 10.7e-6, atol=1e-12)
    np.testing.assert_allclose(loop.late[:3], 2e-6, atol=1e-12)


def test_the_real_clock_reports_a_reading_at_or_after_the_deadline():
    from pointfence.service.clock import RealClock

    for clock in (RealClock(), RealClock(spin_s=0.0), RealClock(spin_yield=True)):
        t = time.perf_counter() + 0.002
        woke = clock.sleep_until(t)
        assert t <= woke <= time.perf_counter()


def test_run_ticks_until_stop_or_keep_going_says_no():
    clock = FakeClock()
    loop = PeriodicLoop(MS, clock)
    ks = []

    def body(k):
        ks.append(k)
        clock.advance(0.1 * MS)
        if k == 4:
            loop.stop()

    loop.run(body)
    assert ks == [0, 1, 2, 3, 4] and loop.stopping
    loop.run(body)                                     # still stopped: no tick
    assert ks == [0, 1, 2, 3, 4]
    loop.rearm()
    loop.run(lambda k: ks.append(k), keep_going=lambda: len(ks) < 8)
    assert ks == [0, 1, 2, 3, 4, 5, 6, 7]


def test_run_accounts_for_a_tick_whose_body_raises():
    clock = FakeClock()
    loop = PeriodicLoop(MS, clock)

    def body(k):
        clock.advance(0.3 * MS)
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        loop.run(body)
    assert loop.ticks == 1 and loop.k == 1 and loop.compute[0] == pytest.approx(0.3 * MS)


def test_a_stop_before_the_thread_runs_is_not_lost():
    loop = PeriodicLoop(MS, FakeClock())
    loop.stop()
    t = threading.Thread(target=loop.run, args=(lambda k: None,))
    t.start()
    t.join(timeout=5.0)
    assert not t.is_alive() and loop.ticks == 0


def test_recent_returns_the_ticks_since_a_mark():
    clock = FakeClock()
    loop = PeriodicLoop(MS, clock, ring=4)
    run(loop, clock, [0.1 * MS, 0.2 * MS, 0.3 * MS, 0.4 * MS, 0.5 * MS, 0.6 * MS])
    late, comp = loop.recent(0)                        # the ring holds the last 4
    np.testing.assert_allclose(comp, [0.3 * MS, 0.4 * MS, 0.5 * MS, 0.6 * MS])
    late, comp = loop.recent(5)
    np.testing.assert_allclose(comp, [0.6 * MS])


@pytest.mark.parametrize("period, ring", [(0.0, 8), (float("nan"), 8), (float("inf"), 8), (MS, 6)])
def test_bad_settings_are_refused_with_their_value(period, ring):
    with pytest.raises(InputError, match="PeriodicLoop"):
        PeriodicLoop(period, FakeClock(), ring=ring)


class _SlowPlant:
    """A simulated grasper whose driver call takes scripted times on a fake clock."""

    def __init__(self, clock, durations):
        from pointfence.service.cable.plant import SimulatedPlant

        self.plant, self.clock, self.durations, self.n = SimulatedPlant(seed=1), clock, list(durations), 0

    def measure(self):
        return self.plant.measure()

    def actuate(self, tau):
        self.clock.advance(self.durations[self.n] if self.n < len(self.durations) else 0.0)
        self.n += 1
        self.plant.actuate(tau)


def test_the_cable_controller_skips_lost_periods_and_counts_them():
    from pointfence.service.cable.controller import CableController
    from pointfence.service.cable.params import GrasperParams

    clock = FakeClock()
    plant = _SlowPlant(clock, [0.0, 3.5 * MS, 0.0, 0.0])
    ctl = CableController(plant, GrasperParams(), clock=clock)
    ctl.run_ticks(4)
    s = ctl.status()
    # tick 1 ends at 4.5 ms (a miss), periods 2 and 3 are lost (misses, not run in a burst)
    assert s.ticks == 4 and s.periods == 6 and s.deadline_misses == 3
    assert s.lateness_p99_us == pytest.approx(2500, rel=0.05) and s.fault is None
    assert any("3 of 6 control periods" in a for a in s.alerts)


def test_every_periodic_loop_of_the_product_is_this_one():
    """The haptic loop, the hosted arms' process and the cable controller tick on PeriodicLoop
    (one policy for missed periods), none on a schedule of its own."""
    import inspect

    from pointfence.service import loop as haptic
    from pointfence.service.cable import controller
    from pointfence.service.robot import hosted_child

    for mod in (haptic, controller, hosted_child):
        src = inspect.getsource(mod)
        assert "PeriodicLoop(" in src, mod.__name__
        assert "sleep_until(" not in src and "time.sleep(delay" not in src, mod.__name__
