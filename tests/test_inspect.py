"""`pointfence inspect` (service/inspect_cmd.py, recording_info.py) and the run measures from a
recording's depth (service/run_measures.py, recorded_surface.py): a recorded live `serve` run is
inspected (topics, counts, cameras, arms, holds as the file's own events say, measures stored by
serve); a constructed recording of a flat surface gives the known penetration, submittance and
tracking; a truncated file is inspected with a clear note; argument errors are clear."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from pointfence.cli import COMMANDS
from pointfence.kernels.frame import DepthFrame
from pointfence.service import config as config_mod
from pointfence.service import run_measures
from pointfence.service.mcap_read import open_recording
from pointfence.service.mcap_record import McapRecorder
from pointfence.service.tick_io import TickInput, TickOutput
from test_mcap_record import served  # noqa: F401  (the recorded serve run, a module fixture)

ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}
README = Path(__file__).resolve().parents[1] / "README.md"


def _inspect(*args, timeout=300):
    return subprocess.run([sys.executable, "-m", "pointfence", "inspect", *map(str, args)], env=ENV,
                          capture_output=True, text=True, timeout=timeout)


def test_inspect_reports_a_recorded_serve_run(served, tmp_path):
    from test_mcap_record import ros2_messages

    # serve measured its run from the recorded depth and wrote the measures into the recording
    # before closing it (no sidecar: inspect reads them from the file)
    side = run_measures.sidecar_path(served)
    assert not side.exists(), "serve --record kept its measures beside the file, not in it"
    stored = open_recording(served).metadata.get(run_measures.METADATA)
    assert stored and stored["ticks"] > 0 and stored["from"] == "recorded depth"
    res = _inspect(served, "--json", "--plot", tmp_path / "plots")
    assert res.returncode == 0, res.stderr[-2000:]
    rep = json.loads(res.stdout)
    r = open_recording(served)
    assert rep["complete"] and rep["truncated"] is None and rep["note"] is None
    topics = {t["topic"]: t for t in rep["topics"]}
    assert topics["/pointfence/tick/input"]["messages"] == len(r.rows) == rep["ticks"]["recorded"]
    assert topics["/overhead/depth/image_raw"]["schema"] == "sensor_msgs/Image"
    depth_rate = topics["/overhead/depth/image_raw"]["rate_hz"]
    assert depth_rate is not None and 1 < depth_rate <= 31
    cam = rep["cameras"][0]
    assert (cam["name"], cam["width"], cam["height"], cam["fx"], cam["cx"]) == ("overhead", 160, 120, 143.95, 79.5)
    assert cam["frames"] == topics["/overhead/depth/image_raw"]["messages"] > 0
    assert rep["arms"] == [{"arm": 0, "robot": "PSM1", "master": "MTMR", "robot_model": "raven2"}]
    # holds: exactly the file's own hold events, each with its reasons and invariants
    holds = [m.ros_msg for m in ros2_messages(served, topics=["/pointfence/events"]) if m.ros_msg.kind == "hold"]
    assert len(rep["holds"]) == len(holds)
    assert [(h["tick"], h["reason"]) for h in rep["holds"]] == [(int(h.tick), h.reason) for h in holds]
    assert all(h["reason"] and re.fullmatch(r"S\d(,S\d)*", h["invariant"]) for h in rep["holds"])
    m = rep["measures"]
    assert m["stored_in"] == "recording" and m["ticks"] == len(r.rows) == stored["ticks"]
    assert m["safety_max_penetration_m"] == stored["safety_max_penetration_m"]
    assert m["snapshots_rebuilt"] > 0 and m["arms"][0]["ticks_measured"] > 0
    assert m["safety_max_penetration_m"] is not None
    assert [Path(p).name for p in rep["plots"]] == ["arm0_PSM1_distances.png", "timeline.png"]
    assert all(Path(p).stat().st_size > 5000 for p in rep["plots"])
    # the text form says the same
    txt = _inspect(served, "--no-measures")
    assert txt.returncode == 0, txt.stderr[-2000:]
    assert "complete" in txt.stdout and "overhead: 160x120, fx 143.95" in txt.stdout
    assert f"holds      {len(holds)}" in txt.stdout and "safety (max penetration)" in txt.stdout


def test_a_truncated_recording_is_inspected_with_a_clear_note(served, tmp_path):
    cut = tmp_path / "cut.mcap"
    data = served.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.7)])
    # the measures were in the file's end, cut off; a sidecar written for the whole file is not believed
    whole = open_recording(served).metadata[run_measures.METADATA]
    run_measures.sidecar_path(cut).write_text(json.dumps({"recording": cut.name, "recording_bytes": len(data),
                                                           run_measures.METADATA: whole}))
    res = _inspect(cut)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "TRUNCATED" in res.stdout and "Everything before the cut is read" in res.stdout
    rep = json.loads(_inspect(cut, "--json").stdout)
    assert not rep["complete"] and rep["truncated"]
    whole = open_recording(served)
    assert 0 < rep["ticks"]["recorded"] < len(whole.rows)
    assert rep["measures"]["stored_in"] is None and rep["measures"]["ticks"] == rep["ticks"]["recorded"]


# --- the measures on a case with a known answer ----------------------------------------------------
SCENE = """
backend = "numpy"
[workspace]
min = [-0.2, -0.2, -0.05]
max = [0.2, 0.2, 0.2]
[fixture]
mode = "fixture"
radius = 0.02
[[camera]]
name = "top"
source = "synthetic:plane"
fx = 160.0
fy = 160.0
cx = 80.0
cy = 60.0
width = 161
height = 121
T_world_cam = [1, 0, 0, 0,  0, -1, 0, 0,  0, 0, -1, 0.5,  0, 0, 0, 1]
[robot]
model = "none"
"""


def _flat_recording(path: Path, close: bool = True):
    """A recording of a camera 0.5 m above a flat table (z = 0, every point protected, 2 cm
    fixture) and 310 ticks of one arm: 100 free ticks at z = 6 cm with the robot 2 mm from its
    command; 100 held-off ticks (master 1 cm under the surface, robot 2.5 cm above it); 100 ticks
    5 mm above the surface (15 mm into the fixture); 10 uncoupled ticks 1 cm under the surface."""
    (path.parent / "scene.toml").write_text(SCENE)
    cfg = config_mod.load(path.parent / "scene.toml")
    rec = McapRecorder(path, n=1)
    rec.describe({"architecture": "III", "backend": "numpy"})
    feeder = SimpleNamespace(on_snapshot=None, clock_minus_stamp=0.0)
    rec.attach(feeder, cfg, config_text=SCENE)
    depth = np.full((121, 161), 500, np.uint16)               # 0.5 m everywhere: the plane z = 0
    rec.offer_snapshot(1, [DepthFrame(camera="top", depth=depth, timestamp=0.0, seq=1)])
    inp, out = TickInput.zeros(1), TickOutput.zeros(1)
    for k in range(310):
        z_r, z_m, coupled, off = ((0.06, 0.06, True, 0.002) if k < 100 else (0.025, -0.010, True, 0.0) if k < 200
                                  else (0.005, 0.005, True, 0.0) if k < 300 else (-0.010, 0.0, False, 0.0))
        inp.k, inp.t, inp.now = k, k / 1000, k / 1000
        out.k, out.t, out.frame_seq = k, k / 1000, 1
        out.robot_pos[0] = inp.robot_pos[0] = (0.0, 0.0, z_r)
        out.command[0] = (off, 0.0, z_r)
        out.xm[0] = (0.0, 0.0, z_m)
        out.coupled[0] = coupled
        rec.write(inp, out)
    if close:
        rec.close()
    return rec


def test_measures_of_a_robot_pushed_into_a_flat_recorded_surface(tmp_path):
    path = tmp_path / "flat.mcap"
    _flat_recording(path)
    ev = run_measures.evaluate(open_recording(path), backend="numpy")
    s = ev.summary
    assert s["snapshots_rebuilt"] == 1 and s["ticks_measured"] == 310
    # 1 cm under the surface, behind what the camera saw: 1 cm + the 2 cm fixture
    assert s["safety_max_penetration_m"] == pytest.approx(0.030, abs=2e-4)
    assert s["submittance_min_distance_m"] == pytest.approx(0.005, abs=2e-4)   # 2.5 cm - 2 cm, held off
    assert s["tracking_rms_m"] == pytest.approx(0.002, abs=1e-9)               # the free ticks only
    arm = s["arms"][0]
    assert arm["ticks_inside"] == 110 and arm["ticks_coupled"] == 300 and arm["deepest"]["tick"] >= 300
    d = ev.traces[0]["d_r"]
    assert d[250] == pytest.approx(-0.015, abs=2e-4)                           # 5 mm above: 15 mm in
    assert d[50] == pytest.approx(0.040, abs=2e-4)
    # stored beside the file, then shown by inspect as stored
    where = run_measures.store(path, s)
    res = _inspect(path, "--json")
    assert res.returncode == 0, res.stderr[-2000:]
    got = json.loads(res.stdout)["measures"]
    assert got["stored_in"] == where and got["safety_max_penetration_m"] == pytest.approx(0.030, abs=2e-4)


def test_measures_go_into_the_open_recording_after_its_flush_barrier(tmp_path):
    path = tmp_path / "flat.mcap"
    rec = _flat_recording(path, close=False)
    late = np.zeros((121, 161), np.uint16)
    got = run_measures.before_close(path, rec)          # seal: every tick on disk, then measured and stored
    rec.offer_snapshot(2, [DepthFrame(camera="top", depth=late, timestamp=1.0, seq=2)])   # after the run: not recorded
    rec.close()
    assert got["stored_in"] == str(path) and got["ticks"] == 310, got
    assert got["safety_max_penetration_m"] == pytest.approx(0.030, abs=2e-4)
    r = open_recording(path)
    assert r.torn is None and len(r.rows) == 310 and sorted(r.snapshots) == [1]
    assert r.metadata[run_measures.METADATA]["safety_max_penetration_m"] == got["safety_max_penetration_m"]
    assert not run_measures.sidecar_path(path).exists()
    rep = json.loads(_inspect(path, "--json").stdout)
    assert rep["measures"]["stored_in"] == "recording" and rep["measures"]["ticks"] == 310
    # a recorder whose writer is gone cannot seal: None (the caller measures the closed file instead)
    path2 = tmp_path / "gone.mcap"
    rec2 = _flat_recording(path2, close=False)
    os.kill(rec2.status()["writer_pid"], 9)
    end = time.monotonic() + 10
    while rec2.status()["writer_alive"] and time.monotonic() < end:
        time.sleep(0.01)
    assert run_measures.before_close(path2, rec2) is None
    rec2.close()


def test_store_puts_the_measures_into_a_recorder_that_offers_metadata(tmp_path):
    got = {}
    rec = SimpleNamespace(add_metadata=lambda name, values: got.update({name: values}))
    assert run_measures.store(tmp_path / "x.mcap", {"safety_max_penetration_m": 0.001, "arms": []}, recorder=rec)
    assert run_measures.stored(tmp_path / "x.mcap", got) == ({"safety_max_penetration_m": 0.001, "arms": []}, "recording")
    assert not run_measures.sidecar_path(tmp_path / "x.mcap").exists()


# --- the command line ----------------------------------------------------------------------------------
def test_inspect_arguments_and_errors_are_clear(tmp_path):
    h = _inspect("--help")
    assert h.returncode == 0 and "--json" in h.stdout and "--plot" in h.stdout and "FILE.mcap" in h.stdout
    none = _inspect()
    assert none.returncode == 2 and "FILE.mcap" in none.stderr
    missing = _inspect(tmp_path / "nope.mcap")
    assert missing.returncode == 1 and "nope.mcap' not found" in missing.stderr
    (tmp_path / "x.mcap").write_text("not mcap")
    bad = _inspect(tmp_path / "x.mcap")
    assert bad.returncode == 1 and "not an MCAP file" in bad.stderr
    both = _inspect(tmp_path / "x.mcap", "--recompute", "--no-measures")
    assert both.returncode == 2 and "not allowed with" in both.stderr
    plot = _inspect(tmp_path / "x.mcap", "--plot", tmp_path / "p", "--no-measures")
    assert plot.returncode == 1 and "drop --no-measures" in plot.stderr


def test_readme_lists_every_command():
    rows = [ln for ln in README.read_text().splitlines() if ln.startswith("| `")]
    for name in COMMANDS:
        assert any(re.search(rf"`{re.escape(name)}[ `]", ln) for ln in rows), f"README's command table lacks {name}"


def _plain_distances(rec, skip=()):
    """The measures' per-tick distances rebuilt the plain way: every snapshot ingested and measured
    in turn (no build beside the measuring, no decoding ahead)."""
    from pointfence.kernels import get_backend
    from pointfence.service.mcap_replay import recording_config
    from pointfence.service.recorded_surface import RecordedSurface

    cfg = recording_config(rec)
    pipe = get_backend(rec.meta["backend"]).pipeline([c.camera for c in cfg.cameras], cfg.pipeline)
    lay, n = rec.layout, rec.layout.n
    c, _ = lay.cols[("out", "frame_seq")]
    seqs = rec.rows[:, c].astype(np.int64)
    cols = {f: lay.cols[("out", f)][0] for f in ("robot_pos", "xm")}
    d_r = np.full((len(seqs), n), np.nan)
    for seq in [int(s) for s in np.unique(seqs) if s > 0 and s not in skip]:
        fseqs, findex, stamps, poses = rec.snapshots[seq]
        frames = [rec.frame(i, idx, fs, stamps[i], poses[16 * i: 16 * i + 16])
                  for i, (fs, idx) in enumerate(zip(fseqs, findex))]
        pipe.ingest(frames)
        surf = RecordedSurface(pipe.host_snapshot(), pipe.rig.cameras, pipe.rig.order(frames), pipe.rig.offsets)
        sel = np.flatnonzero(seqs == seq)
        d_r[sel] = surf.signed_distance(rec.rows[sel, cols["robot_pos"]: cols["robot_pos"] + 3 * n].reshape(-1, 3)
                                        ).reshape(-1, n)
    return seqs, d_r


def test_the_measures_equal_a_plain_rebuild_snapshot_by_snapshot(served):
    """``evaluate`` builds each snapshot while the ticks of the one before it are measured; the
    distances are those of building and measuring one snapshot after the other, bit for bit,
    also where a snapshot's frames are missing from the file."""
    rec = open_recording(served)
    seqs, want = _plain_distances(rec)
    ev = run_measures.evaluate(rec)
    ok = ~np.isnan(want[:, 0])
    assert ok.sum() > 1000 and ev.summary["snapshots_missing"] == []
    np.testing.assert_array_equal(ev.traces[0]["d_r"], want[ok, 0])
    # one snapshot's frames gone (dropped while recording): not measured, the others as before
    gone = int(np.unique(seqs[seqs > 0])[len(np.unique(seqs[seqs > 0])) // 2])
    rec = open_recording(served)
    del rec.snapshots[gone]
    seqs, want = _plain_distances(rec, skip=(gone,))
    ev = run_measures.evaluate(rec)
    ok = ~np.isnan(want[:, 0])
    assert ev.summary["snapshots_missing"] == [gone] and (~ok).sum() >= (seqs == gone).sum() > 0
    np.testing.assert_array_equal(ev.traces[0]["d_r"], want[ok, 0])
