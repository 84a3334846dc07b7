"""The UDP hub's receiver under overload (issue 18): a backlog that waited in the socket while
the receiver was starved is never handed to the tick in order, a sample older than the session
timeout is not used (the arm holds, S9), and a forged flood does not make the genuine device's
samples old; the same for the ITP adapter where it applies (its packets carry increments: all
are integrated, but a stale sample holds the arm). Loopback only; the one threaded test bounds
ages, not speeds."""
import socket
import subprocess
import sys
import threading
import time

from pointfence.clients import Client
from pointfence.clients import protocol as P
from pointfence.service import rx_stamps
from pointfence.service.age_hist import AgeHistogram
from pointfence.service.itp import ItpReceiver, pack_itp
from pointfence.service.udp_server import UdpHub

from test_protocol_attacks import FLOODER

KEY = bytes(range(3, 35))
DEV = 9


def connected(hub, timeout_ms):
    """A client with an open session on a pumped hub (no receiver thread)."""
    c = Client(*hub.address, KEY, DEV, timeout_ms=timeout_ms)
    c.hello_send()
    hub.pump()                               # HELLO -> COOKIE
    assert c.hello_wait(0.0) is None         # COOKIE -> HELLO with the cookie
    hub.pump()                               # -> WELCOME
    assert c.hello_wait(2.0) is not None
    return c


def test_a_backlog_queued_while_the_receiver_was_paused_gives_the_tick_only_its_newest_sample():
    """100 states wait in the socket (the receiver paused), with a forgery numbered above them:
    one drain accepts the newest authentic one only (the forgery fails its tag; the 99 older
    ones are checked after it and superseded: never used, no error against the session). Before:
    all 100 were accepted one after the other, each in turn the sample a tick would read."""
    hub = UdpHub(KEY, 1, receiver=False, timeout_ms=1000)
    try:
        c = connected(hub, 1000)
        for k in range(1, 101):
            c.send_state((0.0005 * k, 0.0, 0.0))
        s = hub.sessions[c.session]
        forged = P.State(1, 0, (0.09, 0.09, 0.09)).encode(bytes(32), DEV, c.session, c.seq + 7)
        c.sock.send(forged)
        hub.pump()
        m = hub.masters[s.slot]
        m.poll(1.0)
        assert m.ok and m.position[0] == 0.05 and s.seq == 100
        assert s.accepted == 1 and hub.superseded == 99
        assert hub.counters["auth"] == 1 and s.rejected == 1
        st = hub.status()
        assert st["superseded"] == 99 and st["rejected_total"] == 1
        c.send_state((0.001, 0.0, 0.0))      # the next sample is used at once
        hub.pump()
        m.poll(1.001)
        assert m.ok and m.position[0] == 0.001 and s.accepted == 2
        c.close()
    finally:
        hub.close()


def test_a_sample_older_than_the_timeout_holds_the_arm_and_a_fresh_one_resumes():
    """A sample that waited 350 ms in the socket (timeout 200 ms) is not used: the master reports
    ok = False (the service holds that arm), the session stays open, and the next fresh sample
    is used. Before: the tick used it as if it were new."""
    hub = UdpHub(KEY, 1, receiver=False, timeout_ms=200)
    try:
        c = connected(hub, 200)
        c.send_state((0.01, 0.0, 0.0))
        hub.pump()
        m = hub.masters[0]
        m.poll(1.0)
        assert m.ok and m.position[0] == 0.01
        c.send_state((0.02, 0.0, 0.0))
        time.sleep(0.35)                     # the receiver starved: the datagram waits in the socket
        hub.pump()
        m.poll(1.001)
        assert not m.ok and c.session in hub.sessions
        st = hub.status()
        assert st["stale_ticks"] == 1 and st["state_age_ms"]["max_ms"] >= 350
        c.send_state((0.03, 0.0, 0.0))
        hub.pump()
        m.poll(1.002)
        assert m.ok and m.position[0] == 0.03
        c.close()
    finally:
        hub.close()


