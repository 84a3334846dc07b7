"""One master slot of the UDP hub (``udp_server.UdpHub``): the newest authenticated sample of
whichever client's session holds the slot, read by the haptic tick (``poll``), and the force sent
back to it (``send_force``: the hub's FEEDBACK). Units: metres and the master's own frame.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from pointfence.clients import protocol as P

from .masters import Master
from .udp_native import BUSY, Sample
from .udp_session import Session


class UdpMaster(Master):
    """Slot ``slot`` of a ``udp_server.UdpHub`` (``hub``): the master of one proxy, driven by whichever client
    holds the slot (``ok`` is False while no fresh authenticated sample exists)."""

    name = "udp"

    def __init__(self, hub, slot: int):
        super().__init__()
        self.hub = hub
        self.slot = slot
        self.name = f"udp{slot}"
        self.ok = False                  # (no sample yet; orientation and grasp: the base's defaults)
        self.clutch = False
        self.session: Optional[Session] = None
        self._sample = Sample()          # the tick's copy of the slot's latest sample

    def poll(self, t: float) -> None:
        """The tick's read: copy the slot's newest sample (loop time ``t``, s), decide its timeout."""
        hub = self.hub
        if t != hub.t:
            hub.tick(t)
        s = self.session
        if s is None or not isinstance(s, Session):
            self.ok = False
            self.clutch = False
            return
        c = self._sample
        n = hub.rx.sample(self.slot, s.id, c)
        if n == BUSY:                            # being written: the last copy stands this tick
            n = s.seen
        elif n:
            s.tick_rejected = c.rejected
            s.tick_error = c.error
        if n and n != s.seen:
            pos, q = self.position, c.quat
            pos[0], pos[1], pos[2] = c.pos
            flags = c.flags
            self.clutch = bool(flags & P.F_CLUTCH)
            self.buttons = c.buttons
            if flags & P.F_ORIENTATION:
                o = self.orientation
                o[0], o[1], o[2], o[3] = q[0], q[1], q[2], q[3]
            if flags & P.F_GRASP:
                self.grasp = c.grasp
            s.seen = n
            s.seq = c.seq
            s.t_client_ns = c.t_client
            s.rx_ns = c.rx_ns
            s.last_rx_t = t
            s.has_state = True
        elif s.last_rx_t is None:
            s.last_rx_t = t                      # a new session: its silence counts from this tick
        if t - s.last_rx_t > s.timeout_s:
            hub.drop(s)
            self.ok = False
            self.clutch = False
            return
        if s.has_state:
            age = hub.t_ns - s.rx_ns
            hub.ages.record(age)
            if age > s.max_age_ns:       # a sample that waited longer than the timeout: none (S9)
                hub.stale_ticks += 1
                self.ok = False
                return
        self.ok = s.has_state

    def send_force(self, f: np.ndarray) -> None:
        self.force[:] = f
        s = self.session
        if s is not None and s.has_state:
            self.hub.send_feedback(self, s, self.force)


__all__ = ["UdpMaster"]
