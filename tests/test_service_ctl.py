"""The control API (service/control_api.py) and `pointfence ctl` against a running Service: the
haptic loop runs in its own thread on the simulated clock (FakeClock: as fast as it can, no
wall-clock deadlines), frames arrive at their timestamps, requests go over HTTP on loopback.
Every command's effect (with the run's token: tests/test_control_auth.py refuses without it); bad commands are 4xx JSON errors and change nothing; radius and
selection changes swap the pipeline between ticks (new snapshots carry the new parameters; no
step in the robot command or the force); and one live `pointfence serve` process driven with `pointfence ctl`."""
import json
import os
import subprocess
import sys
import time
import urllib.error
import urllib.request

import numpy as np
import pytest

from pointfence.service import ctl
from pointfence.service.control_api import ControlServer
from pointfence.service.ctl import ControlRefused
from pointfence.service.record import C

from control_rig import Running
from service_cases import needs_opencl

pytestmark = needs_opencl


@pytest.fixture
def rig(tmp_path):
    r = Running(tmp_path / "rig")
    yield r
    r.close()


def test_status_and_metrics(rig):
    rig.wait_ticks(50)
    st = rig.client.status()
    assert st["ok"] and st["architecture"] == "III" and st["haptics"] is True and st["teleop"] is True
    assert st["tick"] >= 50 and len(st["arms"]) == 1 and set(st["arms"][0]) >= {"xm", "hip", "proxy", "xr", "force", "state"}
    assert st["fixture"]["radius"] == pytest.approx(0.02) and st["fixture"]["selection"]["kind"] == "color"
    assert st["frames"]["cameras"] == ["overhead"] and st["clients"]["slots"] == 1
    m = rig.client.metrics()
    for key in ("ticks", "misses", "overruns", "compute_us_p99", "late_us_p99", "miss_ratio"):
        assert key in m["loop"]
    assert m["loop"]["ticks"] >= 50 and m["loop_error"] is None
    assert m["degraded"] is False and m["hold"] == [] and m["arms_holding"] == [[]]
    assert m["cameras"]["stale"] == [] and m["cameras"]["ages_s"]["overhead"] < 0.1
    assert m["clients"] == {"slots": 1, "connected": 0, "accepted": None, "rejected_total": None,
                            "timed_out": None, "closed": None}
    assert rig.client.get("/config")["fixture"]["cell_size_fixed"] is False


def test_switching_through_the_api_while_pushing_moves_no_robot(tmp_path):
    """S1 through the control API (issue 18, failure 2): the master has pushed the robot onto
    the fixture and holds still; switching III -> I -> II -> III and haptics off and on, each
    applied between two ticks by the API, leave the command where it is (before the fix, the
    API's switch bypassed the re-anchoring: III -> I walked the command into the region)."""
    r = Running(tmp_path / "rig")
    try:
        r.wait_ticks(2100)                          # the push ends at 2 s: the master holds still
        first = r.client.set_architecture("I")["applied_before_tick"]
        for a in ("II", "III"):
            r.wait_ticks(r.loop.ticks + 100)
            r.client.set_architecture(a)
        for on in (False, True):
            r.wait_ticks(r.loop.ticks + 100)
            r.client.engage("haptics", on)
        r.wait_ticks(r.loop.ticks + 100)
        st = r.client.status()
        rec = r.svc.recorder
        cmd = rec.robots[: rec.count, 0, 3:]
        arch = rec.inputs[: rec.count, 4]
        assert set(arch[first:]) == {1, 2, 3}
        assert np.linalg.norm(cmd[first:] - cmd[first - 1], axis=1).max() < 1e-4 and st["hold"] == []
        xm = rec.masters_world[rec.count - 1, 0]
        assert np.linalg.norm(xm - cmd[first - 1]) < 1e-4      # re-anchored: the push is not replayed
    finally:
        r.close()


