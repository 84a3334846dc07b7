"""The soak's simulated devices (bench/soak_devices.py): the scripted operator's path is smooth
and reaches into the fixture as the soak wants, and a device that reads the service's FEEDBACK
only every FEEDBACK_POLL_S, from a small receive buffer, keeps its session (it never starts a new
handshake while the service answers). Loopback only."""
import math
import socket
import time

import numpy as np

from pointfence.bench import soak_devices as D
from pointfence.service.udp_server import UdpHub

KEY = bytes(range(3, 35))


def test_the_scripted_path_pushes_in_smoothly_then_circles_and_freezes_where_told():
    for arm in (0, 1):
        dev = D._Device(arm)
        assert D._position(dev, 0.0, None) == (0.0, 0.0, 0.0)
        x, y, z = D._position(dev, D.APPROACH_S, None)
        assert math.isclose(x, 0.02 * arm, abs_tol=1e-12) and y == 0.0 and math.isclose(z, -D.PUSH)
        t = np.arange(0.0, D.APPROACH_S + 6.0, 1e-3)
        p = np.array([D._position(dev, s, None) for s in t])
        assert np.linalg.norm(np.diff(p, axis=0), axis=1).max() < 1e-4     # < 0.1 mm a millisecond
        circ = p[t >= D.APPROACH_S + 1.0]                                     # the circle at full radius
        centre = np.array([0.02 * arm, D.CIRCLE_R, -D.PUSH])
        assert np.allclose(np.linalg.norm(circ - centre, axis=1), D.CIRCLE_R, atol=1e-12)
        assert np.allclose(circ[:, 2], -D.PUSH)
        assert D._position(dev, 5.0, 2.0) == D._position(dev, 2.0, None)      # frozen at t = 2 s


def test_a_device_reading_feedback_every_poll_period_keeps_its_session():
    hub = UdpHub(KEY, 1, timeout_ms=50)       # its receiver thread applies the states
    dev = D._Device(0)
    link = D._Link(*hub.address, KEY, dev)
    polls = [0]
    poll = link.c.poll

    def counted():
        polls[0] += 1
        return poll()

    link.c.poll = counted
    try:
        assert link.c.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) <= 4 * D.FEEDBACK_RCVBUF
        link.c.connect(timeout=10.0)
        link.last_rx = time.monotonic()
        m, shared = hub.masters[0], {"t0": time.monotonic(), "frozen_at": None, "pedal": True}
        steps, t0 = 300, time.monotonic()
        for k in range(steps):                # 0.3 s at about 1 kHz: device step, then the service's tick
            link.step(time.monotonic(), shared)
            m.poll(time.monotonic() - t0)
            m.send_force(np.zeros(3))
            time.sleep(0.001)
        took = time.monotonic() - t0
        assert not link.connecting and dev.reconnects == 0 and hub.sessions_dropped == 0
        assert link.c.fresh                   # feedback seen within the client's 50 ms
        assert polls[0] <= took / D.FEEDBACK_POLL_S + 2 < steps / 2          # not every step
        assert dev.sent and len(dev.sent) == min(steps, dev.sent.maxlen)
    finally:
        link.c.close()
        hub.close()
