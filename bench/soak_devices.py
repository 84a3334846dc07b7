"""The soak's haptic devices and its attackers, each in a process of its own (so that their
Python does not compete with the service's haptic loop for its interpreter lock).

``devices_main``: the simulated devices, each a ``pointfence.clients.Client`` at 1 kHz over
loopback, served in turn by one thread that sleeps between its periods. They are the soak's
equipment, kept cheap beside the service they load: they display no force, so they read the
service's FEEDBACK only to know that their session lives (every ``FEEDBACK_POLL_S``, from a
receive buffer of a few datagrams: the kernel drops the rest unread, where reading and
verifying every one took most of the devices' process). A device pushes its arm into the
fixture (master frame: down, device 1 also 2 cm along +x) and then circles slowly in the horizontal plane while pushing, as an operator
probing along a surface. The soak drives the devices through a pipe with commands:

* ``("freeze", on)``: every device holds still (operator actions are judged while it does);
* ``("pedal", on)``: every device's foot pedal down (True) or up;
* ``("silence", arm, s)``: that device sends nothing for ``s`` seconds (then reconnects);
* ``("nan", arm, s)``: that device sends NaN positions for ``s`` seconds;
* ``("capture", arm)``: answers with that device's last 200 STATE datagrams and its last
  handshake's HELLOs (a captured session, for the replay attack);
* ``("stop",)``: close the sessions, answer with the link statistics, and end.

``flood_main``: sends datagrams at ``rate_hz`` for ``seconds`` from its own socket to the
service: random forgeries (``"forged"``, STATE-shaped with random tags) or the given captured
datagrams (``"replay"``); it answers with the number sent.
"""
from __future__ import annotations

import math
import os
import socket
import threading
import time
from collections import deque

import numpy as np

#: master-frame push (m): 7.4 cm down moves a Raven II tip 3.7 cm (scale 0.5), 1 cm into the
#: default scene's 2 cm fixture around the balloon
PUSH = 0.074
CIRCLE_R, CIRCLE_HZ = 0.004, 0.25          # the probing circle while pushing (master frame)
APPROACH_S = 1.5
#: a device starts a new handshake after this long without feedback (s): a late feedback from a
#: busy service is not a lost session, and a new handshake would end a live one
RECONNECT_S = 0.5
#: how often a device reads the service's FEEDBACK (s): well within the client's 50 ms freshness
FEEDBACK_POLL_S = 0.01
#: a device socket's receive buffer (bytes asked; Linux doubles it and keeps a floor): the few
#: FEEDBACK datagrams that arrive first after a read wait for the next; the kernel drops the rest
FEEDBACK_RCVBUF = 2048


class _Device:
    """One device's script and its overrides (set by the command thread, read by its loop)."""

    def __init__(self, arm: int):
        self.arm = arm
        self.offset_x = 0.02 * arm
        self.silent_until = 0.0
        self.nan_until = 0.0
        self.sent = deque(maxlen=200)
        self.hellos: list = []
        self.reconnects = 0
        self.errors = 0


def _position(dev: _Device, t: float, frozen_at) -> tuple:
    """The scripted master position (x, y, z, m) at time ``t`` (s since start), or where it was
    frozen."""
    if frozen_at is not None:
        t = frozen_at
    a = min(1.0, t / APPROACH_S)
    a = 0.5 - 0.5 * math.cos(math.pi * a)             # smooth start and stop
    x, y, z = dev.offset_x * a, 0.0, -PUSH * a
    if t > APPROACH_S:
        w = 2 * math.pi * CIRCLE_HZ * (t - APPROACH_S)
        r = min(1.0, (t - APPROACH_S) / 1.0) * CIRCLE_R
        x, y = x + r * math.sin(w), y + r * (1.0 - math.cos(w))
    return x, y, z


class _Link:
    """One device's client session and its reconnection state."""

    def __init__(self, host, port, key, dev: _Device):
        from pointfence.clients import Client

        self.dev = dev
        self.c = Client(host, port, key, device_id=100 + dev.arm, timeout_ms=50,
                        workspace=((-0.2, -0.2, -0.2), (0.2, 0.2, 0.2)))
        try:
            self.c.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, FEEDBACK_RCVBUF)
        except OSError:
            pass
        self.last_rx = self.retry_at = self.next_poll = 0.0
        self.connecting = False

    def step(self, now: float, shared: dict) -> None:
        dev, c = self.dev, self.c
        if now < dev.silent_until:
            return
        if self.connecting:             # a handshake under way: never block the other devices
            try:
                w = c.hello_wait(0.0)
            except Exception:           # noqa: BLE001 -- refused: counted, a new handshake below
                dev.errors += 1
                w, self.connecting = None, False
            if w is None:
                if now >= self.retry_at:
                    self.retry_at = now + 0.1
                    c.hello_send()
                return
            self.connecting = False
            dev.hellos = list(c.hellos_sent)
            dev.reconnects += 1
            self.last_rx = now
        elif not c.fresh and now - self.last_rx > RECONNECT_S:
            self.connecting = True       # the service dropped the session (silence, a restart)
            self.retry_at = now + 0.1
            c.hello_send()
            return
        fz = shared["frozen_at"]
        pos = _position(dev, now - shared["t0"], None if fz is None else fz - shared["t0"])
        if now < dev.nan_until:
            pos = (math.nan, 0.0, 0.0)
        c.send_state(pos, clutch=shared["pedal"])
        dev.sent.append(c.last_datagram)
        if now >= self.next_poll:
            self.next_poll = now + FEEDBACK_POLL_S
            if c.poll() is not None:
                self.last_rx = now


