"""Real-time scheduling of the service's threads that hold the interpreter lock and feed or watch
the haptic tick (issue 18): the UDP and ITP receivers and the tick watchdog run SCHED_FIFO where
the OS allows it, as the loop and the frame threads do. At normal priority on a loaded machine
they waited for a core for tens of milliseconds: the devices' samples grew old and their sessions
timed out (arms held, S9), and one preempted while holding the lock kept the loop waiting."""
import os
import sys
import threading
import time

import pytest

from pointfence.service.clock import FakeClock
from pointfence.service.itp import ItpReceiver
from pointfence.service.osthread import set_fifo
from pointfence.service.udp_server import UdpHub
from pointfence.service.watchdog import TickWatchdog

KEY = bytes(range(3, 35))


def _fifo_allowed() -> bool:
    """Whether this process may make a thread SCHED_FIFO (root, or an RLIMIT_RTPRIO that allows it)."""
    out = {}

    def probe():
        out["s"] = set_fifo(threading.get_native_id(), 1)

    t = threading.Thread(target=probe)
    t.start()
    t.join()
    return out["s"] == "SCHED_FIFO 1"


linux = pytest.mark.skipif(not sys.platform.startswith("linux") or not hasattr(os, "SCHED_FIFO"),
                           reason="SCHED_FIFO is Linux's")


def _policy(native_id: int) -> int:
    return os.sched_getscheduler(native_id)


@linux
def test_set_fifo_applies_or_says_why_not_and_zero_leaves_the_thread_alone():
    out = {}

    def run():
        tid = threading.get_native_id()
        out["zero"] = set_fifo(tid, 0)
        out["policy0"] = _policy(tid)
        out["set"] = set_fifo(tid, 3)
        out["policy"] = _policy(tid)

    t = threading.Thread(target=run)
    t.start()
    t.join()
    assert out["zero"] == "normal" and out["policy0"] == os.SCHED_OTHER
    if _fifo_allowed():
        assert out["set"] == "SCHED_FIFO 3" and out["policy"] == os.SCHED_FIFO
    else:
        assert out["set"].startswith("normal (SCHED_FIFO refused") and out["policy"] == os.SCHED_OTHER
    assert _policy(threading.get_native_id()) == os.SCHED_OTHER      # only that thread
    assert set_fifo(2 ** 22 + 12345, 3).startswith("normal (SCHED_FIFO refused")   # no such thread


@linux
@pytest.mark.skipif(not _fifo_allowed(), reason="SCHED_FIFO not allowed here")
def test_the_udp_and_itp_receivers_run_sched_fifo_when_asked_and_say_so():
    hub = UdpHub(KEY, 1)
    itp = ItpReceiver("127.0.0.1", 0)
    try:
        assert hub.status()["receiver_scheduling"] == "normal"
        assert _policy(hub._thread.native_id) == os.SCHED_OTHER
        assert hub.set_rt_priority(7) == "SCHED_FIFO 7"
        assert _policy(hub._thread.native_id) == os.SCHED_FIFO
        assert os.sched_getparam(hub._thread.native_id).sched_priority == 7
        assert hub.status()["receiver_scheduling"] == "SCHED_FIFO 7"
        assert itp.set_rt_priority(7) == "SCHED_FIFO 7" and itp.status()["receiver_scheduling"] == "SCHED_FIFO 7"
        assert hub.set_rt_priority(0) == "normal"   # 0 leaves it (a running thread is not lowered)
    finally:
        hub.close()
        itp.close()
    pumped = UdpHub(KEY, 1, receiver=False)          # no thread: nothing to schedule
    try:
        assert pumped.set_rt_priority(7) == "normal"
    finally:
        pumped.close()


class _Loop:
    tick_started = None

    def __init__(self):
        self.clock = FakeClock()


@linux
@pytest.mark.skipif(not _fifo_allowed(), reason="SCHED_FIFO not allowed here")
def test_the_tick_watchdog_runs_at_the_loops_priority_and_still_sees_a_stall():
    loop, stalls = _Loop(), []

    class Target:
        def on_stall(self, started, now):
            stalls.append((started, now))

    wd = TickWatchdog(loop, Target(), 0.003, poll_s=0.001, rt_priority=9)
    wd.start()
    try:
        end = time.monotonic() + 5.0
        while wd.scheduling == "normal" and time.monotonic() < end:
            time.sleep(0.005)
        assert wd.scheduling == "SCHED_FIFO 9"
        assert _policy(wd._thread.native_id) == os.SCHED_FIFO
        loop.tick_started = loop.clock.now()
        loop.clock.advance(0.01)                      # a tick 10 ms long: a stall
        end = time.monotonic() + 5.0
        while not stalls and time.monotonic() < end:
            time.sleep(0.005)
        assert len(stalls) == 1 and wd.trips == 1
    finally:
        wd.stop()
    plain = TickWatchdog(loop, Target(), 0.003)       # the default: normal, as before
    assert plain.rt_priority == 0
