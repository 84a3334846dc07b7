"""A real Raven II driven over ITP (``[robot] model = "raven2-itp"``): pointfence is its master console.

The Raven II's control software takes its master's commands as UDP ``u_struct`` packets (its
"ITP" protocol, robot/raven_itp_wire.py; clients/PROTOCOL.md quotes the layout). Each ``step``
(the loop rate) sends one packet to ``address``: the position increment since the last packet
(micrometres, integers, in the ITP frame that the Raven's ``fromITP`` rotates into the arm's base
frame), the rotation increment (a quaternion in the same frame), the grasp increment
(milliradians), ``surgeon_mode`` (the pedal), the sequence number and the checksum.

What the Raven does with them (local_io.cpp ``teleopIntoDS1``): it adds the increments to its
position command and multiplies its orientation command by the rotation, only while the pedal
is down; while it is up it re-seats its command on where the arm is (``updateMasterRelativeOrigin``).
So this arm integrates what it sends exactly as the Raven does (integers, the same rotation
products): the integrated pose, from the pose at the last engage, is what the Raven was told.
Increments are whole micrometres; the fraction left over is carried into the next packet, so the
integrated position stays within 0.5 um of the setpoint (per axis) when the setpoint moves no
faster than ``max_speed`` (m/s) and ``max_angular_speed`` (rad/s): faster moves are streamed at
those rates (the rest follows in later packets).

Measured pose. The Raven's ``v_struct`` (sent only by a Raven built with ``NET_SEND``) carries
no pose: runlevel, forces, joint flags and the last sequence it took. ``measured_cp`` is therefore
always the integrated commanded pose in the world frame (``measured_source`` says so:
"commanded, no feedback"). With ``feedback_port`` the arm listens there for the Raven's
``v_struct`` and uses it as the link's health: a packet of the wrong size, an impossible runlevel
or one acknowledging a sequence never sent faults the arm, as do an E-STOP or INIT runlevel and
silence longer than ``feedback_timeout_s``.

Surgeon mode is 1 only while the arm is ENABLED: the service resumes it when the master couples
(it starts HOLDING: uncoupled) and holds it when it decouples. ``hold()``, ``fault()``, a refused
command (non-finite, malformed, outside the workspace: InputError, and the arm holds), a socket
error and a feedback failure all turn it off in the next packet, with zero increments; it stays
off until the service resumes (HOLDING) or enables (FAULT) the arm, and increments restart from
the integrated pose (the setpoint is re-seated on it), so re-engaging never jumps.

At start (``connect``) the arm sends ``sync_packets`` surgeon-off packets at the control rate
(1001 by default: whatever sequence the Raven last saw, it then takes ours, network_layer.cpp),
and waits up to ``connect_timeout_s`` for the first valid feedback where feedback is configured.

THE ITP LINK IS UNAUTHENTICATED (the published Raven II vulnerability): anyone on the network can
send the Raven increments, or this arm feedback (only the Raven's address is listened to). Put the
Raven and this computer on a dedicated network; a non-loopback address logs a warning saying so.

Threads: none. ``step`` (the tick, or the robot process's period) sends one datagram (non-blocking)
and reads the waiting feedback (non-blocking); nothing else touches the socket.
"""
from __future__ import annotations

import ipaddress
import logging
import math
import socket
import time
from typing import Optional

import numpy as np

from pointfence.kernels.errors import InputError

from .. import limits
from ..ros2.crtk_wire import matrix_to_quat, quat_to_matrix
from . import raven_itp_wire as wire
from .base import Robot, RobotMode

log = logging.getLogger("pointfence.robot.raven_itp")

#: what ``measured_cp`` is (the Raven's v_struct carries no pose)
MEASURED_SOURCE = "commanded, no feedback"
#: the jaw (grasp) limits, rad (the Raven's integrated grasp command, local_io.cpp)
JAW_MIN, JAW_MAX = wire.GRASP_MIN_MRAD / 1000.0, wire.GRASP_MAX_MRAD / 1000.0