def _devices_loop(host, port, key, devs, shared: dict, stop: threading.Event, rt_priority: int = 0) -> None:
    """Every device in one thread at 1 kHz (absolute deadlines; far behind: skip ahead), SCHED_FIFO
    ``rt_priority`` where the OS allows it (0: normal; ``shared["scheduling"]`` says what applied)."""
    from pointfence.service.osthread import set_fifo

    shared["scheduling"] = set_fifo(threading.get_native_id(), rt_priority)
    links = [_Link(host, port, key, d) for d in devs]
    period = 1e-3
    try:
        for ln in links:
            ln.c.connect(timeout=30.0)
            ln.last_rx = time.monotonic()
            ln.dev.hellos = list(ln.c.hellos_sent)
        t0 = time.monotonic()
        k = 0
        while not stop.is_set():
            k += 1
            wait = t0 + k * period - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            elif wait < -0.05:          # fell far behind (a descheduled process): skip ahead
                k = int((time.monotonic() - t0) / period)
            now = time.monotonic()
            for ln in links:
                ln.step(now, shared)
    finally:
        for ln in links:
            ln.dev.stats = ln.c.stats
            ln.c.close()


def devices_main(conn, host: str, port: int, key: bytes, n: int = 2, rt_priority: int = 0) -> None:
    """The devices' process (see the module docstring); ``conn``: its end of a Pipe;
    ``rt_priority``: the devices' thread's SCHED_FIFO priority (0: normal)."""
    shared = {"t0": time.monotonic(), "frozen_at": None, "pedal": True}
    devs = [_Device(b) for b in range(n)]
    stop = threading.Event()
    threads = [threading.Thread(target=_devices_loop, args=(host, port, key, devs, shared, stop, rt_priority), daemon=True,
                                name="soak-devices")]
    for th in threads:
        th.start()
    conn.send(("started",))
    while True:
        msg = conn.recv()
        cmd = msg[0]
        if cmd == "freeze":
            shared["frozen_at"] = time.monotonic() if msg[1] else None
        elif cmd == "pedal":
            shared["pedal"] = bool(msg[1])
        elif cmd == "silence":
            devs[msg[1]].silent_until = time.monotonic() + float(msg[2])
        elif cmd == "nan":
            devs[msg[1]].nan_until = time.monotonic() + float(msg[2])
        elif cmd == "capture":
            d = devs[msg[1]]
            conn.send((list(d.sent), list(d.hellos)))
            continue
        elif cmd == "stop":
            stop.set()
            for th in threads:
                th.join(timeout=5.0)
            conn.send(("stopped", [{"reconnects": d.reconnects, "errors": d.errors, "scheduling": shared.get("scheduling"),
                                    "sent": int(getattr(getattr(d, "stats", None), "sent", 0))} for d in devs]))
            return
        conn.send(("ok",))


def flood_main(conn, host: str, port: int, kind: str, seconds: float, rate_hz: float, datagrams=()) -> None:
    """A flood (see the module docstring) from its own socket; sends back the count sent."""
    from pointfence.clients import protocol as P

    try:   # the attacker's own CPU is not what is measured: it yields to everything else here
        os.nice(19)
    except OSError:
        pass
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rng = np.random.default_rng(int.from_bytes(os.urandom(4), "little"))
    pool = list(datagrams)
    if kind == "forged":    # STATE-shaped, right size and header, random body and tag
        hdr = bytes(pool[0][:16]) if pool else None
        size = len(pool[0]) if pool else P.MAX_DATAGRAM // 2
        pool = [(hdr or b"") + rng.bytes(size - (len(hdr) if hdr else 0)) for _ in range(256)]
    sent, t0 = 0, time.monotonic()
    batch = max(1, int(rate_hz / 1000))
    while time.monotonic() - t0 < seconds:
        for _ in range(batch):
            try:
                s.sendto(pool[sent % len(pool)], (host, port))
            except OSError:
                pass
            sent += 1
        time.sleep(0.001)
    s.close()
    conn.send(sent)
