"""The Python client SDK against the service's UDP hub (its receiver thread verifies datagrams; a
thread plays the haptic loop's part: poll each slot, then a force per slot), and `device-sim`. No wall-clock assertions: waits are
bounded, outcomes are checked."""
import json
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from pointfence.clients import Client, ClientError, Command, LinkLost, Rejected, TimingError
from pointfence.clients import protocol as P
from pointfence.service.udp_server import UdpHub

KEY = bytes(range(1, 33))


class Pump:
    """Ticks the hub's masters every ~1 ms and sends each live slot a force of -100 x its position."""

    def __init__(self, hub, feedback=True):
        self.hub, self.feedback = hub, feedback
        self.stop = threading.Event()
        self.t = 0.0
        self.th = threading.Thread(target=self.run, daemon=True)
        self.th.start()

    def run(self):
        t0 = time.monotonic()
        while not self.stop.is_set():
            self.t = time.monotonic() - t0
            for m in self.hub.masters:
                m.poll(self.t)
            if self.feedback:
                for m in self.hub.masters:
                    if m.ok:
                        m.send_force(-100.0 * m.position)
            time.sleep(0.001)

    def close(self):
        self.stop.set()
        self.th.join(2)


@pytest.fixture
def hub():
    h = UdpHub(KEY, 2)
    yield h
    h.close()


def wait_for(cond, timeout=5.0):
    end = time.monotonic() + timeout
    while not cond() and time.monotonic() < end:
        time.sleep(0.002)
    return cond()


def test_connect_send_receive_force_and_close(hub):
    pump = Pump(hub)
    try:
        with Client(*hub.address, KEY, 5, model="test") as c:
            w = c.connect(timeout=5)
            assert w.slot == 0 and w.timeout_ms == 50 and c.connected
            for _ in range(200):
                c.send_state((0.01, -0.02, 0.005), clutch=True, orientation=(1, 0, 0, 0), grasp=0.2, buttons=3)
                c.poll()
                if c.feedback is not None and c.feedback.echo_seq >= 3:
                    break
                time.sleep(0.002)
            fb = c.feedback
            assert fb is not None and fb.slot == 0 and fb.error == 0
            assert np.allclose(c.force, [-1.0, 2.0, -0.5])
            assert c.stats.rtt_us and min(c.stats.rtt_us) > 0
            m = hub.masters[0]
            assert m.ok and m.clutch and m.buttons == 3 and m.grasp == pytest.approx(0.2)
        assert wait_for(lambda: not hub.sessions)       # BYE ended the session
        assert hub.sessions_closed == 1
        assert wait_for(lambda: not hub.masters[0].ok)  # ... and the next tick's poll sees no sample
    finally:
        pump.close()


def test_busy_and_full_are_rejected(hub):
    pump = Pump(hub, feedback=False)
    try:
        a, b, c, d = (Client(*hub.address, KEY, i) for i in (1, 2, 3, 1))
        a.connect(timeout=5)
        b.connect(timeout=5)
        keep = Sender([a, b])            # a and b prove their keys and stay live
        try:
            assert wait_for(lambda: len(hub.sessions) == 2 and all(s.proven for s in list(hub.sessions.values())))
            with pytest.raises(Rejected) as e:
                c.connect(timeout=5)
            assert e.value.code == P.E_FULL
            with pytest.raises(Rejected) as e:
                d.connect(timeout=5)
            assert e.value.code == P.E_BUSY
        finally:
            keep.close()
        for x in (a, b, c, d):
            x.close()
    finally:
        pump.close()


class Sender:
    """Keeps clients live: each sends a sample every ~2 ms from a thread of its own."""

    def __init__(self, clients):
        self.clients = clients
        self.stop = threading.Event()
        self.th = threading.Thread(target=self.run, daemon=True)
        self.th.start()

    def run(self):
        while not self.stop.is_set():
            for c in self.clients:
                c.send_state((0.0, 0.0, 0.0))
            time.sleep(0.002)

    def close(self):
        self.stop.set()
        self.th.join(2)


def test_wrong_key_gets_no_answer(hub):
    pump = Pump(hub, feedback=False)
    try:
        c = Client(*hub.address, bytes([7]) * 32, 9)
        with pytest.raises(ClientError, match="no answer"):
            c.connect(timeout=0.3)
        c.close()
        assert hub.counters["auth"] >= 1 and not hub.sessions
    finally:
        pump.close()


def test_callback_api_and_timing_contract(hub):
    pump = Pump(hub)
    try:
        c = Client(*hub.address, KEY, 4)
        c.connect(timeout=5)
        seen = []

        def cb(t):
            seen.append((t.index, t.fresh, t.force.copy()))
            return Command((0.0, 0.0, 0.01), finished=t.index >= 299)

        n = c.control(cb)
        assert n == 300 and [s[0] for s in seen] == list(range(300))
        assert any(s[1] for s in seen)
        assert np.allclose(seen[-1][2], [0, 0, -1.0])

        def slow(t):
            time.sleep(0.004)              # breaks the 1 ms contract on every tick
            return Command((0.0, 0.0, 0.0))

        with pytest.raises(TimingError, match="consecutive ticks overran"):
            c.control(slow, late_limit=3)
        assert not c.force.any()
        with pytest.raises(ClientError, match="late_limit 0"):
            c.control(slow, late_limit=0)

        def boom(t):
            raise KeyError("device unplugged")

        with pytest.raises(KeyError):
            c.control(boom)

        # real-time priority for the loop's duration only (or a clear note where refused)
        policy = os.sched_getscheduler(0)
        policies = []

        def rt(t):
            policies.append(os.sched_getscheduler(0))
            return Command((0.0, 0.0, 0.0), finished=t.index >= 9)

        assert c.control(rt, rt_priority=20) == 10
        if c.scheduling == "SCHED_FIFO 20":
            assert set(policies) == {os.SCHED_FIFO}
        else:
            assert c.scheduling.startswith("normal (SCHED_FIFO refused") and set(policies) == {policy}
        assert os.sched_getscheduler(0) == policy
        with pytest.raises(KeyError):
            c.control(boom, rt_priority=20)
        assert os.sched_getscheduler(0) == policy     # restored after an exception too
        c.close()
    finally:
        pump.close()


