"""UDP calls that keep the interpreter lock (``service/held_io.py``): they read and send what the
socket's own methods do, and no other thread runs while one is made (a send from the tick and a
Python receiver's reads: issue 18, a receiver starved between two queued datagrams).
Loopback only."""
import socket
import sys
import threading
import time

import pytest

from pointfence.clients import Client
from pointfence.service import held_io
from pointfence.service.rx_stamps import SO_TIMESTAMPNS
from pointfence.service.udp_server import UdpHub

pytestmark = pytest.mark.skipif(held_io._CALLS is None, reason="the lock-keeping calls are Linux, 64-bit")

KEY = bytes(range(3, 35))


def _pair():
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.setblocking(False)
    rx.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.bind(("127.0.0.1", 0))
    return rx, tx


def test_receiver_reads_what_recvmsg_into_reads_sizes_addresses_stamps_and_a_cut_datagram():
    rx, tx = _pair()
    tx2 = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx2.bind(("127.0.0.1", 0))
    try:
        r = held_io.Receiver(rx, socket.CMSG_SPACE(16))
        assert r.held
        payloads = [bytes([k]) * (1 + 37 * k) for k in range(12)]
        for k, p in enumerate(payloads):
            (tx if k % 2 else tx2).sendto(p, rx.getsockname())
        time.sleep(0.02)
        buf = bytearray(300)
        before = time.time_ns()
        for k, p in enumerate(payloads):
            got = r.read(buf)
            assert got is not None, k
            n, addr, anc = got
            want = p[:len(buf)]                       # longer than the buffer: cut to it
            assert n == len(want) and bytes(buf[:n]) == want
            assert addr == (tx if k % 2 else tx2).getsockname()
            stamps = [d for level, kind, d in anc if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS]
            assert len(stamps) == 1
            sec, nsec = int.from_bytes(stamps[0][:8], "little"), int.from_bytes(stamps[0][8:16], "little")
            assert 0 < before - (sec * 1_000_000_000 + nsec) < 5_000_000_000
        assert r.read(buf) is None                    # nothing waits
        tx.sendto(b"same", rx.getsockname())          # the same path, read again the same way
        time.sleep(0.01)
        mine = r.read(buf)
        tx.sendto(b"same", rx.getsockname())
        time.sleep(0.01)
        n, anc, _, addr = rx.recvmsg_into((buf,), socket.CMSG_SPACE(16))
        assert (mine[0], mine[1], [(a, b) for a, b, _ in mine[2]]) == (n, addr, [(a, b) for a, b, _ in anc])
        rx.close()
        assert r.read(buf) is None                    # a closed socket: nothing, no error
    finally:
        rx.close()
        tx.close()
        tx2.close()


def test_sender_delivers_and_refuses_a_bad_address_without_raising():
    rx, tx = _pair()
    try:
        s = held_io.Sender(tx)
        assert s.held
        assert s.send(rx.getsockname(), b"feedback")
        assert s.send(rx.getsockname(), b"again")
        buf = bytearray(b"in place")                  # a bytearray: sent as it is at the call
        assert s.send(rx.getsockname(), buf)
        buf[:2] = b"IN"
        assert s.send(rx.getsockname(), buf)
        time.sleep(0.01)
        assert rx.recvfrom(100) == (b"feedback", tx.getsockname())
        assert rx.recvfrom(100)[0] == b"again"
        assert rx.recvfrom(100)[0] == b"in place" and rx.recvfrom(100)[0] == b"IN place"
        assert not s.send(("not an address", 1), b"x")
        assert not s.send(("127.0.0.1",), b"x")
        tx.close()
        assert not s.send(rx.getsockname(), b"x")     # a closed socket: refused, counted by the caller
    finally:
        rx.close()
        tx.close()


def _other_thread_ran_during(fn) -> int:
    """How many steps another Python thread made while ``fn()`` ran in this thread. The other
    thread hands the lock back after every step (``time.sleep(0)``) and, with a switch interval of
    10 s, cannot take it from this thread: it runs only where ``fn`` hands the lock over."""
    steps, stop = [0], [False]

    def spin():
        while not stop[0]:
            steps[0] += 1
            time.sleep(0)

    old = sys.getswitchinterval()
    sys.setswitchinterval(10.0)
    th = threading.Thread(target=spin, daemon=True)
    try:
        th.start()
        time.sleep(0.02)             # it runs, and gives the lock back at its next step
        before = steps[0]
        fn()
        return steps[0] - before
    finally:
        stop[0] = True
        th.join()
        sys.setswitchinterval(old)


def test_reads_and_sends_keep_the_interpreter_lock_where_the_sockets_own_calls_hand_it_over():
    """2,000 datagrams sent and read: no other thread runs meanwhile. With the socket's own
    ``sendto`` and ``recvmsg_into`` (the code before) the other thread ran between them (here
    hundreds of times: a few per cent of the calls; in the service, each such hand-over can keep
    the receiver or the tick waiting for the other's whole turn). The other thread takes a
    hand-over only when it wakes before this one is back: on a fast or busy machine that can take
    more than 2,000 calls, so the sockets' own calls get up to 50 rounds to show one (the held
    ones get 50 rounds too, and must show none)."""
    rx, tx = _pair()
    try:
        r, s, buf = held_io.Receiver(rx, socket.CMSG_SPACE(16)), held_io.Sender(tx), bytearray(64)
        dest = rx.getsockname()

        def held():
            for _ in range(2000):
                assert s.send(dest, b"x" * 40)
                assert r.read(buf) is not None

        def own():
            for _ in range(2000):
                tx.sendto(b"x" * 40, dest)
                rx.recvmsg_into((buf,), socket.CMSG_SPACE(16))

        assert sum(_other_thread_ran_during(held) for _ in range(50)) == 0
        assert any(_other_thread_ran_during(own) > 0 for _ in range(50))
    finally:
        rx.close()
        tx.close()


def test_the_hub_answers_through_them_and_its_reads_carry_the_kernel_stamps():
    """A UdpHub (pumped, no receiver thread) answers the handshake through the lock-keeping
    calls, accepts states read by its C receiver with the kernel's arrival stamps, and sends
    FEEDBACK."""
    hub = UdpHub(KEY, 1, receiver=False, timeout_ms=1000)
    c = Client(*hub.address, KEY, 5, timeout_ms=1000)
    try:
        assert hub.stamps and hub.sender.held
        c.hello_send()
        hub.pump()
        assert c.hello_wait(0.0) is None
        hub.pump()
        assert c.hello_wait(2.0) is not None
        c.send_state((0.001, 0.002, 0.003))
        sent = time.perf_counter_ns()
        time.sleep(0.01)
        hub.pump()
        m = hub.masters[0]
        m.poll(0.0)
        assert m.ok and tuple(m.position) == (0.001, 0.002, 0.003)
        s = m.session
        assert abs(s.rx_ns - sent) < 5_000_000            # the kernel's stamp, on perf_counter's clock
        m.send_force([0.5, 0.0, 0.0])
        time.sleep(0.01)
        fb = c.poll()
        assert fb is not None and fb.force == (0.5, 0.0, 0.0)
        assert hub.feedback_sent == 1 and hub.send_errors == 0
    finally:
        c.close()
        hub.close()
