"""The shared-memory block between the service's CRTK masters (ros2/crtk_master.py) and their
ROS 2 bridge process (ros2/master_bridge.py).

Declared once as NumPy structured dtypes, as robot/hosted_block.py declares the robot process's
block, and moved with the same one-writer, one-reader ``Channel`` (two slots, sequence counters,
a CRC-32 of the bytes: neither side ever waits for the other). Per device:

* a state channel (bridge -> service), one row of ``STATE`` (float64): written by the bridge's
  executor thread after each ``measured_cp``, gripper or pedal message;
* a command channel (service -> bridge), one row of ``COMMAND``: the tick's force;
* force counters (``FORCE_STATS``, int64 words the bridge's publishing thread alone writes;
  status only, no consistency needed) and two texts: the pose frame the device is locked to,
  and the last rejection.

Times are ``time.monotonic()`` seconds of this machine (both processes share that clock);
positions m and forces N in the master's own frame; quaternions w, x, y, z.
"""
from __future__ import annotations

import numpy as np

from ..robot.hosted_block import TEXT, Channel, RowLayout

#: control words: stop request (service -> bridge), the bridge's heartbeat (polling periods), its
#: pid, ready (its node and every device's topics exist), an error code (1: the bridge failed)
CONTROL = np.dtype([("stop", "i8"), ("beat", "i8"), ("pid", "i8"), ("ready", "i8"), ("failed", "i8")])

#: one device's state (bridge -> service), float64, SI units:
#: ``poses`` accepted measured_cp messages; ``pose_rx`` arrival of the newest measured_cp
#: (accepted or not, monotonic s); ``pose_valid`` 1 if that newest message was accepted;
#: ``p`` its position (m), ``q`` its orientation (w, x, y, z) from the newest accepted message;
#: ``reject`` the reason code of the newest rejection (``REJECT_*``); ``rejected`` (6,) counts by
#: code (non-finite, frame, range, pedal, gripper, unreadable); ``pedals`` accepted pedal messages, ``pressed`` the
#: pedal's state (-1: no message yet, 0 up, 1 pressed), ``buttons`` the pedal message's pressed
#: buttons as a bit mask (bit i: button i); ``grips`` accepted gripper messages
#: (``gripper/measured_js``), ``grip_rx`` arrival of the newest (accepted or not, monotonic s),
#: ``grip_valid`` 1 if that newest one was accepted, ``grasp`` the gripper's angle (rad) from the
#: newest accepted one
STATE = np.dtype([("poses", "f8"), ("pose_rx", "f8"), ("pose_valid", "f8"), ("p", "f8", (3,)), ("q", "f8", (4,)),
                  ("reject", "f8"), ("rejected", "f8", (6,)), ("pedals", "f8"), ("pressed", "f8"),
                  ("buttons", "f8"), ("grips", "f8"), ("grip_rx", "f8"), ("grip_valid", "f8"), ("grasp", "f8")])
#: reasons a message is rejected (index into ``rejected`` is code - 1)
REJECT_NONFINITE, REJECT_FRAME, REJECT_RANGE, REJECT_PEDAL, REJECT_GRIPPER, REJECT_UNREADABLE = 1, 2, 3, 4, 5, 6
REJECT_NAMES = {REJECT_NONFINITE: "non_finite", REJECT_FRAME: "frame_id", REJECT_RANGE: "range",
                REJECT_PEDAL: "pedal", REJECT_GRIPPER: "gripper", REJECT_UNREADABLE: "unreadable"}

#: one device's command (service -> bridge): the tick's sequence number and force (N, master frame)
COMMAND = np.dtype([("seq", "f8"), ("f", "f8", (3,))])

#: the bridge's force counters per device: published, refused as non-finite, zeroed by its
#: watchdog (no new force from the service within its timeout), publish errors
FORCE_STATS = np.dtype([("published", "i8"), ("nonfinite", "i8"), ("zeroed", "i8"), ("errors", "i8")])

#: the two texts per device (UTF-8, ``TEXT`` bytes each): the locked pose frame, the last rejection
FRAME_TEXT, ERROR_TEXT = 0, 1

STATE_LAYOUT = RowLayout(STATE)
COMMAND_LAYOUT = RowLayout(COMMAND)


def _channel(row: np.dtype) -> np.dtype:
    """A one-row ``Channel``: two slots, their counters and the slot to read, each slot's CRC-32."""
    return np.dtype([("data", row, (2, 1)), ("meta", "i8", (4,)), ("sums", "i8", (2,))])


def block_dtype(n: int) -> np.dtype:
    """The whole block for ``n`` devices."""
    return np.dtype([("ctl", CONTROL), ("state", _channel(STATE), (n,)), ("cmd", _channel(COMMAND), (n,)),
                     ("forces", FORCE_STATS, (n,)), ("text", "u1", (n, 2, TEXT))])


class MasterBlock:
    """The block for ``n`` devices over ``buf`` (None: a private zeroed copy). ``ctl`` (the
    control words), ``state[i]`` and ``cmd[i]`` (``Channel`` per device), ``forces`` (n,
    ``FORCE_STATS``), ``text`` (n, 2, TEXT)."""

    def __init__(self, buf, n: int):
        self.n = n
        self.dtype = block_dtype(n)
        rec = np.zeros((), self.dtype) if buf is None else np.ndarray((), self.dtype, buffer=buf)
        self.ctl = rec["ctl"]
        self.state = [Channel(rec["state"][i, ...]) for i in range(n)]
        self.cmd = [Channel(rec["cmd"][i, ...]) for i in range(n)]
        self.forces = rec["forces"]
        self.text = rec["text"]

    @staticmethod
    def nbytes(n: int) -> int:
        return block_dtype(n).itemsize

