"""service/memory.py: live runs turn transparent huge pages off (khugepaged stalled the loop)."""
import subprocess
import sys

import pytest


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the THP switch is Linux's")
def test_small_pages_turns_the_process_thp_switch_off_and_children_inherit_it():
    # the switch is inherited: start from it on (PR_SET_THP_DISABLE = 41, 0), whatever this
    # test process did before (an in-process live run turns it off for its children too)
    code = """
import ctypes, subprocess, sys
ctypes.CDLL(None, use_errno=True).prctl(41, 0, 0, 0, 0)
from pointfence.service.memory import small_pages, huge_pages_disabled
before = huge_pages_disabled()
done = small_pages()
child = subprocess.run([sys.executable, "-c",
    "from pointfence.service.memory import huge_pages_disabled as h; print(h())"], capture_output=True, text=True)
print(before, huge_pages_disabled(), child.stdout.strip(), done)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    before, after, child, *done = out.stdout.split()
    assert (before, after, child) == ("False", "True", "True")
    assert "THP off (prctl)" in " ".join(done) and "numpy madvise off" in " ".join(done)


def test_live_run_turns_huge_pages_off_before_anything_starts(monkeypatch):
    """LiveRun calls small_pages() first thing (before the robot process, which inherits it)."""
    from pointfence.service import runner

    calls = []
    monkeypatch.setattr(runner, "small_pages", lambda: calls.append("small") or "done")

    class Stop(Exception):
        pass

    def refuse(*a, **k):
        calls.append("service")
        raise Stop

    monkeypatch.setattr(runner, "Service", refuse)
    from dataclasses import replace

    from pointfence.service.config import load

    cfg = load()   # the embedded defaults
    cfg = replace(cfg, service=replace(cfg.service, robot_process=False))
    with pytest.raises(Stop):
        runner.LiveRun(cfg, [object()])
    assert calls == ["small", "service"]