def test_set_architecture_engage_disengage(rig):
    rig.wait_ticks(20)
    r = rig.client.set_architecture("I")
    assert r["architecture"] == "I" and r["previous"] == "III" and rig.svc.architecture == "I"
    assert rig.client.set_architecture("ii")["architecture"] == "II" and rig.svc.architecture == "II"
    r = rig.client.engage("haptics", False)
    assert r["haptics"] is False and r["previous"] is True and rig.svc.haptics_on is False
    rig.wait_ticks(100)                             # force_ramp_s 0.02: the gain has ramped to zero
    st = rig.client.status()
    assert st["haptics"] is False and st["force_gain"] == [0.0] and st["arms"][0]["force"] == [0.0, 0.0, 0.0]
    assert rig.client.engage("haptics", True)["haptics"] is True and rig.svc.haptics_on is True
    assert rig.client.engage("teleop", False)["teleop"] is False
    rig.wait_ticks(5)
    st = rig.client.status()
    assert st["teleop"] is False and st["coupled"] == [False]
    held = np.array(st["arms"][0]["cmd"])
    rig.wait_ticks(200)                             # the master keeps pushing: the robot does not follow
    assert np.allclose(rig.client.status()["arms"][0]["cmd"], held, atol=1e-12)
    assert rig.client.engage("teleop", True)["teleop"] is True
    rig.wait_ticks(5)
    assert rig.client.status()["coupled"] == [True]


def test_bad_commands_are_4xx_json_and_change_nothing(rig):
    rig.wait_ticks(20)
    before = (rig.svc.architecture, rig.svc.haptics_on, rig.svc.teleop_on, rig.svc.pipeline, rig.svc.pipeline.params)
    cases = [
        ("POST", "/architecture", {"architecture": "IV"}, 400, "expected one of I, II, III"),
        ("POST", "/architecture", {}, 400, "architecture = None"),
        ("POST", "/radius", {"radius": -0.01}, 400, "expected 0 < radius"),
        ("POST", "/radius", {"radius": "big"}, 400, "expected a number"),
        ("POST", "/radius", {"radius": 5.0}, 400, "limit"),
        ("POST", "/radius", {"radius": 0.02, "radius_max": 0.01}, 400, "r_max"),
        ("POST", "/selection", {"kind": "box", "min": [0.1, 0, 0], "max": [0, 0.1, 0.1]}, 400, "expected min < max"),
        ("POST", "/selection", {"kind": "box", "min": [0, 0]}, 400, "expected [x, y, z]"),
        ("POST", "/selection", {"kind": "color", "lo": [0, 0, 0], "hi": [300, 0, 0]}, 400, "0..255"),
        ("POST", "/selection", {"kind": "sphere"}, 400, "expected one of all, box, color, mask"),
        ("POST", "/selection", {"kind": "all", "colour": 1}, 400, "unknown key"),
        ("POST", "/haptics", {"engaged": "yes"}, 400, "expected true or false"),
        ("POST", "/teleop", [1, 2], 400, "JSON object"),
        ("GET", "/nothing", None, 404, "no route"),
        ("GET", "/radius", None, 405, "method not allowed"),
    ]
    for method, path, body, code, text in cases:
        status, reply = rig.raw(method, path, body)
        assert status == code and reply["ok"] is False and text in reply["error"], (path, body, status, reply)
    status, reply = rig.raw("POST", "/architecture", b"{not json", ctype="application/json")
    assert status == 400 and "not valid JSON" in reply["error"]
    status, reply = rig.raw("POST", "/architecture", {"architecture": "I"}, ctype="text/plain")
    assert status == 415 and "application/json" in reply["error"]
    rig.wait_ticks(20)
    assert (rig.svc.architecture, rig.svc.haptics_on, rig.svc.teleop_on, rig.svc.pipeline,
            rig.svc.pipeline.params) == before
    assert rig.client.metrics()["control"]["refused"] == len(cases) and rig.controller.reconfigurations == 0
    with pytest.raises(ControlRefused, match="HTTP 400"):
        rig.client.set_architecture("IV")


