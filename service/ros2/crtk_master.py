"""CRTK masters over ROS 2: the dVRK MTM and ROS 2 haptic-device drivers as the haptic loop's
masters (service/masters.py ``Master``: ``poll``, ``position``, ``clutch``, ``buttons``, ``ok``,
``send_force``).

Each device (ros2/crtk_device.py ``CrtkDevice``: its topics, its pedal's meaning, its checks)
gives a ``CrtkMaster``: ``position`` the handle's position from ``measured_cp`` (m, the device's
base frame, which ``[teleop] T_world_master`` registers in the world), ``orientation`` its
quaternion (w, x, y, z: the tool's orientation follows it, service/teleop.py), ``grasp`` the
gripper's angle from ``gripper/measured_js`` (rad: the jaw follows it; 0 for a device whose
gripper is not heard, see crtk_device.py's ``gripper``), ``clutch``
whether the foot pedal couples the master to the robot (see crtk_device.py for what "pressed"
means), ``buttons`` the pedal message's pressed buttons (bit mask), and ``send_force`` the
tick's force back on ``body/servo_cf`` (N, the same base frame). ``ok`` is False (the arm holds,
``HoldReason.MASTER``; S6, S9) until the first valid pose, when the newest ``measured_cp`` is
older than the device's ``timeout_ms`` (a silent device, a dead driver or bridge), and when the
newest one was rejected (non-finite, a wrong ``frame_id``, out of range); and likewise for the
gripper once it has been heard (from the start with ``gripper = "required"``): a rejected or
stale gripper message makes the sample invalid, so the jaw holds with the arm.

**Where rclpy runs: a process of its own (measured).** The MTM publishes ``measured_cp`` near
1 kHz and the tick sends a force every millisecond. Handled in the service's process, each
message is a Python callback (deserialisation, the executor's wait-set, the checks) and each
force a Python publish, all competing with the 1 kHz loop thread for the interpreter lock. On
the 2-core development VM (shared, load about 2.4), 6 s of a live run (``LiveRun``, one proxy,
canned frames; the default OpenCL backend on PoCL; a master circling into the fixture, from a ``sim-master`` process
at 1 kHz for the two ROS runs) gave, as deadline misses and lateness p99:

=====================================================  ==============  ============
master                                                 loop misses     late p99
=====================================================  ==============  ============
scripted, no ROS                                       0.62 %          134 us
rclpy in the service's process (callback + publish)    15.6 %          2,822 us
this module (bridge process, shared memory)            0.98 %          123 us
=====================================================  ==============  ============

(the in-process run also tripped the tick watchdog; a second run at load 11 gave 1.55 %, 15.7 %
and 1.03 % misses, late p99 112, 3,882 and 84 us). So the rclpy side runs in
a child process (ros2/master_bridge.py) and hands over through shared memory
(ros2/master_block.py, the robot process's double-buffered ``Channel``): the tick's ``poll``
copies one CRC-checked record (a few microseconds, no lock, no allocation) and ``send_force``
writes one; neither ever waits for the bridge.

The bridge is watched from both sides: a bridge that dies or stops stops renewing the pose's
arrival time, so the device reads stale within ``timeout_ms`` (``ok`` False); a service that
stops sending forces has its last force zeroed by the bridge after ``timeout_ms``, and a bridge
that ends (told to, its parent gone, its node failed) publishes a zero wrench first.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from multiprocessing import shared_memory
from typing import Optional, Sequence

import numpy as np

from pointfence.kernels.errors import InputError

from ..masters import Master
from ..robot.hosted_block import get_text
from .crtk_device import CrtkDevice
from .master_block import COMMAND_LAYOUT, ERROR_TEXT, FRAME_TEXT, REJECT_NAMES, STATE_LAYOUT, MasterBlock

#: how long the bridge may take to create its node and topics (rclpy's import included), s
START_TIMEOUT_S = 30.0


class CrtkMasterHost:
    """The bridge process for ``devices`` (``CrtkDevice`` or keyword dicts of one) and one
    ``CrtkMaster`` per device (``masters``, in order). ``env``: extra environment for the bridge
    (a DDS environment; default this process's). ``close()`` stops the bridge (it zeroes every
    device's force first) and frees the shared memory; the bridge also ends with this process."""

    def __init__(self, devices: Sequence, env: Optional[dict] = None, start_timeout_s: float = START_TIMEOUT_S):
        self.devices = [d if isinstance(d, CrtkDevice) else CrtkDevice(**dict(d)) for d in devices]
        if not self.devices:
            raise InputError("CRTK masters: no device; expected at least one namespace such as MTMR")
        topics = [d.pose_topic for d in self.devices]
        if len(set(topics)) != len(topics):
            raise InputError(f"CRTK masters: pose topics {topics} repeat; each master needs its own measured_cp")
        self.n = len(self.devices)
        self._shm = shared_memory.SharedMemory(create=True, size=MasterBlock.nbytes(self.n))
        self.block = MasterBlock(self._shm.buf, self.n)
        self.closed = False
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "pointfence.service.ros2.master_bridge", self._shm.name,
             json.dumps([d.to_json() for d in self.devices]), str(os.getpid())],
            stdin=subprocess.DEVNULL, env=None if env is None else {**os.environ, **env})
        end = time.monotonic() + start_timeout_s
        while int(self.block.ctl["ready"]) == 0:
            code = self._proc.poll()
            if code is not None or int(self.block.ctl["failed"]) or time.monotonic() > end:
                why = get_text(self.block.text[0, ERROR_TEXT]) or f"exit code {code}"
                self.close()
                raise RuntimeError(f"the CRTK master bridge process did not start ({why}); check that ROS 2 is "
                                   "installed (pip install 'pointfence[ros2]') and the DDS environment")
            time.sleep(0.01)
        self.masters = [CrtkMaster(self, i) for i in range(self.n)]

    @property
    def alive(self) -> bool:
        return not self.closed and self._proc.poll() is None

    def status(self) -> dict:
        return {"bridge": {"pid": self._proc.pid, "alive": self.alive, "exit_code": self._proc.poll(),
                           "heartbeat": int(self.block.ctl["beat"]) if not self.closed else None},
                "devices": [m.status() for m in self.masters] if not self.closed else []}

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.block.ctl["stop"] = 1
        try:
            self._proc.wait(timeout=3.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        for m in getattr(self, "masters", []):
            m.detach()
        del self.block
        try:
            self._shm.close()
        except BufferError:   # a view still alive: the mapping goes when it does
            pass
        self._shm.unlink()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class CrtkMaster(Master):
    """Device ``i`` of ``host`` as a haptic-loop master (see the module docstring).

    ``poll_also``: an object whose ``tick(t)`` runs once per tick before this master is read
    (``serve`` passes its UDP hub when a ROS 2 master takes a UDP slot, as the ITP arms do)."""

    name = "crtk"

    def __init__(self, host: CrtkMasterHost, i: int, poll_also=None):
        super().__init__()
        self.host, self.i = host, i
        self.device = dev = host.devices[i]
        self.name = f"crtk:{dev.namespace}"
        self.poll_also = poll_also
        self.ok = False
        self.clutch = False
        self.orientation = np.array([1.0, 0.0, 0.0, 0.0])   #: w, x, y, z (device base frame)
        self._state = host.block.state[i]
        self._cmd = host.block.cmd[i]
        self._row = np.zeros(STATE_LAYOUT.size)
        self._row[STATE_LAYOUT.pressed] = -1.0
        self._rv = memoryview(self._row)           # (elements read as Python floats)
        self._pos = memoryview(self.position)
        self._ori = memoryview(self.orientation)
        self._cmd_row = np.zeros(COMMAND_LAYOUT.size)
        self._cv = memoryview(self._cmd_row)
        self._seq = 0
        self._timeout = dev.timeout_s
        self._couples = dev.pedal == "couples"
        self._grip = dev.gripper != "none"
        self._grip_required = dev.gripper == "required"
        L = STATE_LAYOUT
        self._i_poses, self._i_rx, self._i_valid, self._i_pressed, self._i_buttons = (
            L.poses, L.pose_rx, L.pose_valid, L.pressed, L.buttons)
        self._i_grips, self._i_grip_rx, self._i_grip_valid, self._i_grasp = L.grips, L.grip_rx, L.grip_valid, L.grasp
        self._p0, self._q0 = L.p.start, L.q.start
        #: ticks that found the newest pose (or gripper message) too old, or rejected (the service
        #: side's counts)
        self.stale_ticks = 0
        self.invalid_ticks = 0

    def poll(self, t: float) -> None:
        """The tick's read (loop time ``t``, s): copy the bridge's newest state record (no wait:
        a record being written is skipped and the previous one kept), then decide validity
        from its arrival time on this machine's monotonic clock (the pose's and, once heard or
        when required, the gripper's)."""
        hub = self.poll_also
        if hub is not None and t != hub.t:
            hub.tick(t)
        self._state.read(self._rv)
        r = self._rv
        p0, q0 = self._p0, self._q0
        pos, ori = self._pos, self._ori
        pos[0], pos[1], pos[2] = r[p0], r[p0 + 1], r[p0 + 2]
        ori[0], ori[1], ori[2], ori[3] = r[q0], r[q0 + 1], r[q0 + 2], r[q0 + 3]
        pressed = r[self._i_pressed]
        self.clutch = pressed >= 0 and (pressed == 1.0) == self._couples
        self.buttons = int(r[self._i_buttons])
        now = time.monotonic()
        heard = r[self._i_grip_rx] > 0.0                 # (a gripper message's arrival is set)
        grip = self._grip and (heard or self._grip_required)
        if grip:
            self.grasp = r[self._i_grasp]               # (0 until one is accepted; then the newest accepted)
        if r[self._i_poses] == 0 or (grip and not heard):
            self.ok = False
        elif now - r[self._i_rx] > self._timeout or (grip and now - r[self._i_grip_rx] > self._timeout):
            self.ok = False
            self.stale_ticks += 1
        elif r[self._i_valid] != 1.0 or (grip and r[self._i_grip_valid] != 1.0):
            self.ok = False
            self.invalid_ticks += 1
        else:
            self.ok = True

    def send_force(self, f: np.ndarray) -> None:
        """Hand force ``f`` (3,) N (the device's base frame) to the bridge, which publishes it on
        ``body/servo_cf``."""
        self.force[:] = f
        self._seq += 1
        c = self._cv
        c[0] = self._seq
        x, y, z = f
        c[1], c[2], c[3] = float(x), float(y), float(z)
        if self._cmd is not None:
            self._cmd.write(c)

    def detach(self) -> None:
        """The host closed: no more sends to its shared memory."""
        self._cmd = None
        self._state = _Closed()
        self.ok = False

    def status(self) -> dict:
        """The device's topics, its counts (poses, pedal messages, rejections by reason, forces)
        and the bridge's last rejection message (the bridge's texts and force counts only while
        the host is open)."""
        r = self._row
        L = STATE_LAYOUT
        d = self.device
        out = {"namespace": d.namespace, "pose_topic": d.pose_topic, "force_topic": d.force_topic,
               "clutch_topic": d.clutch_topic, "clutch_button": d.clutch_button, "pedal": d.pedal,
               "gripper_topic": d.gripper_topic, "gripper": d.gripper, "grips": int(r[L.grips]),
               "grasp": float(r[L.grasp]),
               "ok": bool(self.ok), "clutch": bool(self.clutch), "poses": int(r[L.poses]), "pedals": int(r[L.pedals]),
               "rejected": {REJECT_NAMES[k + 1]: int(v) for k, v in enumerate(r[L.rejected])},
               "stale_ticks": self.stale_ticks, "invalid_ticks": self.invalid_ticks, "forces_sent": self._seq}
        if not self.host.closed:
            blk = self.host.block
            stats = blk.forces[self.i]
            out.update({"frame_id": get_text(blk.text[self.i, FRAME_TEXT]),
                        "last_rejection": get_text(blk.text[self.i, ERROR_TEXT]),
                        "forces_published": int(stats["published"]), "forces_nonfinite": int(stats["nonfinite"]),
                        "forces_zeroed": int(stats["zeroed"]), "force_errors": int(stats["errors"])})
        return out


class _Closed:
    """The state channel of a closed host: reads nothing (the record keeps its last copy)."""

    @staticmethod
    def read(out, tries: int = 8) -> bool:
        return False


def crtk_masters(namespaces: Sequence[str], env: Optional[dict] = None, **common) -> CrtkMasterHost:
    """A host for one device per namespace, every device with the settings ``common``
    (``CrtkDevice``'s keywords)."""
    return CrtkMasterHost([CrtkDevice(namespace=ns, **common) for ns in namespaces], env=env)