def test_a_forged_flood_on_a_starved_receiver_never_makes_the_genuine_sample_old(monkeypatch):
    """The hub's Python is slowed to >= 50 us a datagram (a starved CPU: it handles fewer than
    the ~20,000 forged datagrams/s one source floods) while the genuine device sends at 1 kHz:
    every sample a tick uses was sent less than the timeout (100 ms) before it. Before: the
    socket's 4 MiB buffer queued seconds of flood and the ticks used samples seconds old."""
    hub = UdpHub(KEY, 1, timeout_ms=100)
    real_handle = hub.handle

    def slow_handle(data, addr, rx_ns=None):
        end = time.perf_counter() + 50e-6
        while time.perf_counter() < end:
            pass
        return real_handle(data, addr, rx_ns)

    monkeypatch.setattr(hub, "handle", slow_handle)
    stop = threading.Event()
    ages, ticks = [], [0, 0]
    proc = None

    def device(c):
        k = 0
        while not stop.is_set():
            k += 1
            c.send_state((0.01 * ((k % 100) / 100.0), 0.0, 0.0))
            time.sleep(0.001)

    def tick():
        m, t0 = hub.masters[0], time.monotonic()
        while not stop.is_set():
            m.poll(time.monotonic() - t0)
            ticks[0] += 1
            if m.ok:
                ticks[1] += 1
                ages.append(hub.t_ns - m.session.t_client_ns)
            time.sleep(0.001)

    try:
        c = Client(*hub.address, KEY, DEV, timeout_ms=1000)
        c.connect(timeout=10)
        threads = [threading.Thread(target=device, args=(c,), daemon=True)]
        threads[0].start()
        time.sleep(0.2)
        threads.append(threading.Thread(target=tick, daemon=True))
        threads[1].start()
        forged = P.State(1, 0, (0.09, 0.09, 0.09)).encode(bytes([9]) * 32, DEV, c.session, 10**9)
        proc = subprocess.Popen([sys.executable, "-c", FLOODER, hub.address[0], str(hub.address[1]), "60000"],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        proc.stdin.write(forged.hex() + "\n")
        proc.stdin.close()
        proc.wait(timeout=120)
        stop.set()
        for th in threads:
            th.join(2)
        assert int(proc.stdout.read().strip() or 0) == 60000
        # the genuine device got through (its share of a queue the starved receiver cannot drain is
        # the kernel's: in proportion to its share of the traffic) ...
        assert ticks[0] > 100 and ticks[1] > 0 and hub.accepted > 10, (ticks, hub.status())
        # ... and no tick used a sample sent longer ago than the timeout (and the send's own delay)
        assert max(ages) <= 120e6, (max(ages) / 1e6, hub.status())
        c.close()
    finally:
        stop.set()
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        hub.close()


_SENDER = """
import socket, sys, time
from pointfence.clients import protocol as P
fd, key, dev, sid, seq0, n = int(sys.argv[1]), bytes.fromhex(sys.argv[2]), *map(int, sys.argv[3:7])
sock = socket.socket(fileno=fd)
print("ready", flush=True)
sys.stdin.readline()
for k in range(1, n + 1):
    sock.send(P.State(time.perf_counter_ns(), 0, (0.0001 * k, 0.0, 0.0)).encode(key, dev, sid, seq0 + k))
    time.sleep(0.001)
"""


def test_a_device_s_samples_reach_the_tick_while_the_interpreter_is_held():
    """The receiver applies STATEs without the interpreter lock: while this process's interpreter
    is held for 400 ms (a flood, a control request, a long Python call elsewhere), a device that
    sends 200 samples from another process has them accepted as they arrive, and the tick then
    reads the newest. Before, the receiver waited for the lock: nothing was accepted during the
    hold, and the backlog gave one sample afterwards."""
    import ctypes
    import ctypes.util

    hub = UdpHub(KEY, 1, timeout_ms=1000)
    held = ctypes.PyDLL(ctypes.util.find_library("c") or "libc.so.6").usleep     # keeps the lock while it sleeps
    try:
        c = Client(*hub.address, KEY, DEV, timeout_ms=1000)
        c.connect()
        s = hub.sessions[c.session]
        proc = subprocess.Popen([sys.executable, "-c", _SENDER, str(c.sock.fileno()), c.key.hex(), str(DEV),
                                 str(c.session), str(c.seq), "200"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                pass_fds=[c.sock.fileno()])
        assert proc.stdout.readline().strip() == b"ready"       # (its imports done: it sends at once)
        before = hub.accepted
        proc.stdin.write(b"go\n")
        proc.stdin.flush()
        held(400_000)
        during = hub.accepted - before
        assert proc.wait(30) == 0
        time.sleep(0.05)
        m = hub.masters[s.slot]
        m.poll(1.0)
        assert during >= 50, f"{during} samples accepted while the interpreter was held"
        assert m.ok and abs(m.position[0] - 0.02) < 1e-12 and s.seq == c.seq + 200
        assert s.rejected == 0 and hub.status()["queue_dropped"] == 0
    finally:
        hub.close()


def test_max_age_has_a_ceiling_and_bounds_the_sample_age():
    import pytest
    from pointfence.kernels.errors import InputError

    with pytest.raises(InputError, match="max_age_ms = 5000; expected 1..1000"):
        UdpHub(KEY, 1, receiver=False, max_age_ms=5000)
    hub = UdpHub(KEY, 1, receiver=False, timeout_ms=1000, max_age_ms=100)
    try:
        c = connected(hub, 1000)
        c.send_state((0.01, 0.0, 0.0))
        time.sleep(0.2)
        hub.pump()
        m = hub.masters[0]
        m.poll(1.0)
        assert not m.ok and hub.stale_ticks == 1
        c.close()
    finally:
        hub.close()


def test_the_receive_buffer_holds_tens_of_milliseconds_and_arrivals_are_kernel_stamped():
    """The hub's socket asks for RCVBUF_BYTES (before: 4 MiB, seconds of flood); each datagram
    carries the time it reached the socket, not the time it was read."""
    hub = UdpHub(KEY, 1, receiver=False)
    try:
        assert hub.status()["rcvbuf_bytes"] <= 4 * rx_stamps.RCVBUF_BYTES
        if hub.stamps:
            tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            t0 = time.perf_counter_ns()
            tx.sendto(b"x", hub.address)
            time.sleep(0.05)
            assert hub.rx.poll(10) == 1
            n, addr, rx_ns = hub.rx.next(bytearray(64), 0)
            assert n == 1 and addr[1] == tx.getsockname()[1] and t0 <= rx_ns < t0 + 40_000_000
            tx.close()
    finally:
        hub.close()


def test_age_histogram_quantiles_never_understate():
    h = AgeHistogram()
    for us in range(1, 1001):
        h.record(us * 1000)
    s = h.summary()
    assert s["n"] == 1000 and s["max_ms"] == 1.0
    assert 0.5 <= s["p50_ms"] <= 0.5 * 1.1 and 0.99 <= s["p99_ms"] <= 1.0
    before = h.counts()
    h.record(5_000_000)
    part = h.summary([b - a for a, b in zip(before, h.counts())])
    assert part["n"] == 1 and 5.0 <= part["p99_ms"] <= 5.0 * 1.1


# --- the ITP adapter (service/itp.py) -------------------------------------------------------------
Q = [[0, 0, 0, 1], [0, 0, 0, 1]]


def test_itp_backlog_is_integrated_but_a_stale_one_holds_the_arm_until_fresh():
    """ITP packets carry increments, so a backlog is worked through in order (nothing skipped:
    the position is their sum); but when its newest packet waited longer than the timeout in the
    socket, the arm reports ok = False (holds, S9) until a fresh packet comes. Before: the tick
    followed the backlog as if it were new."""
    r = ItpReceiver("127.0.0.1", 0, timeout_ms=200, receiver=False)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        arm = r.arm_master(0)
        for seq in range(1, 51):
            tx.sendto(pack_itp(seq, [[10, 0, 0], [0, 0, 0]], Q), r.address)
        time.sleep(0.35)                     # the receiver starved: the packets wait in the socket
        assert r.pump() == 50
        arm.poll(1.0)
        assert not arm.ok and abs(arm.position[0] - 50 * 10e-6) < 1e-12
        st = r.status()
        assert st["stale_ticks"] == 1 and st["state_age_ms"]["max_ms"] >= 350
        tx.sendto(pack_itp(51, [[10, 0, 0], [0, 0, 0]], Q), r.address)
        r.pump()
        arm.poll(1.001)
        assert arm.ok and abs(arm.position[0] - 51 * 10e-6) < 1e-12
    finally:
        tx.close()
        r.close()


def test_itp_receive_buffer_holds_tens_of_milliseconds():
    r = ItpReceiver("127.0.0.1", 0, receiver=False)
    try:
        assert r.reader.rcvbuf <= 4 * rx_stamps.RCVBUF_BYTES      # before: 1 MiB (2 MiB granted)
    finally:
        r.close()
