"""The ITP adapter's receiver (service/itp.py): packets are read and parsed outside the haptic
tick (a receiver thread, or pump()), floods are dropped per source before parsing, and the tick
only copies the newest accepted sample. Loopback only; waits are bounded, no timings asserted."""
import socket
import subprocess
import sys
import threading
import time

import pytest

from pointfence.kernels.errors import InputError
from pointfence.service import itp
from pointfence.service.itp import ItpReceiver, pack_itp
from pointfence.service.udp_ratelimit import SourceLimiter

Q = [[0, 0, 0, 1], [0, 0, 0, 1]]


class ParseCounter:
    """Counts the parsing of ITP packets: ``in_poll``, every step (handle, the struct unpack,
    the checksum) run inside an arm's poll (the tick); ``elsewhere``, the packets handled
    outside it (the receiver's). (pack_itp, which the test calls, checksums too: not counted.)"""

    def __init__(self, monkeypatch):
        self.local = threading.local()
        self.in_poll = 0
        self.elsewhere = 0
        real_handle, real_sum, real_struct = ItpReceiver.handle, itp.itp_checksum, itp.ITP
        counter = self

        def handle(rx, *a, **k):
            counter.count(True)
            return real_handle(rx, *a, **k)

        def checksum(data, *rule):
            counter.count()
            return real_sum(data, *rule)

        class Struct:
            size = real_struct.size

            def unpack_from(self, *a):
                counter.count()
                return real_struct.unpack_from(*a)

            def __getattr__(self, name):       # pack, format: the real struct's
                return getattr(real_struct, name)

        monkeypatch.setattr(ItpReceiver, "handle", handle)
        monkeypatch.setattr(itp, "itp_checksum", checksum)
        monkeypatch.setattr(itp, "ITP", Struct())

    def count(self, handled=False):
        if getattr(self.local, "in_poll", False):
            self.in_poll += 1
        elif handled:
            self.elsewhere += 1

    def poll(self, arm, t):
        self.local.in_poll = True
        try:
            arm.poll(t)
        finally:
            self.local.in_poll = False


def test_the_tick_copies_the_newest_sample_and_never_parses(monkeypatch):
    counter = ParseCounter(monkeypatch)
    r = ItpReceiver("127.0.0.1", 0, receiver=False)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        arm = r.arm_master(0)
        for s in range(1, 6):
            tx.sendto(pack_itp(s, [[10, -20, 30], [0, 0, 0]], Q, buttons=(3, 0), grasp_mrad=(250, 0)), r.address)
        for k in range(3):                     # packets waiting in the socket: the tick does not read them
            counter.poll(arm, 0.001 * k)
        assert r.received == 0 and arm.seen == 0 and not arm.ok and list(arm.position) == [0.0, 0.0, 0.0]
        end = time.monotonic() + 10
        while r.received < 5 and time.monotonic() < end:
            r.pump()
        assert r.accepted == 5 and counter.elsewhere > 0
        counter.poll(arm, 0.004)
        assert arm.ok and arm.clutch and arm.buttons == 3 and arm.grasp == pytest.approx(0.25)
        assert list(arm.position) == pytest.approx([50e-6, -100e-6, 150e-6])
        assert counter.in_poll == 0
        counter.poll(arm, 0.2)                 # no newer sample: silent for 196 ms
        assert not arm.ok
    finally:
        tx.close()
        r.close()


def test_a_flooding_source_is_dropped_before_parsing_and_others_keep_their_share(monkeypatch):
    counter = ParseCounter(monkeypatch)
    # (a buffer that holds all 502 packets: what is measured here is the limiter, not the kernel's drops)
    r = ItpReceiver("127.0.0.1", 0, receiver=False, limiter=SourceLimiter(rate=1.0, burst=10.0), rcvbuf_bytes=1 << 20)
    genuine = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    flooder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    genuine.bind(("127.0.0.1", 0))
    try:
        arm = r.arm_master(0)
        genuine.sendto(pack_itp(1, [[1, 0, 0], [0, 0, 0]], Q), r.address)
        for _ in range(500):
            flooder.sendto(pack_itp(2, [[0, 500, 0], [0, 0, 0]], Q), r.address)
        genuine.sendto(pack_itp(2, [[1, 0, 0], [0, 0, 0]], Q), r.address)
        end = time.monotonic() + 10
        while r.received < 502 and time.monotonic() < end:
            r.pump()
        arm.poll(0.0)
        st = r.status()
        # the flooder's burst of 10 (and a token a second) reached the checks (refused: the link is locked);
        # the rest was never parsed
        assert st["received"] == 502 and st["rejected"]["rate_limited"] >= 480 and st["rejected"]["source"] <= 20
        assert r.accepted == 2 and arm.position[0] == pytest.approx(2e-6) and arm.position[1] == 0.0
        assert st["locked_to"] == list(genuine.getsockname())
        assert counter.elsewhere == 2 + st["rejected"]["source"]       # the genuine two and the flooder's burst
    finally:
        genuine.close()
        flooder.close()
        r.close()


FLOODER = """
import socket, sys, time
host, port, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
forged = bytes.fromhex(sys.stdin.readline().strip())
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
sent = 0
while sent < n:
    for _ in range(20):                  # ~20,000 packets/s: 20 x an ITP master, 5 x the per-source limit
        try:
            s.sendto(forged, (host, port))
        except OSError:
            pass
    sent += 20
    time.sleep(0.001)
print(sent)
"""


