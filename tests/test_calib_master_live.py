"""`pointfence calib master --live` (calib/master_live.py) against a running Service with its
control API (tests/control_rig.py): an operator, played by the prompt hook, moves a master
along each prompted world direction through a known rotation R_world_master; the live capture
reads the master's raw samples from GET /masters (service/control_api.py, published by the tick,
Service.master_sample) and the guided solver recovers R. Also: the endpoint itself, refusals
without or with a wrong token, a master that never moves (NOT TRUSTED, nothing written), one
that never rests or gives no valid sample, and a wrong --arm."""
import argparse
import threading

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pointfence.calib import master_live, master_reg
from pointfence.calib.common import rotation_angle_deg
from pointfence.kernels.errors import InputError
from pointfence.service import config
from pointfence.service.ctl import ControlRefused
from pointfence.service.masters import Master

from control_rig import Running
from service_cases import needs_opencl

R_TRUE = Rotation.from_euler("zyx", [35, -20, 10], degrees=True).as_matrix()   # R_world_master
START = np.array([0.01, 0.02, 0.03])                                          # master frame, m


class OperatorMaster(Master):
    """A master held by a scripted hand: it moves toward ``target`` (master frame, m) at
    ``speed`` m/s of loop time, with ``noise`` m (per axis) of hand tremor on every sample."""

    name = "operator"

    def __init__(self, speed=0.5, noise=1e-4, seed=1):
        super().__init__()
        self.target = START.copy()
        self.position[:] = START
        self.clutch = False            # pedal up: the robot does not follow during calibration
        self.speed, self.noise = speed, noise
        self._at, self._t = START.copy(), None
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()

    def move_to(self, p):
        with self._lock:
            self.target = np.asarray(p, dtype=float).copy()

    def poll(self, t):
        dt = 0.0 if self._t is None else max(t - self._t, 0.0)
        self._t = t
        with self._lock:
            d = self.target - self._at
        n = np.linalg.norm(d)
        self._at = self.target.copy() if n <= self.speed * dt else self._at + d / n * self.speed * dt
        self.position[:] = self._at + self._rng.normal(0.0, self.noise, 3)


def _args(rig, *extra):
    p = argparse.ArgumentParser()
    master_reg.add_arguments(p)
    return p.parse_args(["--live", "--port", str(rig.server.address[1]), *map(str, extra)])


def _follower(master, seed=0, lengths=(0.045, 0.055)):
    """The prompt hook: the operator moves the master about 5 cm along each prompted world
    direction (master frame: R^T e), from wherever it rests."""
    rng = np.random.default_rng(seed)
    prompts = []

    def prompt(direction, text):
        prompts.append((direction, text))
        if direction != "start":
            e = np.asarray(master_reg.DIRECTIONS[direction], dtype=float)
            master.move_to(master.target + rng.uniform(*lengths) * (R_TRUE.T @ e))

    return prompt, prompts


@pytest.fixture
def live(tmp_path):
    m = OperatorMaster()
    r = Running(tmp_path / "rig", master=m)
    yield r, m
    r.close()


@needs_opencl
def test_masters_endpoint_reports_the_raw_sample_and_needs_the_token(live):
    rig, m = live
    rig.wait_ticks(20)
    st, rep = rig.raw("GET", "/masters")
    assert st == 200 and rep["ok"] and rep["loop_running"] is True and rep["loop_error"] is None
    a = rep["masters"][0]
    assert a["arm"] == 0 and a["valid"] is True
    assert np.allclose(a["position"], START, atol=1e-3)       # the master frame, not the world (X_m)
    rig.wait_ticks(2)
    st2, rep2 = rig.raw("GET", "/masters")
    assert rep2["tick"] > rep["tick"] and rep2["t"] > rep["t"]
    assert rig.raw("GET", "/masters", auth=False)[0] == 401
    st, rep = rig.raw("GET", "/masters", auth="Bearer " + "0" * 64)
    assert st == 403 and "wrong control token" in rep["error"]
    m.ok = False                                               # a master without a valid sample
    rig.wait_ticks(5)
    a = rig.client.get("/masters")["masters"][0]
    assert a["valid"] is False and a["position"] is None


