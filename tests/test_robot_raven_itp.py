"""pointfence as a Raven II's ITP master console (robot/raven_itp.py), against a receiver that reads
its packets the way the Raven II control software does (github.com/uw-biorobotics/raven2):
network_layer.cpp's size and sequence rules and UDPChecksum, local_io.cpp's teleopIntoDS1
integration, mapping.cpp's fromITP frames. The receiver's layout and rules are written here from
the C source, independently of the module's own packing."""
from __future__ import annotations

import logging
import math
import socket
import struct
import threading
import time

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service.robot.base import RobotMode
from pointfence.service.robot.factory import robot_from_config
from pointfence.service.robot.raven_itp import RavenItpRobot

# itp_teleoperation.h, u_struct (packed): 3 unsigned int, int delx[2], dely[2], delz[2], double Qx[2], Qy[2],
# Qz[2], Qw[2], int buttonstate[2], grasp[2], surgeon_mode, checksum
U = struct.Struct("<III" + "ii" * 3 + "dd" * 4 + "ii" * 2 + "ii")
V = struct.Struct("<IIII" + "ii" * 3 + "iIi")       # v_struct
# mapping.cpp fromITP, without ORIENTATION_V
ITP2GOLD = np.array([[0, 0, -1], [-1, 0, 0], [0, 1, 0]], dtype=float)
ITP2GREEN = np.array([[0, 0, -1], [1, 0, 0], [0, -1, 0]], dtype=float)


def c_int(x):
    x &= 0xFFFFFFFF
    return x - (1 << 32) if x >= (1 << 31) else x


def quat_mat(x, y, z, w):
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def rot(axis, a):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K


class RavenReceiver:
    """A Raven II's network layer and teleopIntoDS1 for one arm (UDP on 127.0.0.1, a thread)."""

    def __init__(self, arm="right", start_seq=0, pos0=(0, 0, 0), R0=None):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        # room for every packet of a test (2,000 at 1 kHz) while a loaded machine keeps this
        # thread off the CPU: the kernel drops datagrams a full buffer cannot take
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.slot = 1 if arm == "right" else 0
        self.M = ITP2GREEN if arm == "right" else ITP2GOLD
        self.seq = start_seq
        self.xd = np.array(pos0, dtype=np.int64)        # um, base frame (data1.xd)
        self.R = np.eye(3) if R0 is None else np.array(R0)
        self.grasp = 0
        self.counts = {"valid": 0, "reflect": 0, "skipped": 0, "duplicate": 0, "reset": 0, "out_of_seq": 0,
                       "size": 0, "checksum": 0, "malformed": 0}
        self.problems = []        # every field that is not what the Raven expects
        self.log = []             # (sequence, surgeon_mode, xd, R, grasp) after each valid packet
        self.received = 0
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except socket.timeout:
                continue
            except OSError:
                return
            self.handle(data)
            self.received += 1        # (after: a waiter that sees the count sees the packet's effects)

    def handle(self, data):
        c = self.counts
        if len(data) != U.size:                             # network_layer.cpp: bytesread != uSize
            c["size"] += 1
            return
        u = U.unpack(data)
        seq, pactyp, version = u[0], u[1], u[2]
        delx, dely, delz = u[3:5], u[5:7], u[7:9]
        Qx, Qy, Qz, Qw = u[9:11], u[11:13], u[13:15], u[15:17]
        buttons, grasp, mode, checksum = u[17:19], u[19:21], u[21], u[22]
        chk = c_int(mode + delx[0] + dely[0] + delz[0] + delx[1] + dely[1] + delz[1] + buttons[0] + buttons[1]
                    + c_int(seq))                          # UDPChecksum
        if chk != checksum:
            c["checksum"] += 1
            self.problems.append(f"{seq}: checksum {checksum} != UDPChecksum {chk}")
        bad = []
        if mode not in (0, 1):
            bad.append(f"surgeon_mode {mode}")
        for a in (0, 1):
            n = math.sqrt(Qx[a] ** 2 + Qy[a] ** 2 + Qz[a] ** 2 + Qw[a] ** 2)
            if not abs(n - 1) < 1e-9:
                bad.append(f"quaternion {a} norm {n}")
        o = 1 - self.slot
        if (delx[o], dely[o], delz[o], grasp[o], Qx[o], Qy[o], Qz[o], Qw[o]) != (0, 0, 0, 0, 0.0, 0.0, 0.0, 1.0):
            bad.append("the other arm's slot moves it")
        if mode == 0 and (delx[self.slot], dely[self.slot], delz[self.slot], grasp[self.slot]) != (0, 0, 0, 0):
            bad.append("increments with surgeon mode off")
        if (pactyp, version, buttons) != (0, 0, (0, 0)):
            bad.append("pactyp/version/buttons")
        if bad:
            c["malformed"] += 1
            self.problems.append(f"{seq}: " + ", ".join(bad))
        # network_layer.cpp's sequence rules (unsigned int arithmetic)
        s = self.seq
        if seq == 0:
            c["reflect"] += 1
        elif seq > ((s + 1) & 0xFFFFFFFF):
            c["skipped"] += 1
            self.seq = seq
        elif seq == s:
            c["duplicate"] += 1
        elif seq > s:
            self.seq = seq
            c["valid"] += 1
            self.teleop(u)
        elif s > 1000 and seq < s - 1000:
            c["reset"] += 1
            self.seq = seq
        else:
            c["out_of_seq"] += 1

    def teleop(self, u):
        """local_io.cpp teleopIntoDS1 + mapping.cpp fromITP (pedal up re-seats nothing here: the
        master sends no increments then, which the checks above hold it to)."""
        a = self.slot
        d = np.array([u[3 + a], u[5 + a], u[7 + a]], dtype=float)
        q = (u[9 + a], u[11 + a], u[13 + a], u[15 + a])
        M = self.M
        p = M @ d                                          # incr = ITP2arm * incr * ITP2arm^-1
        self.xd += np.trunc(p).astype(np.int64)            # (int) casts
        self.R = (M @ quat_mat(*q) @ M.T) @ self.R          # Q_ori = q_temp * Q_ori
        self.grasp = min(max(self.grasp - u[19 + a], -174), 1570)
        self.log.append((u[0], u[21], self.xd.copy(), self.R.copy(), self.grasp))

    def wait(self, n, timeout=15.0):
        end = time.monotonic() + timeout
        while self.received < n and time.monotonic() < end:
            time.sleep(0.002)
        return self.received

    def close(self):
        self._stop.set()
        self.thread.join(1)
        self.sock.close()


