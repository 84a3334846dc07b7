"""The tick's FEEDBACK datagrams (``udp_server.UdpHub.send_feedback``).

One per arm and tick: the force to display (saturated at the session's force limit, zero if not
finite) with the state behind it, that is the arm's proxy, robot position, contact, hold mask,
robot mode and fixture flags. The service's output of the tick (``Service.out``) holds them;
``FeedbackFields`` reads them once a tick for every arm, as plain lists, and ``write_feedback``
writes one arm's datagram into the ``FeedbackWriter``'s buffer (no allocation but the tag).
"""
from __future__ import annotations

import math
import time

from pointfence.clients import protocol as P

#: FEEDBACK's robot mode for each ``RobotMode`` value (ENABLED, HOLDING, FAULT)
ROBOT_MODES = (P.ROBOT_ENABLED, P.ROBOT_HOLDING, P.ROBOT_FAULT)


class FeedbackFields:
    """Every arm's FEEDBACK fields of the current tick, read from the service once per tick
    (``of(service, tick_ns)``: the tick is named by its start, perf_counter ns)."""

    def __init__(self, n: int):
        self.n = int(n)
        self._fields, self._ns = None, -1

    def of(self, svc, tick_ns: int) -> tuple:
        """(proxies, contacts, robots, modes, holds, fixtures) of service ``svc`` (None: none
        attached): lists, one entry per arm."""
        if self._ns != tick_ns:
            self._fields, self._ns = self._read(svc), tick_ns
        return self._fields

    def _read(self, svc) -> tuple:
        n = self.n
        if svc is None:
            zero = [(0.0, 0.0, 0.0)] * n
            return zero, [P.CONTACT_FREE] * n, zero, [P.ROBOT_IDEAL] * n, [0] * n, [0] * n
        out = svc.out
        modes = [P.ROBOT_IDEAL if r is None else ROBOT_MODES[int(r.state)] for r in svc.robots]
        flags = ((P.FX_HAPTICS if svc.haptics_on else 0) | (P.FX_TELEOP if svc.teleop_on else 0)
                 | (P.FX_FIXTURE if svc.cfg.mode == "fixture" else 0))
        fixtures = [flags | (P.FX_COUPLED if c else 0) for c in out.coupled.tolist()]
        return (out.proxy.tolist(), out.state.tolist(), out.robot_pos.tolist(), modes, out.arm_hold.tolist(),
                fixtures)


def write_feedback(writer: P.FeedbackWriter, s, slot: int, f, fields: tuple, tick: int, t_tick_ns: int) -> bytearray:
    """Arm ``slot``'s FEEDBACK to session ``s`` (its next sequence number), force ``f`` (N,
    master frame), into ``writer``'s buffer, which it returns: send it before the next write."""
    fx, fy, fz = f.tolist()
    if not (math.isfinite(fx) and math.isfinite(fy) and math.isfinite(fz)):
        fx = fy = fz = 0.0
    n2 = fx * fx + fy * fy + fz * fz
    mf = s.max_force
    if n2 > mf * mf:
        k = mf / n2 ** 0.5
        fx, fy, fz = fx * k, fy * k, fz * k
    proxies, contacts, robots, modes, holds, fixtures = fields
    px, py, pz = proxies[slot]
    rx, ry, rz = robots[slot]
    return writer.write(s.key, s.device_id, s.id, s.next_tx(), tick, t_tick_ns, time.perf_counter_ns(), s.seq,
                        s.t_client_ns, fx, fy, fz, px, py, pz, rx, ry, rz, contacts[slot], fixtures[slot], modes[slot],
                        0, holds[slot], s.tick_error, slot, s.tick_rejected)


__all__ = ["FeedbackFields", "ROBOT_MODES", "write_feedback"]
