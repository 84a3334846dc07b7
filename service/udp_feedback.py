"""The tick's FEEDBACK datagrams (``udp_server.UdpHub.send_feedback``).

One per arm and tick: the force to display with the state behind it, that is the arm's proxy,
robot position, contact, hold mask, robot mode and fixture flags. The service's output of the
tick (``Service.out``) holds them; ``FeedbackFields`` reads them once a tick for every arm, as
plain lists, and ``fill`` writes one arm's into the ``udp_native.Feedback`` struct that the C
receiver saturates (the session's force limit; zero if not finite), stamps, tags and sends.
"""
from __future__ import annotations

from pointfence.clients import protocol as P

from .udp_native import Feedback

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


def fill(fb: Feedback, s, slot: int, f, fields: tuple, tick: int, t_tick_ns: int) -> Feedback:
    """Arm ``slot``'s FEEDBACK to session ``s``, force ``f`` (N, master frame, (3,)), into ``fb``
    (returned): the tick ``tick`` that started at ``t_tick_ns`` (the deadline grid), the sample it
    used (sequence, client time) and ``fields`` (``FeedbackFields.of``)."""
    proxies, contacts, robots, modes, holds, fixtures = fields
    fb.tick, fb.t_tick_ns, fb.echo_seq, fb.echo_t_client_ns = tick, t_tick_ns, s.seq, s.t_client_ns
    fb.force[0], fb.force[1], fb.force[2] = f.tolist()
    fb.proxy[0], fb.proxy[1], fb.proxy[2] = proxies[slot]
    fb.robot[0], fb.robot[1], fb.robot[2] = robots[slot]
    fb.contact, fb.fixture, fb.robot_mode, fb.hold = contacts[slot], fixtures[slot], modes[slot], holds[slot]
    fb.error, fb.slot, fb.rejected = s.tick_error, slot, s.tick_rejected & 0xFFFFFFFF
    return fb


__all__ = ["FeedbackFields", "ROBOT_MODES", "fill"]
