"""bench/machine.py's per-process CPU shares (``bench ros2``'s ``cpu_pct_by_process``): a child's
time goes to the role its command line names, this process's to "service", and a process that is
not a descendant is not counted."""
from __future__ import annotations

import subprocess
import sys
import time

import pytest

from pointfence.bench.machine import process_times, process_usage

BURN = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.4: pass\ntime.sleep(5)"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_childs_cpu_time_goes_to_its_role():
    roles = {"burner": "pf_burn_marker", "idle": "pf_idle_marker"}
    kids = [subprocess.Popen([sys.executable, "-c", BURN + "  # pf_burn_marker"]),
            subprocess.Popen([sys.executable, "-c", "import time; time.sleep(5)  # pf_idle_marker"])]
    try:
        t0 = process_times(roles)
        time.sleep(0.1)
        end = time.process_time() + 0.2
        while time.process_time() < end:       # this process: 0.2 s of CPU
            pass
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            t1 = process_times(roles)
            if t1.get("burner", 0.0) - t0.get("burner", 0.0) >= 0.35:
                break
            time.sleep(0.1)
        use = process_usage(t0, t1)
        assert t1["burner"] - t0.get("burner", 0.0) >= 0.35            # the child's 0.4 s (clock ticks of 10 ms)
        assert t1["service"] - t0["service"] >= 0.15
        assert t1.get("idle", 0.0) - t0.get("idle", 0.0) < 0.1
        assert set(use) >= {"burner", "service"} and use["burner"] > 0
    finally:
        for k in kids:
            k.kill()
            k.wait()


def test_processes_that_are_not_descendants_are_not_counted(tmp_path):
    """An orphan (its shell parent gone: reparented away from this process) burning CPU with a
    matching command line is not counted."""
    script = tmp_path / "pf_orphan_marker.py"          # (the command line names the file)
    script.write_text(BURN + "\n")
    subprocess.run(["sh", "-c", f"{sys.executable} {script} >/dev/null 2>&1 &"], check=True)
    try:
        time.sleep(0.6)
        t = process_times({"orphan": "pf_orphan_marker"})
        assert t is not None and "service" in t and "orphan" not in t
        assert subprocess.run(["pgrep", "-f", "pf_orphan_marker"], capture_output=True).stdout.strip()   # (it runs)
    finally:
        subprocess.run(["pkill", "-f", "pf_orphan_marker"])