def test_link_lost_when_the_service_goes_silent(hub):
    pump = Pump(hub)
    c = Client(*hub.address, KEY, 6)
    c.connect(timeout=5)
    ticks = []

    def cb(t):
        ticks.append(t.fresh)
        if len(ticks) == 100:
            pump.close()                   # the service stops answering
        return Command((0.0, 0.0, 0.0))

    with pytest.raises(LinkLost, match="force zeroed"):
        c.control(cb, duration=10)
    assert not c.force.any() and not c.fresh
    c.close()


def test_client_refuses_forged_and_replayed_feedback(hub):
    pump = Pump(hub)
    try:
        c = Client(*hub.address, KEY, 8)
        c.connect(timeout=5)
        c.send_state((0.01, 0.0, 0.0))
        assert wait_for(lambda: c.poll() is not None or c.feedback is not None)
        s = hub.sessions[c.session]
        forged = P.Feedback(force=(50.0, 0, 0)).encode(bytes(32), 8, c.session, 10**6)
        replay = P.Feedback(force=(50.0, 0, 0)).encode(s.key, 8, c.session, 1)   # seq 1 was used
        for d in (forged, replay):   # from the service's own address: only the tag can tell
            hub.sock.sendto(d, c.sock.getsockname())
        time.sleep(0.01)
        c.poll()
        assert c.stats.rejected_in >= 2 and abs(c.force[0]) < 5.0
        c.close()
    finally:
        pump.close()


def test_device_sim_runs_a_scripted_motion_and_a_trajectory(hub, tmp_path):
    from pointfence.service.masters import write_trajectory

    key = tmp_path / "k"
    key.write_text(KEY.hex() + "\n")
    key.chmod(0o600)
    traj = tmp_path / "t.csv"
    write_trajectory(traj, [0.0, 0.2], [[0, 0, 0], [0, 0, -0.01]], [1, 1])
    pump = Pump(hub)
    try:
        # (its own process, as a device is: its 1 kHz loop busy-waits, and in this process it
        # would hold the interpreter lock from the hub's receiver and the ticks it talks to)
        for extra in (["--motion", "circle", "--duration", "0.3"], ["--trajectory", str(traj)]):
            r = subprocess.run([sys.executable, "-m", "pointfence.cli", "device-sim", "--key-file", str(key), "--port",
                                str(hub.address[1]), *extra], capture_output=True, text=True, timeout=120)
            assert r.returncode == 0, r.stderr[-2000:]
            out = json.loads(r.stdout.strip().splitlines()[-1])
            assert out["ticks"] > 100 and out["feedback_received"] > 0 and out["states_answered"] > 0
        assert out["last_robot"] is not None
    finally:
        pump.close()


def test_deadline_grid_estimate_recovers_from_a_tick_off_the_timeline(monkeypatch):
    """The hub stamps feedback with its tick's deadline (origin of the grid + loop time). A
    tick outside the loop's timeline (the service's start-up poll at loop time 0, tens of ms
    before the first tick) must not shift that origin for good: it is a windowed minimum."""
    from pointfence.service import udp_server as U

    clock = {"ns": 1_000_000_000}
    monkeypatch.setattr(U.time, "perf_counter_ns", lambda: clock["ns"])
    h = UdpHub(KEY, 1, receiver=False)
    try:
        h.tick(0.0)                       # start-up poll, 32 ms before the loop's t0
        t0 = clock["ns"] + 32_000_000
        assert h._base_ns == clock["ns"]
        for k in range(1, 2 * U.BASE_WINDOW + 2):
            clock["ns"] = t0 + k * 1_000_000 + 3_000 + (k % 7) * 1_000   # ticks 3-9 us late
            h.tick(k * 0.001)
        assert h._base_ns == t0 + 3_000
    finally:
        h.close()


def test_device_sim_plays_a_trajectory_as_the_service_does(tmp_path):
    """clients.trajectory (device-sim) and service.masters.ScriptedMaster interpolate one CSV alike."""
    from pointfence.clients.trajectory import Trajectory, write_trajectory
    from pointfence.service.masters import ScriptedMaster

    path = tmp_path / "t.csv"
    write_trajectory(path, [0.5, 0.7, 1.0, 1.6], [[0, 0, 0], [0.01, 0, -0.02], [0.01, 0.03, -0.02], [0, 0, 0.01]],
                     [1, 0, 1, 1])
    tr, m = Trajectory.from_csv(path), ScriptedMaster.from_csv(path)
    assert tr.duration == pytest.approx(m.duration)
    for t in np.linspace(-0.2, 1.5, 58):
        m.poll(0.5 + t)
        pos, clutch = tr.at(t)
        np.testing.assert_allclose(pos, m.position, atol=1e-15)
        assert clutch == m.clutch