def parse_address(address) -> tuple:
    """``"host:port"`` -> (IPv4 address, port); InputError saying what is wrong."""
    if not isinstance(address, str) or not address:
        raise InputError(f"address = {address!r}; expected the Raven II's \"host:port\" (its network layer listens "
                         "on UDP port 36000: e.g. \"192.168.0.10:36000\")")
    host, sep, port = address.rpartition(":")
    if not sep or not host:
        raise InputError(f"address = {address!r} has no port; expected \"host:port\" (the Raven II listens on UDP "
                         f"port 36000: \"{address}:36000\")")
    try:
        p = int(port)
    except ValueError:
        raise InputError(f"address = {address!r}: port {port!r} is not a number; expected \"host:port\"") from None
    if not 1 <= p <= 65535:
        raise InputError(f"address = {address!r}: port {p} is outside 1..65535")
    try:
        ip = socket.getaddrinfo(host, p, socket.AF_INET, socket.SOCK_DGRAM)[0][4][0]
    except (socket.gaierror, UnicodeError) as e:
        raise InputError(f"address = {address!r}: host {host!r} does not resolve to an IPv4 address ({e})") from None
    return ip, p


class RavenItpRobot(Robot):
    """A Raven II arm driven over ITP (module docstring). World = the service's frame; the Raven's
    arm base frame (its "robot 0 frame", micrometres on the wire) is ``T_world_base`` in it.

    Options (``[robot] model = "raven2-itp"``): ``address`` ("host:port" of the Raven's network
    layer), ``arm`` ("right": green, u_struct slot 1; "left": gold, slot 0), ``T_world_base``,
    ``x0`` (the integrated pose's start position, world, m; default the base origin),
    ``workspace_min``/``workspace_max`` (world, m), ``max_speed`` (m/s), ``max_angular_speed``
    (rad/s), ``feedback_port`` (0: none), ``feedback_timeout_s``, ``sync_packets``,
    ``connect_timeout_s``, ``control_rate_hz``. ``connect=False`` opens no socket: a copy for
    geometry and checks (the service's side of an arm in the robot process).
    """

    model = "raven2-itp"
    #: a real arm: the robot process cannot place it
    simulated = False

    def __init__(self, *, address: str = "", arm: str = "right", T_world_base=None, x0=None, workspace_min=None,
                 workspace_max=None, max_speed: float = 0.2, max_angular_speed: float = 6.0, feedback_port: int = 0,
                 feedback_timeout_s: float = 0.05, sync_packets: int = wire.SYNC_PACKETS,
                 connect_timeout_s: float = 5.0, control_rate_hz: float = 1000.0, connect: bool = True):
        self.raven = parse_address(address)
        if arm not in wire.ARM_SLOT:
            raise InputError(f"arm = {arm!r}; expected \"right\" (green, u_struct slot 1) or \"left\" (gold, slot 0)")
        for name, v in (("max_speed", max_speed), ("max_angular_speed", max_angular_speed),
                        ("connect_timeout_s", connect_timeout_s)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
                raise InputError(f"{name} = {v!r}; expected a finite number > 0")
        for name, v, hi in (("feedback_port", feedback_port, 65535), ("sync_packets", sync_packets, 100000)):
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= hi:
                raise InputError(f"{name} = {v!r}; expected an integer 0..{hi}")
        self.feedback_timeout_s = limits.check("robot.measured_timeout_s", feedback_timeout_s, "feedback_timeout_s")
        super().__init__(["jaw"], [JAW_MIN], [JAW_MAX], T_world_base=T_world_base, workspace_min=workspace_min,
                         workspace_max=workspace_max, control_rate_hz=control_rate_hz)
        self.arm = arm
        self.slot = wire.ARM_SLOT[arm]
        self._M = wire.ITP_TO_BASE[arm]          # ITP frame -> base frame (a signed permutation)
        self._Ml = self._M.tolist()
        self.max_speed = float(max_speed)
        self.max_angular_speed = float(max_angular_speed)
        self.feedback_port = feedback_port
        self.sync_packets = sync_packets
        self.measured_source = MEASURED_SOURCE
        # the integrated pose (base frame): origin (m) + whole micrometres sent since, rotation
        self._origin = [0.0, 0.0, 0.0]
        self._acc_um = [0, 0, 0]
        self._R = np.eye(3)
        self._grasp_mrad = 0                     # integrated grasp command sent (mrad)
        self._jaw_target = 0.0                   # rad
        if x0 is not None:
            from .base import as_vector

            p = self._T_base_world @ np.append(as_vector(x0, 3, "x0"), 1.0)
            self._origin[:] = p[:3].tolist()
        self._T_base = np.eye(4)                 # scratch: a pose in the base frame
        self._publish_measured()
        np.copyto(self._T_d, self._T_meas)
        self._mode = RobotMode.HOLDING           # uncoupled until the service resumes it
        # the link
        self.sequence = 0                        # the last sequence sent
        self.sent = 0                            # packets sent
        self.send_errors = 0
        self.surgeon_mode = wire.SURGEON_DISENGAGED   # in the last packet sent
        self._buf = bytearray(wire.ITP_SIZE)
        self._rx = bytearray(2048)
        self.feedback = None                     # the newest valid v_struct's fields
        self.feedback_counters = {"received": 0, "accepted": 0, "source": 0, "stale": 0}
        self._fb_t = None                        # time.monotonic() of the newest valid v_struct
        self._fb_bad: Optional[str] = None       # a corrupt v_struct since the last check
        self._synced = False                     # the sync packets are out (the Raven's last_sequence is ours)
        self.exposed = not ipaddress.ip_address(self.raven[0]).is_loopback
        self.sock = None
        if connect:
            self._open()
            self._connect(connect_timeout_s)

    # ---------------------------------------------------------------- the link
    def _open(self) -> None:
        if self.exposed:
            log.warning("Raven II ITP link to %s:%d is not loopback: ITP is UNAUTHENTICATED, anyone on that network "
                        "can move the Raven or feed this arm its feedback; use a dedicated network", *self.raven)
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            s.setblocking(False)
            if self.feedback_port:
                s.bind(("0.0.0.0" if self.exposed else "127.0.0.1", self.feedback_port))
        except OSError as e:
            s.close()
            raise InputError(f"feedback_port = {self.feedback_port}: cannot listen there ({e}); choose a free port "
                             "(the one the Raven sends its v_struct to)") from None
        self.sock = s

    def _connect(self, timeout_s: float) -> None:
        """Send the sync packets (surgeon mode off) at the control rate; with feedback, wait up to
        ``timeout_s`` for a valid v_struct (else FAULT saying so)."""
        period = self.control_period
        t0 = time.monotonic()
        for k in range(self.sync_packets):
            self._send()
            self._read_feedback()
            wait = t0 + (k + 1) * period - time.monotonic()
            if wait > 0:
                time.sleep(wait)
        self._synced = True
        if self.feedback_port:
            end = time.monotonic() + timeout_s
            why = self._link_problem()
            while why is not None and time.monotonic() < end:
                self._send()
                time.sleep(period)
                why = self._link_problem()
            if why is not None:
                self.fault(f"{why} (after waiting {timeout_s:g} s: is the Raven built with NET_SEND and sending to "
                           f"this computer's port {self.feedback_port}?)")

    def _send(self) -> None:
        """One u_struct: increments while ENABLED, else surgeon mode off with zero increments."""
        seq = (self.sequence + 1) & 0xFFFFFFFF
        if seq == 0:
            seq = 1                                  # 0 asks the Raven to reflect the packet
        resync = seq == 1 and self.sequence != 0     # after the wrap the Raven drops packet 1 (its reset branch)
        on = self._mode is RobotMode.ENABLED and not resync
        if on:
            kept = (self._acc_um[:], self._R, self._grasp_mrad)
            d_itp, q_itp, grasp = self._increments()
        else:
            d_itp, q_itp, grasp = (0, 0, 0), (0.0, 0.0, 0.0, 1.0), 0
        mode = wire.SURGEON_ENGAGED if on else wire.SURGEON_DISENGAGED
        wire.pack_u(self._buf, seq, self.slot, d_itp, q_itp, -grasp, mode)
        self.sequence = seq
        self.surgeon_mode = mode
        if self.sock is None:
            return
        try:
            self.sock.sendto(self._buf, self.raven)
            self.sent += 1
        except OSError as e:
            self.send_errors += 1
            if on:                                   # it never left: the Raven did not take these increments
                self._acc_um[:], self._R, self._grasp_mrad = kept
                self._q[0] = self._grasp_mrad / 1000.0
                self._publish_measured()
            if self._mode is not RobotMode.FAULT:
                self.fault(f"ITP send to {self.raven[0]}:{self.raven[1]} failed: {e}")

    def _increments(self) -> tuple:
        """The increments towards the setpoint (rate-limited), integrated here as the Raven
        integrates them: (position, ITP frame, um), (rotation, ITP frame, x y z w), grasp (mrad)."""
        T = self._T_base
        if self._identity_mount:
            np.copyto(T, self._T_d)
        else:
            np.matmul(self._T_base_world, self._T_d, out=T)
        o, acc = self._origin, self._acc_um
        d = [T[i, 3].item() - (o[i] + acc[i] * 1e-6) for i in range(3)]
        n = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        lim = self.max_speed * self.control_period
        if n > lim:
            d = [x * (lim / n) for x in d]
        d_um = [int(round(x * 1e6)) for x in d]
        acc[0] += d_um[0]
        acc[1] += d_um[1]
        acc[2] += d_um[2]
        M = self._Ml                                  # d_itp = M^T d_base (exact: a signed permutation)
        d_itp = tuple(int(M[0][j] * d_um[0] + M[1][j] * d_um[1] + M[2][j] * d_um[2]) for j in range(3))
        # rotation increment R_inc = R_target R^T, at most max_angular_speed * period
        R_inc = T[:3, :3] @ self._R.T
        x, y, z, w = matrix_to_quat(R_inc)
        if w < 0:
            x, y, z, w = -x, -y, -z, -w
        ang = 2.0 * math.atan2(math.sqrt(x * x + y * y + z * z), w)
        alim = self.max_angular_speed * self.control_period
        if ang > alim:
            s = math.sin(alim / 2) / math.sin(ang / 2)
            x, y, z, w = x * s, y * s, z * s, math.cos(alim / 2)
        q_itp = (M[0][0] * x + M[1][0] * y + M[2][0] * z, M[0][1] * x + M[1][1] * y + M[2][1] * z,
                 M[0][2] * x + M[1][2] * y + M[2][2] * z, w)
        # the Raven: Q_ori = (M q_itp M^-1) * Q_ori; the same product here, on matrices
        Rq = np.empty((4, 4))
        quat_to_matrix(x, y, z, w, Rq)
        self._R = Rq[:3, :3] @ self._R
        g = int(round(1000.0 * self._jaw_target)) - self._grasp_mrad
        self._grasp_mrad += g
        self._q[0] = self._grasp_mrad / 1000.0
        self._publish_measured()
        return d_itp, q_itp, g

    def _publish_measured(self) -> None:
        """The integrated pose (base frame) into ``_T_meas`` (world)."""
        T = self._T_base
        T[:3, :3] = self._R
        o, acc = self._origin, self._acc_um
        T[0, 3], T[1, 3], T[2, 3] = o[0] + acc[0] * 1e-6, o[1] + acc[1] * 1e-6, o[2] + acc[2] * 1e-6
        T[3] = (0.0, 0.0, 0.0, 1.0)
        if self._identity_mount:
            np.copyto(self._T_meas, T)
        else:
            np.matmul(self._T_world_base, T, out=self._T_meas)
        self._T_meas_ok = True

    def _read_feedback(self) -> None:
        """Take every waiting v_struct (non-blocking): a corrupt one is remembered in ``_fb_bad``."""
        if self.sock is None or not self.feedback_port:
            return
        while True:
            try:
                n, addr = self.sock.recvfrom_into(self._rx)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:            # (an ICMP error of an earlier send, on some systems)
                self._fb_bad = f"ITP socket error: {e}"
                return
            c = self.feedback_counters
            c["received"] += 1
            if addr[0] != self.raven[0]:
                c["source"] += 1           # not the Raven: ignored (a spoofer must not fault the arm)
                continue
            if n != wire.V_SIZE:
                self._fb_bad = f"corrupt feedback from the Raven: {n} bytes; a v_struct has {wire.V_SIZE}"
                continue
            v = wire.unpack_v(self._rx)
            seq, last_seq, runlevel = v[0], v[1], v[7]
            if runlevel not in wire.RUNLEVELS:
                self._fb_bad = f"corrupt feedback from the Raven: runlevel {runlevel}; expected 0..3"
                continue
            if self._synced and last_seq and wire.newer(last_seq, self.sequence):
                self._fb_bad = (f"corrupt feedback from the Raven: it took packet {last_seq}, but the last one sent "
                                f"is {self.sequence}")
                continue
            if self.feedback is not None and seq and not wire.newer(seq, self.feedback[0]):
                c["stale"] += 1
                continue
            c["accepted"] += 1
            self.feedback = v
            self._fb_t = time.monotonic()

    def _link_problem(self) -> Optional[str]:
        """Why the Raven may not be commanded now (None: it may); takes the waiting feedback."""
        self._read_feedback()
        if not self.feedback_port:
            return None
        if self._fb_bad is not None:
            why, self._fb_bad = self._fb_bad, None
            return why
        if self._fb_t is None:
            return f"no feedback from the Raven on port {self.feedback_port} yet"
        age = time.monotonic() - self._fb_t
        if age > self.feedback_timeout_s:
            return (f"no feedback from the Raven for {1e3 * age:.0f} ms (feedback_timeout_s = "
                    f"{1e3 * self.feedback_timeout_s:.0f} ms)")
        runlevel = self.feedback[7]
        if runlevel not in wire.RUNLEVELS_READY:
            return f"the Raven is in runlevel {runlevel} ({wire.RUNLEVELS[runlevel]}); expected PEDAL UP or PEDAL DOWN"
        return None

    # ---------------------------------------------------------------- the Robot hooks
    def _fk(self, q, out):
        raise InputError("a Raven II over ITP has its kinematics in its own controller: pointfence has no forward "
                         "kinematics for it (measured_cp is the integrated commanded pose)")

    def _ik(self, T_base, seed):
        raise InputError("a Raven II over ITP takes Cartesian increments: servo_cp sends the pose itself")

    def _stop(self) -> None:
        """A FAULT sends surgeon mode off from the next packet (``_send``)."""

    def _advance(self, dt: float) -> None:
        why = self._link_problem() if self.sock is not None else None
        if why is not None and self._mode is not RobotMode.FAULT:
            self.fault(why)
        self._send()

    def step(self, dt: float = 1e-3) -> None:
        """One packet to the Raven (and the feedback read), then the time advances by ``dt`` (s).
        An arm with no connection (``connect=False``) only advances its time."""
        if not (dt > 0.0) or dt == math.inf:
            raise InputError(f"step: dt = {dt!r}; expected a finite number > 0")
        if self.sock is not None:
            self._advance(dt)
        self.t += dt

    # ---------------------------------------------------------------- commands
    def servo_cp(self, T) -> bool:
        """Stream a Cartesian setpoint (a 4x4 world pose, or a position (3,) with the setpoint's
        orientation); it leaves, as increments, from the next ``step``. A malformed, non-finite or
        out-of-workspace pose raises InputError (counted) and holds the arm: surgeon mode goes
        off in the next packet. False, nothing sent, unless ENABLED."""
        try:
            pose = self.checked_setpoint(T, out=self._scratch4)
        except InputError:
            self.hold()
            raise
        if self._mode is not RobotMode.ENABLED:
            self.ignored_commands += 1
            return False
        np.copyto(self._T_d, pose)
        return True

    jaw_limits = (JAW_MIN, JAW_MAX)

    def measured_jaw(self) -> float:
        """The integrated grasp command the Raven was sent (rad): what it was told, as for the pose."""
        return self._q[0]

    def servo_jaw(self, angle: float) -> bool:
        """The jaw (grasp) angle (rad, within the Raven's -10 deg .. 90 deg), sent as grasp
        increments from the next ``step``. InputError on a non-finite angle or one outside."""
        if isinstance(angle, bool) or not isinstance(angle, (int, float)) or not math.isfinite(angle):
            self.hold()
            self._reject(f"servo_jaw: angle = {angle!r}; expected a finite number of radians")
        if not JAW_MIN <= angle <= JAW_MAX:
            self.hold()
            self._reject(f"servo_jaw: angle = {angle:.6g} rad is outside the Raven's grasp range "
                         f"[{JAW_MIN:g}, {JAW_MAX:g}] rad")
        if self._mode is not RobotMode.ENABLED:
            self.ignored_commands += 1
            return False
        self._jaw_target = float(angle)
        return True

    def servo_jp(self, q) -> bool:
        raise InputError("servo_jp is not sent to a Raven II over ITP: pointfence streams Cartesian increments")

    def _seat(self) -> None:
        np.copyto(self._T_d, self._T_meas)
        self._jaw_target = self._grasp_mrad / 1000.0
        self._q_d[0] = self._q[0]

    def hold(self) -> None:
        """Surgeon mode off from the next packet; the setpoint moves onto the integrated pose."""
        if self._mode is RobotMode.ENABLED:
            self._seat()
            self._mode = RobotMode.HOLDING

    def enable(self) -> None:
        """Clear a FAULT (or leave HOLDING) only while the link is healthy (with feedback: fresh,
        valid, the Raven ready); else stay and say why in ``last_error``. The setpoint re-seats
        on the integrated pose: increments restart from there."""
        if self.sock is not None:
            why = self._link_problem()
            if why is not None:
                self.last_error = f"enable refused: {why}"
                return
        if self._mode is not RobotMode.ENABLED:
            self._seat()
            self._fault = None
        self._mode = RobotMode.ENABLED

    def reset(self, q=None) -> None:
        """A real arm cannot be placed: with ``q`` an InputError; without, the setpoint re-seats."""
        if q is not None:
            raise InputError("reset(q): a Raven II over ITP cannot be placed; move it with its master")
        self._seat()

    # ---------------------------------------------------------------- extras
    @property
    def connected(self) -> bool:
        return self.sock is not None

    def link_status(self) -> dict:
        """The link for status: what measured_cp is, packets, the Raven's newest feedback."""
        fb = self.feedback
        return {"measured": self.measured_source, "address": f"{self.raven[0]}:{self.raven[1]}", "arm": self.arm,
                "sequence": self.sequence, "sent": self.sent, "send_errors": self.send_errors,
                "surgeon_mode": self.surgeon_mode, "exposed": self.exposed,
                "feedback": None if fb is None else {"runlevel": wire.RUNLEVELS[fb[7]], "last_sequence": fb[1],
                                                     "force": [list(fb[4]), list(fb[5]), list(fb[6])]},
                "feedback_counters": dict(self.feedback_counters)}

    def close(self) -> None:
        """One last surgeon-off packet, then the socket closes (idempotent); the arm reads FAULT."""
        if self.sock is not None:
            if self._mode is not RobotMode.FAULT:
                self.fault("the ITP link was closed")
            self._send()
            self.sock.close()
            self.sock = None