def test_a_spoofed_flood_from_another_process_never_changes_the_genuine_masters_sample(monkeypatch):
    counter = ParseCounter(monkeypatch)
    r = ItpReceiver("127.0.0.1", 0, timeout_ms=1000)    # receiver thread; generous: a loaded machine stalls threads
    arm = r.arm_master(0)
    stop = threading.Event()
    seen_y = []

    def ticker():                                        # the haptic tick: poll the arm about once a millisecond
        t0 = time.monotonic()
        while not stop.is_set():
            counter.poll(arm, time.monotonic() - t0)
            if arm.position[1] != 0.0:
                seen_y.append(float(arm.position[1]))
            time.sleep(0.001)

    th = threading.Thread(target=ticker, daemon=True)
    genuine = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    genuine.bind(("127.0.0.1", 0))
    proc = None
    seq = 0

    def send_genuine():
        nonlocal seq
        seq += 1
        genuine.sendto(pack_itp(seq, [[1, 0, 0], [0, 0, 0]], Q), r.address)

    try:
        th.start()
        end = time.monotonic() + 10
        while r.accepted == 0 and time.monotonic() < end:     # the genuine master holds the link
            send_genuine()
            time.sleep(0.002)
        assert r.status()["locked_to"] == list(genuine.getsockname())
        # valid packets with a newer sequence and 5 mm sideways per packet, from another process
        forged = pack_itp(10**6, [[0, 5000, 0], [0, 0, 0]], Q)
        proc = subprocess.Popen([sys.executable, "-c", FLOODER, *map(str, r.address), "20000"],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        proc.stdin.write(forged.hex() + "\n")
        proc.stdin.close()
        sent_during = 0
        end = time.monotonic() + 60
        while proc.poll() is None and time.monotonic() < end:
            send_genuine()
            sent_during += 1
            time.sleep(0.002)
        flooded = int(proc.stdout.read().strip() or 0)
        end = time.monotonic() + 10                            # the receiver catches up
        while r.accepted + sum(r.counters.values()) < r.received and time.monotonic() < end:
            time.sleep(0.01)
        last = r.received
        time.sleep(0.2)
        while r.received != last and time.monotonic() < end:
            last = r.received
            time.sleep(0.2)
        stop.set()
        th.join(5)
        arm.poll(1e9)                                          # a last copy (ok does not matter here)
        st = r.status()
        assert flooded == 20000 and sent_during > 100
        assert st["locked_to"] == list(genuine.getsockname())
        assert arm.position[1] == 0.0 and not seen_y, "a spoofed packet moved the arm"
        assert r.accepted <= seq and arm.position[0] == pytest.approx(r.accepted * 1e-6)
        assert r.accepted >= (seq - sent_during) + sent_during // 2, (r.accepted, seq, st)
        assert st["rejected"]["rate_limited"] > 0 and st["rejected"]["source"] > 0
        assert st["rejected"]["rate_limited"] + st["rejected"]["source"] == st["received"] - r.accepted
        assert counter.in_poll == 0 and counter.elsewhere > 0
    finally:
        stop.set()
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        th.join(5)
        genuine.close()
        r.close()


def test_a_raven_master_s_own_checksum_is_accepted_and_others_refused():
    """The receiver holds ITP masters to the Raven II's own UDPChecksum by default (a sum of the
    fields, what the Raven's master consoles send: service/robot/raven_itp_wire.py builds its
    packets from the Raven's C source), not to a byte sum a genuine console never sends."""
    from pointfence.service.itp import itp_checksum
    from pointfence.service.robot.raven_itp_wire import pack_u

    def console_packet(seq):
        buf = bytearray(124)
        pack_u(buf, seq, 1, (120, -40, 7), (0.0, 0.0, 0.0, 1.0), 30, 1)
        return bytes(buf)

    src = ("127.0.0.1", 40001)
    r = ItpReceiver("127.0.0.1", 0, receiver=False)
    try:
        assert r.checksum == "raven"
        assert r.handle(console_packet(1), 0.001, src)                   # a genuine console's packet
        assert r.counters["checksum"] == 0
        byte_sum = pack_itp(2, [[0, 0, 0], [120, -40, 7]], Q, rule="sum")
        assert itp_checksum(byte_sum, "sum") != itp_checksum(byte_sum, "raven")
        assert not r.handle(byte_sum, 0.002, src) and r.counters["checksum"] == 1
        assert r.handle(pack_itp(3, [[0, 0, 0], [1, 0, 0]], Q), 0.003, src)   # pack_itp: the Raven's rule
    finally:
        r.close()
    legacy = ItpReceiver("127.0.0.1", 0, receiver=False, checksum="sum")
    try:
        assert legacy.handle(pack_itp(1, [[0, 0, 0], [1, 0, 0]], Q, rule="sum"), 0.001, src)
        assert not legacy.handle(console_packet(2), 0.002, src)
    finally:
        legacy.close()
    with pytest.raises(InputError, match="checksum rule"):
        ItpReceiver("127.0.0.1", 0, receiver=False, checksum="crc")
