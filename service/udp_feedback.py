"""The tick's FEEDBACK datagrams (``udp_server.UdpHub.send_feedback``).

One per arm and tick: the force to display with the state behind it, that is the arm's proxy,
robot position, contact, hold mask, robot mode and fixture flags. The service's output of the
tick (``Service.out``) holds them: ``FeedbackFields`` points a ``udp_native.FeedbackSource`` at
its arrays (bound once) and sets, once a tick, what is not in them (the tick's number and start,
the service's fixture flags, each arm's robot mode); the C receiver then fills each arm's
FEEDBACK from it (``NativeReceiver.send_arm``, native/udp_tick.h), saturates the force (the
session's limit; zero if not finite), stamps, tags and sends it.
"""
from __future__ import annotations

import ctypes
from operator import is_

import numpy as np

from pointfence.clients import protocol as P
from pointfence.native import ptr

from .udp_native import FeedbackSource

#: FEEDBACK's robot mode for each ``RobotMode`` value (ENABLED, HOLDING, FAULT)
ROBOT_MODES = (P.ROBOT_ENABLED, P.ROBOT_HOLDING, P.ROBOT_FAULT)


class FeedbackFields:
    """Every arm's FEEDBACK fields of the current tick (``of(service, tick, t_tick_ns)``, once a
    tick: the tick's number and start on the deadline grid, ns), as ``byref`` of a
    ``FeedbackSource`` for ``NativeReceiver.send_arm``."""

    def __init__(self, n: int):
        self.n = n = int(n)
        self.src = FeedbackSource(n=n)
        self.ref = ctypes.byref(self.src)
        self._modes = np.full(n, P.ROBOT_IDEAL, np.uint8)
        self._zero3, self._zero_i32 = np.zeros((n, 3)), np.zeros(n, np.int32)
        self._zero_i64, self._zero_b = np.zeros(n, np.int64), np.zeros(n, bool)
        self._bound_to = ()               # the output arrays the source points at
        self._bind(None)
        self.src.mode = ptr(self._modes, np.uint8, "modes")
        self._ns = -1

    def _bind(self, out) -> None:
        """Point the source at ``out``'s arrays (None: zeros, no service attached)."""
        arrays = ((self._zero3, self._zero3, self._zero_i32, self._zero_i64, self._zero_b) if out is None else
                  (out.proxy, out.robot_pos, out.state, out.arm_hold, out.coupled))
        if self._bound_to and all(map(is_, arrays, self._bound_to)):
            return
        src = self.src
        src.proxy, src.robot = ptr(arrays[0], np.float64, "proxy"), ptr(arrays[1], np.float64, "robot_pos")
        src.contact, src.hold = ptr(arrays[2], np.int32, "state"), ptr(arrays[3], np.int64, "arm_hold")
        src.coupled = ptr(arrays[4], bool, "coupled")
        self._bound_to = arrays           # (kept alive: the struct holds only their addresses)

    def of(self, svc, tick: int, t_tick_ns: int, tick_ns: int):
        """The source for service ``svc`` (None: none attached) at the tick that started at
        ``tick_ns`` (perf_counter ns): set once for that tick."""
        if self._ns != tick_ns:
            self._ns = tick_ns
            src = self.src
            src.tick, src.t_tick_ns = tick, t_tick_ns
            if svc is None:
                self._bind(None)
                src.fixture = 0
                return self.ref
            self._bind(svc.out)
            src.fixture = ((P.FX_HAPTICS if svc.haptics_on else 0) | (P.FX_TELEOP if svc.teleop_on else 0)
                           | (P.FX_FIXTURE if svc.cfg.mode == "fixture" else 0))
            self._modes[:] = [P.ROBOT_IDEAL if r is None else ROBOT_MODES[int(r.state)] for r in svc.robots]
        return self.ref


__all__ = ["FeedbackFields", "ROBOT_MODES"]