@needs_opencl
def test_live_guided_motion_recovers_the_rotation_and_writes_teleop(live, tmp_path, capsys):
    rig, m = live
    scene = tmp_path / "scene.toml"
    scene.write_text((tmp_path / "rig" / "scene.toml").read_text())
    out = tmp_path / "teleop.toml"
    prompt, prompts = _follower(m)
    rc = master_reg.run(_args(rig, "--hold", 0.25, "--step-timeout", 10, "--config", scene, "--out", out),
                        prompt=prompt, say=lambda s: None)
    text = capsys.readouterr().out
    assert rc == 0, text
    assert [d for d, _ in prompts] == ["start", "+x", "-x", "+y", "-y", "+z", "-z"]
    assert all("about 5 cm toward world" in t for d, t in prompts[1:])
    assert "verdict: TRUSTED" in text and "live guided motion, arm 0, 6 steps" in text
    T = np.array(config.load(scene).teleop.T_world_master)
    assert rotation_angle_deg(R_TRUE.T @ T[:3, :3]) < 0.5
    assert np.allclose(T[:3, 3], 0.0) and config.load(scene).teleop.scale == 0.5   # kept as configured
    assert "T_world_master" in out.read_text()


@needs_opencl
def test_a_master_that_never_moves_is_not_trusted_and_nothing_is_written(live, tmp_path, capsys):
    rig, _m = live
    out = tmp_path / "teleop.toml"
    rc = master_reg.run(_args(rig, "--hold", 0.2, "--step-timeout", 0.5, "--out", out),
                        prompt=lambda d, t: None, say=lambda s: None)
    text = capsys.readouterr().out
    assert rc == 3
    assert "verdict: NOT TRUSTED" in text and "step +x not captured: the master did not move" in text
    assert "0 of 6 steps captured" in text and "not written" in text and not out.exists()


@needs_opencl
def test_refused_without_the_right_token_and_for_a_wrong_arm(live, tmp_path):
    rig, _m = live
    bad = tmp_path / "bad.token"
    bad.write_text("ab" * 32 + "\n")
    bad.chmod(0o600)
    with pytest.raises(ControlRefused, match="wrong control token.*not this service's"):
        master_reg.run(_args(rig, "--token-file", bad), prompt=lambda d, t: None, say=lambda s: None)
    with pytest.raises(InputError, match="--arm 2, but the service has 1 master"):
        master_reg.run(_args(rig, "--arm", 2), prompt=lambda d, t: None, say=lambda s: None)


# -- the capture alone, on a simulated clock (no service) ------------------------------------------
class _Feed:
    """GET /masters as ``MasterFeed.read`` gives it: one new tick per read, the position from
    ``fn(t)`` (wall s) or None."""

    def __init__(self, fn, clock):
        self.fn, self.clock, self.k = fn, clock, 0

    def read(self):
        self.k += 1
        p = self.fn(self.clock.t)
        return self.k, self.clock.t, None if p is None else np.asarray(p, float)


class _Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t

    def sleep(self, s):
        self.t += s


def _capture(fn, **kw):
    c = _Clock()
    g = master_live.GuidedCapture(_Feed(fn, c), list(master_reg.DIRECTIONS), clock=c, sleep=c.sleep,
                                  say=lambda s: None, prompt=lambda d, t: None, **kw)
    return g


def test_capture_averages_the_rest_and_names_each_failure():
    rng = np.random.default_rng(3)
    # never still (5 mm tremor): no start position
    with pytest.raises(InputError, match="no start position: the master never held still"):
        _capture(lambda t: START + rng.normal(0, 0.005, 3), step_timeout=2.0).run()
    # no valid sample at all
    with pytest.raises(InputError, match="no start position: the master gave no valid sample"):
        _capture(lambda t: None, step_timeout=2.0).run()
    # the service stopped ticking
    c = _Clock()
    stuck = master_live.GuidedCapture(type("F", (), {"read": lambda self: (7, 0.0, START)})(), ["+x"], clock=c,
                                      sleep=c.sleep, say=lambda s: None, prompt=lambda d, t: None)
    with pytest.raises(InputError, match="published no new tick"):
        stuck.run()
    # the start is the mean of the rest (noise averages out), a step too short is named
    cap = _capture(lambda t: START + rng.normal(0, 2e-4, 3), step_timeout=3.0).run()
    assert np.allclose(cap.steps[0][1], START, atol=1.5e-4) and len(cap.steps) == 1
    assert len(cap.problems) == 6 and all("did not move" in p for p in cap.problems)
    # --enter: pressed before moving far enough
    presses = []
    g = _capture(lambda t: START + [0.01 * (len(presses) > 1), 0, 0], enter=True, wait_enter=presses.append,
                 step_timeout=3.0)
    g.directions = ["+x"]
    cap = g.run()
    assert len(presses) == 2 and len(cap.steps) == 1
    assert "rests 1.0 cm from the previous position" in cap.problems[0]
