"""OS-level thread names: the service's threads show as such in top -H, ps -L and perf."""
import sys
import threading

import pytest

from pointfence.service.clock import FakeClock
from pointfence.service.loop import HapticLoop
from pointfence.service.osthread import name_this_thread, os_thread_name

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="thread names from /proc are Linux's")


@linux
def test_a_thread_names_itself_and_long_names_are_cut_to_15_bytes():
    out = {}

    def run():
        out["ok"] = name_this_thread("pf-a-name-longer-than-fifteen")
        out["name"] = os_thread_name()

    t = threading.Thread(target=run)
    t.start()
    t.join()
    assert out["ok"] and out["name"] == "pf-a-name-longe"
    assert os_thread_name() != "pf-a-name-longe"   # only that thread


@linux
def test_the_haptic_loop_thread_is_named():
    class Target:
        def __init__(self):
            self.name = None
            self.seen = threading.Event()

        def tick(self, k, t, dt, overrun, now):
            self.name = os_thread_name()
            self.seen.set()

        def safe_tick(self, k, t, dt, now):
            pass

    target = Target()
    loop = HapticLoop(target, FakeClock(), switch_interval_s=None, cooperate=False)
    loop.start()
    try:
        assert target.seen.wait(5.0)
    finally:
        loop.stop()
    assert target.name == "pf-haptic-loop"
