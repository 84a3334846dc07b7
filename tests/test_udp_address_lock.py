"""A session is locked to the address its handshake came from (issue 18, item 7): an authentic
STATE or BYE captured and sent again from another address, even ahead of the original, is
refused as naming no session of that address, before any tag is computed, and moves nothing.
Loopback only; a pumped hub (no receiver thread)."""
import socket
import time

from pointfence.clients import protocol as P
from pointfence.service.udp_server import UdpHub

from test_udp_receiver import connected

KEY = bytes(range(3, 35))


def test_a_replay_from_another_address_that_overtakes_the_original_is_refused_and_moves_nothing():
    """The copy arrives first (an attacker on the path is faster than the device): refused as
    no_session, the session's address and sample unchanged; the original is accepted after it.
    Before, the copy was accepted and moved the session's FEEDBACK to the attacker's address."""
    hub = UdpHub(KEY, 1, receiver=False, timeout_ms=1000)
    attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    attacker.bind(("127.0.0.1", 0))
    try:
        c = connected(hub, 1000)
        home = hub.sessions[c.session].addr
        state = P.State(1, 0, (0.002, 0.0, 0.0)).encode(c.key, c.device_id, c.session, c.seq + 1)
        attacker.sendto(state, hub.address)               # the copy, first
        time.sleep(0.005)
        c.sock.send(state)                                 # the original, from the device
        time.sleep(0.01)
        hub.pump()
        s = hub.sessions[c.session]
        assert s.addr == home and s.accepted == 1 and hub.counters["no_session"] == 1
        m = hub.masters[0]
        m.poll(0.0)
        assert m.ok and tuple(m.position) == (0.002, 0.0, 0.0)
        m.send_force([0.1, 0.0, 0.0])                      # FEEDBACK goes to the device, not the attacker
        time.sleep(0.01)
        attacker.setblocking(False)
        try:
            got = attacker.recv(2048)
        except BlockingIOError:
            got = None
        assert got is None
        c.close()
    finally:
        attacker.close()
        hub.close()


def test_a_bye_from_another_address_does_not_end_the_session():
    hub = UdpHub(KEY, 1, receiver=False, timeout_ms=1000)
    attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        c = connected(hub, 1000)
        bye = P.Bye(P.E_OK).encode(c.key, c.device_id, c.session, c.seq + 1)
        attacker.sendto(bye, hub.address)
        time.sleep(0.01)
        hub.pump()
        assert c.session in hub.sessions and hub.counters["no_session"] == 1
        c.close()
    finally:
        attacker.close()
        hub.close()
