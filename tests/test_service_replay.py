"""Replay: offline runs are deterministic, a live run's recording replays to the same ticks, and
the ticks.csv / summary.json formats."""
import argparse
import gc
import json

import numpy as np
import pytest

from pointfence.kernels import yielding
from pointfence.service import replay
from pointfence.service.masters import write_trajectory
from pointfence.service.record import TICK_COLUMNS, read_ticks_csv
from pointfence.service.runner import LiveRun

from service_cases import BALLOON, RAVEN, balloon_config, needs_opencl, push

pytestmark = needs_opencl
SUMMARY_KEYS = {"architecture", "ticks", "frames", "safety_max_penetration_m", "submittance_min_distance_m",
                "tracking_rms_m", "tick_us_p50", "tick_us_p99", "deadline_misses", "backend", "device"}


def cli(args):
    p = argparse.ArgumentParser()
    replay.add_arguments(p)
    return replay.run(p.parse_args(args))


def test_replay_cli_is_deterministic_and_formats(tmp_path, capsys):
    cfg_path = tmp_path / "scene.toml"
    cfg_path.write_text(BALLOON.format(arch="III", robot=RAVEN, source="synthetic:sphere", options=""))
    traj = tmp_path / "push.csv"
    write_trajectory(traj, [0.0, 0.1, 0.7, 0.8], [[0, 0, 0], [0, 0, 0], [0, 0, -0.09], [0, 0, -0.09]])
    outs = []
    for name in ("a", "b"):   # NumPy reference: bit-for-bit reproducible snapshots (see below)
        assert cli(["--config", str(cfg_path), "--trajectory", str(traj), "--out", str(tmp_path / name),
                    "--backend", "numpy"]) == 0
        outs.append(tmp_path / name)
    capsys.readouterr()
    texts = [(o / "ticks.csv").read_text().splitlines() for o in outs]
    assert texts[0][0] == ",".join(TICK_COLUMNS)
    strip = lambda lines: [ln.rsplit(",", 1)[0] for ln in lines]  # noqa: E731 (tick_us is this machine's time)
    assert strip(texts[0]) == strip(texts[1])
    a = read_ticks_csv(outs[0] / "ticks.csv")
    assert a.shape == (1300, len(TICK_COLUMNS))
    np.testing.assert_allclose(np.diff(a[:, 0]), 1e-3, atol=1e-9)
    assert set(np.unique(a[:, 19])) <= {0, 1, 2} and a[-1, 20] >= 30      # states; snapshots at 30 Hz
    s = json.loads((outs[0] / "summary.json").read_text())
    assert SUMMARY_KEYS <= set(s)
    assert s["architecture"] == "III" and s["ticks"] == 1300 and s["frames"] >= 39
    assert s["safety_max_penetration_m"] <= 0.001 and s["submittance_min_distance_m"] is not None
    # architecture override
    assert cli(["--config", str(cfg_path), "--trajectory", str(traj), "--out", str(tmp_path / "c"),
                "--architecture", "I"]) == 0
    s1 = json.loads((tmp_path / "c" / "summary.json").read_text())
    assert s1["architecture"] == "I" and s1["safety_max_penetration_m"] > 0.005


def test_recorded_offline_run_replays_exactly(tmp_path):
    # on the NumPy reference every snapshot is bit-for-bit reproducible, so the replay is exact
    # (PoCL's counting sort may order the points of a cell differently from run to run: the
    # proxy's sums then differ in the last bit and runs drift apart by up to ~0.5 mm, see below)
    cfg = balloon_config(tmp_path, arch="II")
    events = {500: lambda s: s.set_architecture("III"), 800: lambda s: s.engage_teleop(False)}
    svc, loop, sources = replay.simulate(cfg, [push(0.10, t_end=0.8, hold=0.2)], 1.0, events=events,
                                         backend="numpy")
    replay.write_outputs(svc, sources, cfg, tmp_path / "rec", svc.feeder.snapshots)
    for s in sources:
        s.close()
    svc2, sources2 = replay.replay_recording(cfg, tmp_path / "rec")
    assert svc2.backend.name == "numpy"
    for s in sources2:
        s.close()
    a, b = svc.recorder.ticks(), svc2.recorder.ticks()
    np.testing.assert_array_equal(a[:, :-1], b[:, :-1])


def test_live_run_recording_replays_to_the_same_forces(tmp_path):
    # a shared test machine may be late by milliseconds: no overrun holds here, this is about replay;
    # the robot steps in the tick (a hosted robot runs on its own clock, which no replay repeats)
    cfg = balloon_config(tmp_path, arch="III", extra="max_lateness_s = 1.0\nrobot_process = false\n")
    run = LiveRun(cfg, [push(0.10, t_end=0.6, hold=1.0)], record_s=2.0)
    run.start()
    try:
        run.wait_ticks(400)
        # the live run's start-up objects are frozen out of garbage collection, and its frame
        # threads step aside for the loop's ticks (kernels/yielding.py)
        frozen, gate = gc.get_freeze_count(), yielding.installed()
        run.service.set_architecture("I")
        run.wait_ticks(800)
    finally:
        run.stop()
    assert frozen > 1000 and gc.get_freeze_count() == 0
    assert gate is not None and gate.owner is not None and yielding.installed() is None
    svc = run.service
    assert svc.recorder.count > 500 and run.loop.error is None   # (periods skipped on a loaded machine are not ticks)
    # frame threads: SCHED_FIFO below the loop where the loop got it, else left normal
    fr = run.frames.status(run.clock.now())["scheduling"]
    if run.loop.scheduling.startswith("SCHED_FIFO"):
        assert fr == f"SCHED_FIFO {cfg.service.frames_rt_priority}"
    else:
        assert fr == "normal" or fr.startswith("normal (SCHED_FIFO refused")
    replay.write_outputs(svc, run.sources, cfg, tmp_path / "live", svc.feeder.snapshots)
    svc2, sources2 = replay.replay_recording(cfg, tmp_path / "live")
    for s in sources2:
        s.close()
    a, b = svc.recorder.ticks(), svc2.recorder.ticks()
    assert len(a) == len(b) == svc.recorder.count
    # whatever the machine's timing was live (skipped periods, frame arrival), the same ticks
    # follow, within the OpenCL snapshots' run-to-run reproducibility (see above)
    np.testing.assert_allclose(b[:, 16:19], a[:, 16:19], atol=0.05)
    np.testing.assert_allclose(b[:, 10:16], a[:, 10:16], atol=1e-3)
    assert (b[:, 19] == a[:, 19]).mean() > 0.98
    assert np.abs(a[:, 16:19]).max() > 0.5        # it was in contact (not a trivially zero replay)