class FakeRaven:
    """The Raven's v_struct feedback (a Raven built with NET_SEND), every ``period`` s, to ``port``."""

    def __init__(self, port, receiver=None, period=0.001, runlevel=3):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port, self.receiver, self.period, self.runlevel = port, receiver, period, runlevel
        self.seq = 0
        self.paused = threading.Event()
        self._lock = threading.Lock()     # a send in progress ends before pause() returns
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def send(self, data):
        self.sock.sendto(data, ("127.0.0.1", self.port))

    def pause(self):
        """Stops sending; no packet leaves after this returns (one being sent has left)."""
        with self._lock:
            self.paused.set()

    def resume(self, seq_jump=0):
        """Sends again, the sequence ``seq_jump`` further on."""
        with self._lock:
            self.seq += seq_jump
            self.paused.clear()

    def _run(self):
        while not self._stop.wait(self.period):
            with self._lock:
                if self.paused.is_set():
                    continue
                self.seq += 1
                last = self.receiver.seq if self.receiver is not None else 0
                self.send(V.pack(self.seq, last, 0, 0, 0, 0, 0, 0, 0, 0, self.runlevel, 0, 0))

    def close(self):
        self._stop.set()
        self.thread.join(1)
        self.sock.close()


def make(port, **kw):
    kw.setdefault("sync_packets", 3)
    return RavenItpRobot(address=f"127.0.0.1:{port}", **kw)


