"""`pointfence bench replay` end to end: it records a live run driven by device-sim, replays it in
a process of its own and reports the speed, the phases and exactness (the figure itself is the
benchmark's, never asserted here)."""
from __future__ import annotations

import json
import subprocess
import sys


def test_bench_replay_records_replays_and_reports():
    r = subprocess.run([sys.executable, "-m", "pointfence", "bench", "replay", "--json", "--seconds", "2",
                        "--repeat", "2"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    d = json.loads(r.stdout)
    assert d["bench"] == "replay" and d["exact"] and d["mismatched_ticks"] == [0, 0]
    assert d["recording"]["ticks"] > 1500 and d["recording"]["backend"] == "opencl"
    assert len(d["replay_x_realtime"]) == 2 and all(x > 0 for x in d["replay_x_realtime"])
    assert set(d["phases_s"]) >= {"open", "setup", "ticks", "outputs", "total", "run_s"}
    assert d["replay_x_realtime_min"] <= d["replay_x_realtime_p50"] <= d["replay_x_realtime_max"]