def test_radius_change_rebuilds_the_snapshots_between_ticks(rig):
    rig.wait_ticks(1500)                        # the master has pushed the robot onto the fixture
    assert rig.svc.batch.states[0] != 0
    old = rig.svc.pipeline
    seq0 = rig.svc.frame_seq
    r = rig.client.radius(0.012)
    assert r["changed"] and r["fixture"]["radius"] == pytest.approx(0.012) and r["fixture"]["radius_max"] == pytest.approx(0.012)
    k = r["applied_before_tick"]
    assert rig.svc.pipeline is not old and rig.svc.pipeline.params.radius.r_base == pytest.approx(0.012)
    assert rig.svc.batch.pipeline is rig.svc.pipeline and rig.svc.feeder.pipeline is rig.svc.pipeline
    assert rig.svc.cfg.pipeline.radius.r_base == pytest.approx(0.012)
    assert rig.svc.pipeline.params.cell_size < old.params.cell_size      # follows the radius
    rig.wait_ticks(200)
    snap = rig.svc.pipeline.host_snapshot()
    prot = snap.protected != 0
    assert prot.any() and np.allclose(snap.points[prot, 3], 0.012)
    assert rig.svc.frame_seq > seq0                                      # numbering goes on
    rec = rig.svc.recorder
    rows = rec.ticks()
    i = int(np.flatnonzero(rec.inputs[: rec.count, 0] == k)[0])
    # at the swap, as at any new snapshot, the proxy may move several steps; the robot command
    # stays rate-limited and the force stays low-passed (no step on the master)
    w = slice(i - 30, i + 60)
    f = rows[w, C["f_x"]: C["f_z"] + 1]
    cmd = rows[w, C["xr_cmd_x"]: C["xr_cmd_z"] + 1]
    hp = rig.svc.params
    assert np.linalg.norm(np.diff(cmd, axis=0), axis=1).max() <= rig.cfg.teleop.max_robot_speed * 1e-3 * (1 + 1e-9)
    assert np.linalg.norm(np.diff(f, axis=0), axis=1).max() <= 2 * hp.max_force / hp.fir_taps
    m = rig.client.metrics()
    assert m["loop_error"] is None and m["kernel_errors"] == 0 and m["control"]["reconfigurations"] == 1
    # the same radius again: nothing to rebuild
    assert rig.client.radius(0.012)["changed"] is False and rig.svc.pipeline.params.radius.r_base == pytest.approx(0.012)


def test_selection_change(rig):
    rig.wait_ticks(100)
    lo, hi = [-0.03, -0.03, 0.0], [0.03, 0.03, 0.2]
    r = rig.client.select("box", min=lo, max=hi)
    assert r["changed"] and r["fixture"]["selection"] == {"kind": "box", "min": lo, "max": hi}
    rig.wait_ticks(100)
    snap = rig.svc.pipeline.host_snapshot()
    pts = snap.points[snap.protected != 0, :3]
    assert len(pts) and np.all(pts >= np.array(lo) - 1e-6) and np.all(pts <= np.array(hi) + 1e-6)
    assert (snap.protected == 0).any()            # the table outside the box is not protected
    assert rig.client.select("all")["fixture"]["selection"] == {"kind": "all"}
    rig.wait_ticks(50)
    assert np.all(rig.svc.pipeline.host_snapshot().protected != 0)


def test_radius_refused_when_the_cell_size_is_fixed(tmp_path):
    r = Running(tmp_path, extra="[hash]\ncell_size = 0.031\n")
    try:
        r.wait_ticks(20)
        before = r.svc.pipeline
        status, reply = r.raw("POST", "/radius", {"radius": 0.03})
        assert status == 409 and "cannot be applied at runtime" in reply["error"] and "cell_size" in reply["error"]
        assert r.svc.pipeline is before and r.svc.feeder.pipeline is before
        ok = r.client.radius(0.015)                      # within the fixed cells: applied
        assert ok["changed"] and r.svc.pipeline.params.cell_size == pytest.approx(0.031)
    finally:
        r.close()


