"""Frame threads step aside for the haptic loop (kernels/yielding.py, service/loop.py)."""
import threading
import time

from pointfence.kernels import yielding
from pointfence.service.clock import FakeClock
from pointfence.service.loop import HapticLoop


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
