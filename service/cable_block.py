"""The shared-memory block between the service and its grasper process (cable_grasper.py,
cable_grasper_child.py), declared once as NumPy dtypes, as robot/hosted_block.py declares the
robot process's: both sides take every region and field from ``GrasperBlock`` by name.

Regions: control words (``CONTROL``), the command channel (service -> child, one ``COMMAND`` row),
the state channel (child -> service, one ``STATE`` row), and two texts (the fault reason, the
tension alert; UTF-8, ``TEXT`` bytes). The channels are ``hosted_block.Channel``: double-buffered,
sequence-counted and CRC-checked, so neither side ever waits for the other.

Units: angles rad (the jaw is the link side of the cable drive), torques N m, stiffness N/m,
tension grams(-force), times s.
"""
from __future__ import annotations

import numpy as np

from .robot.hosted_block import TEXT, Channel, RowLayout, get_text, put_text

#: control words: stop request (service -> child), ticks run (the child's heartbeat), the child's
#: pid, ready (the controller is built), faulted (the child's fault is latched: zero torque),
#: inject (fault injection, service -> child: ``INJECT_*``)
CONTROL = np.dtype([("stop", "i8"), ("ticks", "i8"), ("pid", "i8"), ("ready", "i8"), ("faulted", "i8"),
                    ("inject", "i8")])
#: fault injection codes: none; the motor encoder reads NaN (a broken sensor)
INJECT_NONE, INJECT_NAN = 0, 1

#: one command (service -> child): commands sent (a sequence number), the jaw angle asked for
#: (rad), fault clears asked for (a count), hold (1: the service saw a fault: zero torque, latch)
COMMAND = np.dtype([("seq", "f8"), ("jaw", "f8"), ("clear_seq", "f8"), ("hold", "f8")])

#: the grasper's state (child -> service), float64: child clock (s), ticks run, periods (run or
#: skipped), deadline misses, commands and clears applied, jaw setpoint (rad, the command after
#: clamping and the rate limit), estimated jaw angle and velocity (rad, rad/s), estimated motor
#: angle (rad), motor torque applied (N m), estimated external link torque (N m, contact), cable
#: stiffness used/estimated (N/m), estimated tension (g; NaN: not estimated), tension alert (0
#: none, 1 below the range, 2 above), this tick's lateness and the largest so far (s), this tick's
#: compute time and the largest so far (s), faulted (0/1), the fault's kind (``FAULT_CODES``), fault
#: and alert text versions,
#: degraded (1: the UKF/MPC run interpreted, no C), the sim plant's true jaw angle (rad) and load
#: torque on the link (N m) (NaN for a real plant)
STATE = np.dtype([(name, "f8") for name in (
    "t", "ticks", "periods", "misses", "cmd_seq", "clear_seq", "setpoint", "jaw", "jaw_velocity", "motor_angle",
    "motor_torque", "link_torque", "k_e", "tension_g", "tension_alert", "late", "late_max", "compute",
    "compute_max", "faulted", "fault_code", "fault_ver", "alert_ver", "degraded", "true_jaw", "true_link_torque")])

FAULT_TEXT, ALERT_TEXT = 0, 1
#: the kinds of grasper fault, by code (0: none): the controller's own (``CableLoop``: encoder,
#: estimate, torque, parameter range), a late tick, a hold the service asked for, the process lost
FAULT_CODES = {1: "controller", 2: "late", 3: "held", 4: "process lost"}
CONTROLLER, LATE, HELD, LOST_CODE = 1, 2, 3, 4


def _channel(row: np.dtype) -> np.dtype:
    """A ``Channel`` of one ``row``: two slots, their counters and the slot to read, their CRC-32s
    (the layout ``hosted_block.Channel`` reads)."""
    return np.dtype([("data", row, (2, 1)), ("meta", "i8", (4,)), ("sums", "i8", (2,))])


def block_dtype() -> np.dtype:
    return np.dtype([("ctl", CONTROL), ("state", _channel(STATE)), ("cmd", _channel(COMMAND)),
                     ("text", "u1", (2, TEXT))])


class GrasperBlock:
    """The block over ``buf`` (None: a private zeroed copy): ``ctl`` (a record of ``CONTROL``),
    ``state`` and ``cmd`` (``Channel``; rows read through ``state_layout`` / ``command_layout``),
    ``text`` (2, TEXT), ``raw`` (the bytes)."""

    state_layout = RowLayout(STATE)
    command_layout = RowLayout(COMMAND)

    def __init__(self, buf=None):
        self.dtype = block_dtype()
        rec = np.zeros((), self.dtype) if buf is None else np.ndarray((), self.dtype, buffer=buf)
        self.ctl = rec["ctl"]
        self.state = Channel(rec["state"])
        self.cmd = Channel(rec["cmd"])
        self.text = rec["text"]
        self.raw = np.ndarray((self.dtype.itemsize,), np.uint8, buffer=buf) if buf is not None else \
            rec.reshape(1).view(np.uint8)

    @staticmethod
    def nbytes() -> int:
        return block_dtype().itemsize


__all__ = ["GrasperBlock", "FAULT_CODES", "CONTROL", "COMMAND", "STATE", "INJECT_NONE", "INJECT_NAN", "FAULT_TEXT",
           "ALERT_TEXT", "get_text", "put_text"]