def test_radius_and_selection_refused_in_rendering_mode(tmp_path):
    r = Running(tmp_path, mode_line="rendering")
    try:
        r.wait_ticks(10)
        for path, body in (("/radius", {"radius": 0.01}), ("/selection", {"kind": "all"})):
            status, reply = r.raw("POST", path, body)
            assert status == 409 and "rendering mode" in reply["error"]
        assert r.controller.reconfigurations == 0
    finally:
        r.close()


def test_safe_mode_and_stopped_loop_refuse_with_503(rig):
    rig.wait_ticks(20)
    rig.loop.error = "tick 7: RuntimeError: injected"      # as the loop records an escaped exception
    rig.wait_ticks(5)                                      # safe ticks: every arm decoupled, holding
    status, reply = rig.raw("POST", "/architecture", {"architecture": "I"})
    assert status == 503 and "safe mode" in reply["error"] and rig.svc.architecture == "III"
    status, reply = rig.raw("POST", "/clear-faults", {})     # S3: the pedal is still down
    assert status == 409 and "pedal" in reply["error"] and rig.loop.error is not None
    rig.svc.masters[0].clutches[:] = False                    # the operator lifts the pedal
    rig.wait_ticks(5)
    r = rig.client.post("/clear-faults", {})
    assert r["cleared_loop_error"].startswith("tick 7") and rig.loop.error is None
    assert rig.client.set_architecture("I")["architecture"] == "I"
    rig.loop.stop()
    status, reply = rig.raw("POST", "/radius", {"radius": 0.01})
    assert status == 503 and "not running" in reply["error"]
    assert rig.svc.pipeline.params.radius.r_base == pytest.approx(0.02)


def test_request_not_taken_by_a_tick_is_cancelled(tmp_path):
    """A loop that runs no tick (here: never started, but 'running' as far as the API knows):
    the request times out, is withdrawn, and a radius change puts the feeder back."""
    r = Running(tmp_path, start=False)
    try:
        r.controller.loop = None          # no loop state to check: only the tick would apply it
        r.controller.apply_timeout = 0.3
        old = r.svc.pipeline
        status, reply = r.raw("POST", "/architecture", {"architecture": "I"})
        assert status == 503 and "ran no tick" in reply["error"]
        status, reply = r.raw("POST", "/radius", {"radius": 0.01})
        assert status == 503 and "ran no tick" in reply["error"]
        assert r.svc.pipeline is old and r.svc.feeder.pipeline is old
        r.loop.run_ticks(3)               # the withdrawn requests never run
        assert r.svc.architecture == "III" and r.svc.pipeline is old
    finally:
        r.close()


def test_ctl_command_line(rig, capsys):
    port = str(rig.server.address[1])
    rig.wait_ticks(20)
    assert ctl.main(["--port", port, "set-architecture", "II"]) == 0
    assert json.loads(capsys.readouterr().out)["architecture"] == "II" and rig.svc.architecture == "II"
    assert ctl.main(["--port", port, "disengage", "haptics"]) == 0 and rig.svc.haptics_on is False
    assert ctl.main(["--port", port, "engage", "haptics"]) == 0 and rig.svc.haptics_on is True
    capsys.readouterr()
    assert ctl.main(["--port", port, "radius", "0.015"]) == 0
    assert json.loads(capsys.readouterr().out)["fixture"]["radius"] == pytest.approx(0.015)
    assert ctl.main(["--port", port, "select", "box", "--min", "-0.05", "-0.05", "0", "--max", "0.05", "0.05", "0.2"]) == 0
    assert rig.svc.pipeline.params.selection.kind == "box"
    capsys.readouterr()
    assert ctl.main(["--port", port, "set-architecture", "IV"]) == 1
    err = capsys.readouterr().err
    assert "pointfence ctl: error:" in err and "expected one of I, II, III" in err and "HTTP 400" in err
    assert ctl.main(["--port", port, "radius", "-0.01"]) == 1 and rig.svc.pipeline.params.radius.r_base == pytest.approx(0.015)
    assert ctl.main(["--port", port, "select", "box", "--min", "0", "0", "0"]) == 1
    assert "needs --min X Y Z and --max" in capsys.readouterr().err
    assert ctl.main(["--port", port, "metrics"]) == 0 and "loop" in json.loads(capsys.readouterr().out)
    kept = rig.server.token_file.with_name("kept.token")
    kept.write_text(rig.server.token_file.read_text())
    kept.chmod(0o600)
    rig.server.close()                            # the run's token file goes with it
    assert not rig.server.token_file.exists()
    assert ctl.main(["--port", port, "status"]) == 1
    assert "no control token" in capsys.readouterr().err
    assert ctl.main(["--port", port, "--token-file", str(kept), "status"]) == 1
    assert "no control API" in capsys.readouterr().err
    kept.unlink()


