"""One master slot of the UDP hub (``udp_server.UdpHub``): the newest authenticated sample of
whichever client's session holds the slot, read by the haptic tick (``poll``), and the force sent
back to it (``send_force``: the hub's FEEDBACK). Units: metres and the master's own frame.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from pointfence.native import ptr

from .masters import Master
from .udp_native import TAKE_SILENT, TAKE_STALE
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
        self._session: Optional[Session] = None
        self._pos_p = ptr(self.position, np.float64, "position")      # (the take writes a new sample here)
        self._quat_p = ptr(self.orientation, np.float64, "orientation")
        self._force_p = ptr(self.force, np.float64, "force")

    @property
    def session(self):
        """The session that holds the slot (a ``Session``; None: none; the service may put a
        placeholder of its own while it reserves the slot)."""
        return self._session

    @session.setter
    def session(self, s) -> None:
        if isinstance(s, Session):       # its take writes into this master's arrays
            tk = s.take
            tk.pos, tk.quat, tk.grasp, tk.buttons = self._pos_p, self._quat_p, self.grasp, self.buttons
        self._session = s

    def poll(self, t: float) -> None:
        """The tick's read: take the slot's newest sample (loop time ``t``, s) and decide its
        timeout and age, in one compiled call (``NativeReceiver.take``, native/udp_tick.h)."""
        hub = self.hub
        if t != hub.t:
            hub.tick(t)
        s = self._session
        if s is None or not isinstance(s, Session):
            self.ok = False
            self.clutch = False
            return
        tk = s.take
        code = hub.rx.take(self.slot, s.take_ref, t, hub.t_ns)
        self.clutch, self.buttons, self.grasp, self.ok = tk.clutch != 0, tk.buttons, tk.grasp, tk.ok != 0
        if code == TAKE_SILENT:
            hub.drop(s)
            return
        age = tk.age_ns
        if age >= 0:
            hub.ages.record(age)
        if code == TAKE_STALE:           # a sample that waited longer than the timeout: none (S9)
            hub.stale_ticks += 1

    def send_force(self, f: np.ndarray) -> None:
        self.force[:] = f
        s = self._session
        if s is not None and isinstance(s, Session) and s.take.has_state:
            self.hub.send_feedback(self, s, self._force_p)


__all__ = ["UdpMaster"]