def world_pose(T_wb, p_um, R, p0=(0.0, 0.0, 0.0)):
    """The world pose of the Raven's integrated command: ``p0`` (m, base) + ``p_um`` (um), ``R``."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(p0, float) + np.asarray(p_um, float) * 1e-6
    return T_wb @ T


@pytest.fixture
def rx():
    r = RavenReceiver()
    yield r
    r.close()


def test_tracks_commanded_poses_2s_at_1khz_every_field_accepted():
    """2,000 packets at 1 kHz (a moving, turning pose and the jaw): every packet the Raven's rules
    accept (sequence consecutive, checksum, fields), and the pose the Raven integrates tracks every
    commanded pose within 1 um and 1e-9 rad. The left arm (slot 0) and a rotated mount."""
    rx = RavenReceiver(arm="left")
    T_wb = np.eye(4)
    T_wb[:3, :3] = rot([1, 1, 0], 0.7)
    T_wb[:3, 3] = [0.1, -0.05, 0.3]
    x0 = np.array([0.12, -0.03, 0.25])
    r = make(rx.port, arm="left", T_world_base=T_wb, x0=x0, workspace_min=[-1, -1, -1], workspace_max=[1, 1, 1])
    try:
        assert r.measured_source == "commanded, no feedback"
        assert rx.wait(3) == 3                                 # (the sync packets counted before we count)
        p_b0 = (np.linalg.inv(T_wb) @ np.append(x0, 1))[:3]
        rx.xd[:] = 0                                           # the Raven's pose at engage: p_b0 (base)
        rx.R = np.eye(3)
        start_valid = rx.counts["valid"]
        r.resume()                                             # the master couples
        n, period = 2000, 1e-3
        wanted = []
        t0 = time.perf_counter()
        for k in range(n):
            s = (k + 1) * period
            T = np.eye(4)
            T[:3, :3] = rot([0.3, -0.2, 1.0], 0.4 * math.sin(2 * math.pi * s)) @ T_wb[:3, :3]   # from the start
            T[:3, 3] = x0 + 0.02 * np.array([math.sin(2 * math.pi * s), 1 - math.cos(2 * math.pi * s), 0.3 * s])
            assert r.servo_cp(T)
            r.servo_jaw(0.3 + 0.2 * math.sin(3 * s))
            r.step(period)
            wanted.append(T)
            wait = t0 + (k + 1) * period - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
        assert rx.wait(3 + n) == 3 + n
        assert rx.problems == [] and rx.counts["malformed"] == 0 and rx.counts["checksum"] == 0
        assert rx.counts["valid"] - start_valid == n
        assert {k: v for k, v in rx.counts.items() if k != "valid"} == dict.fromkeys(
            ["reflect", "skipped", "duplicate", "reset", "out_of_seq", "size", "checksum", "malformed"], 0)
        log = rx.log[-n:]
        assert [e[0] for e in log] == list(range(4, 4 + n))    # consecutive after the 3 sync packets
        assert all(e[1] == 1 for e in log)
        pos_err = max(np.linalg.norm(world_pose(T_wb, e[2], e[3], p_b0)[:3, 3] - T[:3, 3]) for e, T in zip(log, wanted))
        rot_err = max(np.abs(world_pose(T_wb, e[2], e[3], p_b0)[:3, :3] - T[:3, :3]).max() for e, T in zip(log, wanted))
        assert pos_err < 1e-6 and rot_err < 1e-9
        assert log[-1][4] == round(1000 * (0.3 + 0.2 * math.sin(3 * n * period)))   # the grasp (mrad)
        np.testing.assert_allclose(r.measured_cp(), world_pose(T_wb, log[-1][2], log[-1][3], p_b0), atol=1e-12)
    finally:
        r.close()
        rx.close()


def _last(rx, n):
    rx.wait(n)
    return rx.log[-1]


def test_hold_fault_and_refused_commands_turn_surgeon_mode_off_in_the_next_packet(rx):
    r = make(rx.port, workspace_min=[-0.1] * 3, workspace_max=[0.1] * 3)
    try:
        r.resume()
        target = r.measured_cp()
        sent = 3

        def move(dx):
            nonlocal sent
            target[0, 3] += dx
            r.servo_cp(target)
            r.step()
            sent += 1
            return _last(rx, sent)

        assert move(1e-4)[1] == 1
        for action in (r.hold, lambda: r.fault("e-stop"),
                       lambda: pytest.raises(InputError, r.servo_cp, [math.nan, 0, 0]),
                       lambda: pytest.raises(InputError, r.servo_cp, [5.0, 0, 0]),
                       lambda: pytest.raises(InputError, r.servo_jaw, 3.0)):
            before = rx.xd.copy()
            action()
            for _ in range(3):                                 # off from the next packet, and stays off
                e = move(2e-4)
                assert e[1] == 0 and np.array_equal(e[2], before)
            assert r.state is not RobotMode.ENABLED
            r.enable()                                         # re-engage: no jump, increments restart
            r.step()
            sent += 1
            e = _last(rx, sent)
            assert e[1] == 1 and np.array_equal(e[2], before)
            target = r.measured_cp()
            e = move(1e-4)
            assert e[1] == 1 and (e[2] - before).tolist() == [100, 0, 0]   # base = world here
        assert rx.problems == []
    finally:
        r.close()


def test_a_socket_error_faults_and_surgeon_mode_goes_off(rx):
    r = make(rx.port)
    real = r.sock

    class Failing:
        fail = False

        def sendto(self, data, addr):
            if self.fail:
                raise OSError(101, "Network is unreachable")
            return real.sendto(data, addr)

        def __getattr__(self, name):
            return getattr(real, name)

    f = Failing()
    r.sock = f
    try:
        r.resume()
        r.servo_cp(r.measured_cp()[:3, 3] + [1e-4, 0, 0])
        r.step()
        assert _last(rx, 4)[1] == 1
        f.fail = True
        r.servo_cp(r.measured_cp()[:3, 3] + [1e-4, 0, 0])
        r.step()
        assert r.state is RobotMode.FAULT and "Network is unreachable" in r.fault_reason
        f.fail = False
        before = rx.xd.copy()
        r.step()                                               # 6: the Raven drops it (a gap: "skipped")
        r.step()                                               # 7: taken, surgeon mode off
        e = _last(rx, 6)
        assert rx.counts["skipped"] == 1 and e[0] == 7 and e[1] == 0
        assert np.array_equal(e[2], before)
        # the failed packet's increment was not integrated: the arm's pose is the Raven's
        np.testing.assert_allclose(r.measured_cp()[:3, 3], [100e-6, 0, 0], atol=1e-12)
    finally:
        r.sock = real
        r.close()


def test_a_send_the_kernel_refuses_faults_at_start():
    r = RavenItpRobot(address="255.255.255.255:36000", sync_packets=1)   # broadcast without SO_BROADCAST
    try:
        assert r.state is RobotMode.FAULT and "ITP send to 255.255.255.255:36000 failed" in r.fault_reason
        assert r.exposed
    finally:
        r.close()


def test_feedback_corrupt_silent_or_estop_faults_the_arm(rx):
    port = _free_port()
    fake = FakeRaven(port, rx)
    r = make(rx.port, feedback_port=port, feedback_timeout_s=0.05, connect_timeout_s=2.0)
    try:
        assert r.state is RobotMode.HOLDING and r.feedback is not None
        r.resume()
        assert _steps_until(r, lambda: rx.log and rx.log[-1][1] == 1)
        for breaker in (lambda: fake.send(b"\0" * 51),
                        lambda: fake.send(V.pack(10 ** 6, 0, 0, 0, 0, 0, 0, 0, 0, 0, 7, 0, 0)),
                        lambda: fake.send(V.pack(10 ** 6 + 1, rx.seq + 50, 0, 0, 0, 0, 0, 0, 0, 0, 3, 0, 0))):
            fake.pause()
            time.sleep(0.01)
            breaker()
            time.sleep(0.005)
            r.step()
            assert r.state is RobotMode.FAULT and "corrupt feedback" in r.fault_reason
            r.step()
            assert _last(rx, r.sent)[1] == 0
            fake.resume(seq_jump=2 * 10 ** 6)
            assert _steps_until(r, lambda: (r.enable(), r.state is RobotMode.ENABLED)[1])
        # silence beyond the timeout (measured from the step that took the last packet sent)
        fake.pause()
        r.step()
        time.sleep(0.08)
        r.step()
        assert r.state is RobotMode.FAULT and "no feedback from the Raven for" in r.fault_reason
        r.enable()
        assert r.state is RobotMode.FAULT and r.last_error.startswith("enable refused: no feedback")
        # E-STOP
        fake.runlevel = 0
        fake.resume()
        assert _steps_until(r, lambda: r.feedback[7] == 0)
        r.enable()
        assert r.state is RobotMode.FAULT and "runlevel 0 (E-STOP)" in r.last_error
        fake.runlevel = 2
        assert _steps_until(r, lambda: (r.enable(), r.state is RobotMode.ENABLED)[1])
        assert rx.problems == []
    finally:
        r.close()
        fake.close()


def test_no_feedback_at_start_faults_saying_so(rx):
    r = make(rx.port, feedback_port=_free_port(), connect_timeout_s=0.1)
    try:
        assert r.state is RobotMode.FAULT and "no feedback from the Raven on port" in r.fault_reason
        assert "NET_SEND" in r.fault_reason
    finally:
        r.close()


def test_default_sync_makes_the_raven_take_our_sequence_whatever_it_last_saw():
    """The Raven last saw packet 700 from an earlier master: after the 1001 sync packets, the
    first engaged packet is valid (network_layer.cpp would drop it as out of sequence otherwise)."""
    rx = RavenReceiver(start_seq=700)
    r = RavenItpRobot(address=f"127.0.0.1:{rx.port}")
    try:
        r.resume()
        r.servo_cp(r.measured_cp()[:3, 3] + [1e-4, 0, 0])
        r.step()
        assert rx.wait(1002) == 1002
        assert rx.log[-1][0] == 1002 and rx.log[-1][1] == 1 and rx.counts["valid"] >= 1
        assert rx.xd.tolist() == [100, 0, 0]
    finally:
        r.close()
        rx.close()


def test_sequence_wrap_sends_the_dropped_packet_empty(rx):
    r = make(rx.port)
    try:
        r.resume()
        assert rx.wait(r.sync_packets) == r.sync_packets   # (the sync packets handled before we move the sequence)
        r.sequence = rx.seq = 0xFFFFFFFE
        p0 = r.measured_cp()[:3, 3]
        for k in range(3):
            r.servo_cp(p0 + [1e-4 * (k + 1), 0, 0])
            r.step()
        rx.wait(6)
        assert [e[0] for e in rx.log[-2:]] == [0xFFFFFFFF, 2]   # packet 1 is the Raven's "skipped" branch
        assert rx.counts["skipped"] == 1 and rx.xd.tolist() == [300, 0, 0]   # no increment lost
    finally:
        r.close()


@pytest.mark.parametrize("address, said", [("10.0.0.1", "has no port"), ("10.0.0.1:abc", "is not a number"),
                                           ("10.0.0.1:70000", "outside 1..65535"), ("", "expected the Raven"),
                                           ("no.such.host.invalid:36000", "does not resolve")])
def test_bad_address_is_a_clear_error(address, said):
    with pytest.raises(InputError, match=said):
        robot_from_config({"model": "raven2-itp", "address": address})


def test_bad_options_are_clear_errors():
    with pytest.raises(InputError, match="arm = 'middle'"):
        robot_from_config({"model": "raven2-itp", "address": "127.0.0.1:1", "arm": "middle"})
    with pytest.raises(InputError, match="did you mean 'feedback_port'"):
        robot_from_config({"model": "raven2-itp", "address": "127.0.0.1:1", "feedback_prot": 3})
    with pytest.raises(InputError, match="feedback_timeout_s"):
        robot_from_config({"model": "raven2-itp", "address": "127.0.0.1:1", "feedback_timeout_s": 2.0})
    with pytest.raises(InputError, match=r"\[robot.tool\] with model = 'raven2-itp'"):
        robot_from_config({"model": "raven2-itp", "address": "127.0.0.1:1", "tool": {"shaft_radius": 0.004}})
    with pytest.raises(InputError, match="servo_jp is not sent"):
        RavenItpRobot(address="127.0.0.1:1", connect=False).servo_jp([0.0])


def test_a_non_loopback_raven_warns_that_itp_is_unauthenticated(caplog):
    with caplog.at_level(logging.WARNING, logger="pointfence.robot.raven_itp"):
        r = RavenItpRobot(address="192.0.2.1:36000", sync_packets=0)
    try:
        assert r.exposed and "UNAUTHENTICATED" in caplog.text
    finally:
        r.close()


def test_connect_false_opens_nothing_and_checks_commands():
    r = robot_from_config({"model": "raven2-itp", "address": "127.0.0.1:36000", "workspace_min": [-0.1] * 3,
                           "workspace_max": [0.1] * 3}, connect=False)
    assert not r.connected and r.state is RobotMode.HOLDING
    r.resume()
    assert r.servo_cp([0.05, 0, 0])
    with pytest.raises(InputError, match="outside the workspace"):
        r.servo_cp([0.5, 0, 0])
    assert r.state is RobotMode.HOLDING                       # a refused command holds the arm


def _free_port():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    p = s.getsockname()[1]
    s.close()
    return p


def _steps_until(r, cond, timeout=2.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        r.step()
        if cond():
            return True
        time.sleep(0.001)
    return False