def test_control_api_binds_loopback_only(rig):
    from pointfence.kernels.errors import InputError

    with pytest.raises(InputError, match="loopback only"):
        ControlServer(rig.controller, "0.0.0.0", 0)
    req = urllib.request.Request(rig.server.url + "/status", headers={"Host": "evil.example:80"})
    with pytest.raises(urllib.error.HTTPError) as e:
        urllib.request.urlopen(req, timeout=30)
    assert e.value.code == 403


def test_live_serve_process_with_ctl(tmp_path):
    """`pointfence serve` (the real clock) with its control API, driven by `pointfence ctl`."""
    from pointfence.bench.e2e import LIGHT_SCENE

    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    key = tmp_path / "pf.key"
    assert subprocess.run([sys.executable, "-m", "pointfence.service.serve", "--new-key", str(key)], env=env,
                          capture_output=True).returncode == 0
    scene = tmp_path / "scene.toml"
    scene.write_text(LIGHT_SCENE)
    ready, stats = tmp_path / "ready.json", tmp_path / "stats.json"
    proc = subprocess.Popen([sys.executable, "-m", "pointfence.service.serve", "--key-file", str(key), "--port", "0",
                             "--control-port", "0", "--config", str(scene), "--ready-file", str(ready),
                             "--stats-file", str(stats), "--duration", "120", "--status-every", "0"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        end = time.monotonic() + 120
        while not ready.exists() and proc.poll() is None and time.monotonic() < end:
            time.sleep(0.05)
        assert ready.exists(), proc.stderr.read().decode()[-2000:] if proc.poll() is not None else "no ready file"
        port = str(json.loads(ready.read_text())["control_port"])

        def ctl_(*a):
            out = subprocess.run([sys.executable, "-m", "pointfence.service.ctl", "--port", port, *a], env=env,
                                 capture_output=True, text=True, timeout=60)
            return out.returncode, (json.loads(out.stdout) if out.returncode == 0 else out.stderr)

        rc, st = ctl_("status")
        assert rc == 0 and st["architecture"] == "III" and st["clients"]["slots"] == 1
        rc, m = ctl_("metrics")
        assert rc == 0 and m["loop"]["ticks"] > 0 and m["clients"]["connected"] == 0
        # a loaded machine may overrun or stall a tick past the watchdog's limit; nothing else holds
        assert set(m["hold"]) <= {"overrun", "tick watchdog"}
        assert ctl_("set-architecture", "I")[1]["architecture"] == "I"
        assert ctl_("radius", "0.015")[1]["fixture"]["radius"] == pytest.approx(0.015)
        rc, err = ctl_("set-architecture", "IV")
        assert rc == 1 and "expected one of I, II, III" in err
        rc, st = ctl_("status")
        assert st["architecture"] == "I" and st["fixture"]["radius"] == pytest.approx(0.015)
    finally:
        proc.terminate()
        proc.wait(30)
    final = json.loads(stats.read_text())
    assert final["control"]["reconfigurations"] == 1 and final["loop"]["ticks"] > 0
