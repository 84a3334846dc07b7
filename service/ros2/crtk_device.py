"""One CRTK master device's ROS 2 interface: its topics, its pedal's meaning and the checks on
what it publishes (``CrtkDevice``), shared by the service side (ros2/crtk_master.py) and the
bridge process (ros2/master_bridge.py).

Topics, for a device in namespace ``MTMR`` (each can be set on its own):

* ``/MTMR/measured_cp`` (``geometry_msgs/PoseStamped``): the handle's pose in the device's base
  frame (position m, orientation a unit quaternion), as the dVRK MTM and ROS 2 haptic-device
  drivers publish it;
* ``/MTMR/body/servo_cf`` (``geometry_msgs/WrenchStamped``): pointfence's force on the handle, N,
  in the same base frame (``header.frame_id`` the pose's frame, torque zero). The dVRK applies a
  ``body/servo_cf`` in the base frame's orientation when ``body/set_cf_orientation_absolute`` is
  true, which the bridge publishes (``std_msgs/Bool``) when it first hears the device
  (``orientation_absolute``);
* ``/MTMR/gripper/measured_js`` (``sensor_msgs/JointState``, one position, rad): the handle's
  gripper angle, as the dVRK MTM publishes it: the master's ``grasp``, which the jaw follows
  (``gripper``: ``"auto"`` reads it once heard, a device without a gripper reads 0;
  ``"required"`` holds the arm until it is heard; ``"none"`` does not subscribe);
* the foot pedal, ``sensor_msgs/Joy`` on ``clutch_topic`` (default the dVRK's
  ``/footpedals/clutch``), button ``clutch_button``: 1 pressed, 0 released, 2 released (the
  dVRK's "quick tap", sent after a release).

**What the pedal means.** In pointfence a master's ``clutch`` is True while the operator's pedal
couples the master to the robot (service/masters.py, service/teleop.py): the robot follows only
then; with the pedal up, or no valid sample, the mapped master point stays where it is and the
arm holds, and every re-engagement re-anchors so that coupling never moves the robot (S1).
The dVRK's *clutch* pedal means the opposite: pressed, the MTM is declutched (moved freely
without moving the PSM). ``pedal`` says which: ``"decouples"`` (the default, for
``/footpedals/clutch`` and ``/console/clutch``): coupled while the pedal is released;
``"couples"``: coupled while it is pressed (a dead-man or operator-present pedal, e.g. the
dVRK's ``/footpedals/coag``). Either way the device is decoupled until its first valid pedal
message, and a malformed one (a button index it does not have, a value other than 0, 1, 2)
decouples it.

**Checks** (S6: a bad message changes no command, is counted and named): a pose whose position
or orientation is not finite, a quaternion whose norm is off 1 by more than ``QUAT_TOLERANCE``, a
position farther than ``max_position_m`` from the base frame's origin, or a ``header.frame_id``
other than ``frame_id`` (when ``frame_id`` is not given, the first valid pose's frame is the
device's frame from then on) is rejected, and the device reads as invalid (``ok`` False: the arm
holds) until a valid pose arrives. A device heard from no newer than ``timeout_ms`` ago is
invalid too (S9). A gripper message whose position is empty or not finite, or farther than
``GRASP_LIMIT_RAD`` from 0, is rejected the same way, and once the gripper has been heard (or
from the start, ``"required"``) a gripper silent for ``timeout_ms`` makes the device invalid.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Optional

from pointfence.clients import protocol as P
from pointfence.kernels.errors import InputError

from .master_block import REJECT_FRAME, REJECT_GRIPPER, REJECT_NONFINITE, REJECT_RANGE

PEDAL_MEANINGS = ("decouples", "couples")
#: whether the device's gripper is read (see the module docstring)
GRIPPER_MODES = ("auto", "required", "none")
#: the largest gripper angle accepted, rad (either way from 0)
GRASP_LIMIT_RAD = math.pi
#: how far a pose's quaternion norm may be from 1
QUAT_TOLERANCE = 0.01
#: ceiling of ``max_position_m`` (S7)
MAX_POSITION_CEILING_M = 10.0
#: the Joy values of a pedal button: released, pressed, the dVRK's quick tap (sent after a release)
RELEASED, PRESSED, QUICK_TAP = 0, 1, 2


def _topic(name: str, what: str) -> str:
    t = str(name).strip()
    if not t or any(c.isspace() for c in t) or "//" in t or t.endswith("/"):
        raise InputError(f"{what} = {name!r}; expected a ROS 2 topic name such as /MTMR/measured_cp")
    return t if t.startswith("/") else "/" + t


@dataclass(frozen=True)
class CrtkDevice:
    """A CRTK master device (see the module docstring): ``namespace`` (e.g. ``MTMR``) gives the
    default topics; ``timeout_ms`` the freshness bound of ``measured_cp`` (and of the service's
    forces at the bridge, which zeroes the force after that long without one); ``max_position_m``
    the largest distance of a pose from the device's origin (m)."""

    namespace: str
    pose_topic: Optional[str] = None
    force_topic: Optional[str] = None
    clutch_topic: str = "/footpedals/clutch"
    clutch_button: int = 0
    pedal: str = "decouples"
    frame_id: Optional[str] = None
    force_frame_id: Optional[str] = None
    timeout_ms: int = P.DEFAULT_TIMEOUT_MS
    max_position_m: float = 2.0
    orientation_absolute: bool = True
    gripper_topic: Optional[str] = None
    gripper: str = "auto"

    def __post_init__(self):
        ns = str(self.namespace).strip().strip("/")
        if not ns or any(c.isspace() for c in ns):
            raise InputError(f"CRTK master namespace = {self.namespace!r}; expected a name such as MTMR")
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen: normalised once here)
        set_("namespace", ns)
        set_("pose_topic", _topic(self.pose_topic or f"/{ns}/measured_cp", "pose topic"))
        set_("force_topic", _topic(self.force_topic or f"/{ns}/body/servo_cf", "force topic"))
        set_("clutch_topic", _topic(self.clutch_topic, "clutch topic"))
        set_("gripper_topic", _topic(self.gripper_topic or f"/{ns}/gripper/measured_js", "gripper topic"))
        if self.gripper not in GRIPPER_MODES:
            raise InputError(f"gripper = {self.gripper!r}; expected 'auto' (read the gripper once heard), "
                             "'required' (hold the arm until it is heard) or 'none' (a device without one)")
        if not isinstance(self.clutch_button, int) or isinstance(self.clutch_button, bool) or not 0 <= self.clutch_button < 64:
            raise InputError(f"clutch button = {self.clutch_button!r}; expected the pedal's index in the Joy "
                             "message's buttons, 0-63")
        if self.pedal not in PEDAL_MEANINGS:
            raise InputError(f"pedal = {self.pedal!r}; expected 'decouples' (a clutch pedal: pressed, the master "
                             "moves freely) or 'couples' (a dead-man pedal: pressed, the master drives the robot)")
        if not isinstance(self.timeout_ms, int) or not 1 <= self.timeout_ms <= P.MAX_TIMEOUT_MS:
            raise InputError(f"CRTK master timeout = {self.timeout_ms!r} ms; expected 1-{P.MAX_TIMEOUT_MS} ms "
                             "(a silent master must hold its arm)")
        m = self.max_position_m
        if not isinstance(m, (int, float)) or not 0 < m <= MAX_POSITION_CEILING_M:
            raise InputError(f"max_position_m = {m!r}; expected > 0 and <= {MAX_POSITION_CEILING_M} m")

    @property
    def timeout_s(self) -> float:
        return self.timeout_ms / 1000.0

    @property
    def cf_orientation_topic(self) -> str:
        """Where the dVRK takes ``body/servo_cf``'s frame: next to the force topic."""
        return self.force_topic.rsplit("/", 1)[0] + "/set_cf_orientation_absolute"

    def to_json(self) -> dict:
        return asdict(self)

    # --- the checks (the bridge applies them to each message) ---------------------------------------
    def check_pose(self, frame: str, locked: Optional[str], p, q) -> Optional[tuple]:
        """None if a pose in ``frame`` at position ``p`` (x, y, z m) with quaternion ``q``
        (w, x, y, z) is valid given the frame the device is ``locked`` to (None: not yet); else
        (reason code, message) (codes in ``ros2.master_block``)."""
        if not all(math.isfinite(v) for v in (*p, *q)):
            return REJECT_NONFINITE, (f"{self.pose_topic}: non-finite pose, position {tuple(p)} orientation "
                                      f"{tuple(q)}; the arm holds until a finite pose arrives")
        want = self.frame_id if self.frame_id is not None else locked
        if want is not None and frame != want:
            return REJECT_FRAME, (f"{self.pose_topic}: header.frame_id {frame!r}; expected {want!r} (the device's "
                                  "base frame); the arm holds until a pose in that frame arrives")
        r = math.sqrt(sum(v * v for v in p))
        if r > self.max_position_m:
            return REJECT_RANGE, (f"{self.pose_topic}: position {tuple(round(v, 4) for v in p)} is {r:.3f} m from "
                                  f"the device's origin; at most max_position_m = {self.max_position_m} m")
        nq = math.sqrt(sum(v * v for v in q))
        if abs(nq - 1.0) > QUAT_TOLERANCE:
            return REJECT_RANGE, (f"{self.pose_topic}: orientation quaternion of norm {nq:.4f}; expected a unit "
                                  "quaternion")
        return None

    def check_grip(self, position) -> Optional[tuple]:
        """None if a gripper message's ``position`` (its joint angles, rad) holds a valid angle
        (the first); else (reason code, message)."""
        if len(position) == 0:
            return REJECT_GRIPPER, (f"{self.gripper_topic}: no position; expected the gripper's angle (rad) as "
                                    "position[0]")
        g = float(position[0])
        if not math.isfinite(g):
            return REJECT_NONFINITE, (f"{self.gripper_topic}: non-finite gripper angle {g}; the arm holds until a "
                                      "finite one arrives")
        if abs(g) > GRASP_LIMIT_RAD:
            return REJECT_GRIPPER, (f"{self.gripper_topic}: gripper angle {g:.4f} rad; expected at most "
                                    f"{GRASP_LIMIT_RAD:.4f} rad either way")
        return None

    def pedal_state(self, buttons) -> Optional[int]:
        """The pedal's state (1 pressed, 0 up) from a Joy message's ``buttons``, or None when the
        message has no button ``clutch_button`` or an unknown value there."""
        if len(buttons) <= self.clutch_button:
            return None
        v = int(buttons[self.clutch_button])
        if v == PRESSED:
            return 1
        if v in (RELEASED, QUICK_TAP):
            return 0
        return None

    def coupled(self, pressed: float) -> bool:
        """Whether the pedal state ``pressed`` (-1 unknown, 0 up, 1 pressed) couples the master."""
        if pressed < 0:
            return False
        return (pressed == 1) == (self.pedal == "couples")
