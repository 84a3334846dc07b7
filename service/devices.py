"""The service's devices: B haptic masters (position, orientation, grasp and pedal in, force out)
and B robots (measured pose and jaw in, pose and jaw commands out), read into a ``TickInput`` and
written from a ``TickOutput``.

CHAI3D's device abstraction: the tick never talks to a device but through ``read`` and ``write``.
A robot is any object of the ``service.robot`` interface (``measured_cp``, ``servo_cp``, ``hold``,
``resume``, ``step``, ``state``; a robot with a jaw adds ``jaw_limits``, ``measured_jaw`` and
``servo_jaw``), in the loop's process or hosted in its own (``robot.hosted``);
``None`` is an ideal robot (X_r = X_r*: its position is its last command).

The masters' force sends are serialised by a lock: the tick sends, and so does the tick
watchdog's thread when a tick stalls (``send_zero_forces``).
"""
from __future__ import annotations

import math
import threading
from ctypes import POINTER, c_double, c_int64
from operator import is_
from typing import Optional, Sequence

import numpy as np

from pointfence.kernels.errors import InputError
from pointfence.native import fast, lib, ptr

from .masters import Master
from .robot.base import RobotMode
from .tick_io import TickInput, TickOutput

_FAULT = RobotMode.FAULT
#: the per-arm arrays each compiled call reads or writes (``Devices._pointers``): (dtype, values
#: per arm; None: one)
_F3, _F4, _F1, _B1 = (np.float64, 3), (np.float64, 4), (np.float64, None), (bool, None)
_ROBOT_KINDS = (_F3, _F4, _B1, _B1, _F1, _F1)
_MASTER_KINDS = (_F3, _F4, _F1, _B1)
_POSE_KINDS = (_F3, _F4)


class Devices:
    """``masters`` (one per arm) and ``robots`` (one per arm, None: ideal)."""

    def __init__(self, masters: Sequence, robots: Sequence):
        self.masters = list(masters)
        self.robots = list(robots)
        if len(self.robots) != len(self.masters):
            raise InputError(f"{len(self.robots)} robots for {len(self.masters)} masters; expected one per master "
                             "(None: ideal robot)")
        n = self.n = len(self.masters)
        #: (index, robot) of the arms with a robot device
        self.real = [(b, r) for b, r in enumerate(self.robots) if r is not None]
        self.present = np.array([r is not None for r in self.robots], bool)
        self._all_real = len(self.real) == n
        self._T4 = np.zeros((n, 4, 4))
        self._T4_rows = list(self._T4)            # (views made once: no view per arm and tick)
        self._tips = self._T4[:, :3, 3]           # (n, 3) view: each measured pose's position
        self._tip_rows = list(self._tips)
        self._zero3 = np.zeros(3)
        self._T4p = ptr(self._T4, np.float64, "poses")
        self._n64, self._four = c_int64(n), c_int64(4)      # (the core's int64 arguments, made once)
        #: the tick's commanded poses (n, 4, 4), world: the command's position and orientation
        self._cmd4 = np.zeros((n, 4, 4))
        self._cmd4_rows = list(self._cmd4)
        self._cmd4p = ptr(self._cmd4, np.float64, "command poses")
        self._q4 = np.zeros((n, 4))                # the measured orientations, before the ideal arms'
        self._q4p = ptr(self._q4, np.float64, "orientations")
        self._ptr_sets: dict = {}                  # key -> (arrays, pointers): ``_pointers``
        self._views = None                         # ``_scalar_views``
        self._bind_sources()
        #: arms whose robot takes jaw commands (``servo_jaw``) and reports its jaw (``measured_jaw``)
        self.jawed = [(b, r) for b, r in self.real if callable(getattr(r, "servo_jaw", None))
                      and getattr(r, "jaw_limits", None) is not None]
        #: arms whose robot reports its orientation as a quaternion itself (``measured_orientation``:
        #: a recording's, taken as recorded, bit for bit, rather than through its rotation matrix)
        self.quat_direct = [(b, r) for b, r in self.real if callable(getattr(r, "measured_orientation", None))]
        #: the robot process whose arms are all the robots, arm b on row b (None: other robots):
        #: ``read_robots`` then reads every arm in one compiled call
        self._host = self._one_host()
        self._jawed_mask = np.array([(b, r) in self.jawed for b, r in enumerate(self.robots)], bool)
        self._jawed_p = ptr(self._jawed_mask, bool, "jawed")
        self._no_jaw = np.full(n, math.nan)       # the ideal jaw when the tick gives none
        self._codes = np.zeros(n, np.int32)       # each arm's setpoint code (``_command_host``)
        self._codes_p = ptr(self._codes, np.int32, "codes")
        self.tx_lock = threading.Lock()   #: held while forces are sent (the tick, the watchdog)
        # masters that only store the force they are sent (``Master.send_force``: into their own
        # ``force`` array, in place) take it in one compiled call, their arrays' addresses bound
        # once (None: some master sends it on)
        self._stores = None
        if all(type(m).send_force is Master.send_force and isinstance(m.force, np.ndarray)
               and m.force.dtype == np.float64 and m.force.shape == (3,) and m.force.flags.c_contiguous
               for m in self.masters):
            self._stores = (POINTER(c_double) * n)(*(ptr(m.force, np.float64, "master force") for m in self.masters))
            self._store_refs = [m.force for m in self.masters]      # (the addresses' arrays, kept alive)
        #: arms whose robot refused this tick's command, and the setpoint it kept (world, m)
        self.refused = np.zeros(n, bool)
        self._refused_any = False
        self.kept = np.zeros((n, 3))
        self.kept_orientation = np.zeros((n, 4))
        self.refusals = 0
        self.last_refusal: Optional[str] = None

    def _one_host(self):
        """The robot host all robots are arms of, arm b on its row b (None: not so)."""
        host = getattr(self.robots[0], "host", None) if self.robots and self.robots[0] is not None else None
        if host is None or len(self.real) != self.n or getattr(host, "n", None) != self.n:
            return None
        if any(getattr(r, "host", None) is not host or r.index != b for b, r in enumerate(self.robots)):
            return None
        return host

    def jaw_ranges(self, default) -> np.ndarray:
        """(n, 2) each arm's jaw range (rad): its robot's ``jaw_limits``, ``default`` for arms
        whose robot has no jaw (or no robot)."""
        out = np.tile(np.asarray(default, dtype=float), (self.n, 1))
        for b, r in self.jawed:
            out[b] = r.jaw_limits
        return out

    # --- in ------------------------------------------------------------------------------------------
    def read_masters(self, inp: TickInput) -> None:
        """Poll every master at loop time ``inp.t``: position (master frame), orientation (w x y z,
        master frame), grasp (rad), pedal, validity. A sample is valid only if the device says so
        and its position, orientation and grasp are finite, the orientation a unit quaternion (S2)."""
        t, pos, quat = inp.t, inp.master_pos, inp.master_orientation
        g, c, k = self._scalar_views(inp)
        src_pos, src_quat, stale = self._src_pos, self._src_quat, False
        for b, m in enumerate(self.masters):
            m.poll(t)
            g[b], c[b], k[b] = m.grasp, m.clutch, m.ok
            if m.position is not src_pos[b] or m.orientation is not src_quat[b]:
                stale = True
        if stale:                                  # a master replaced its arrays: point at the new ones
            self._bind_sources()
        pp, qp, gp, okp = self._pointers("read_masters", (pos, quat, inp.grasp, inp.master_ok), _MASTER_KINDS)
        fast.pf_masters_take(self._src_pos_p, self._src_quat_p, self._n64, pp, qp, gp, okp)

    def _bind_sources(self) -> None:
        """The masters' own position and orientation arrays, as the pointers ``pf_masters_take``
        reads (each master writes its sample into them in place: ``masters.Master``)."""
        n = self.n
        self._src_pos = [np.ascontiguousarray(m.position, np.float64) for m in self.masters]
        self._src_quat = [np.ascontiguousarray(m.orientation, np.float64) for m in self.masters]
        for m, a, q in zip(self.masters, self._src_pos, self._src_quat):    # (the gather copies 3 and 4 floats)
            if a.shape != (3,) or q.shape != (4,):
                raise InputError(f"master {getattr(m, 'name', m)!r}: position of shape {a.shape} and orientation of "
                                 f"shape {q.shape}; expected (3,) and (4,) (m; quaternion w, x, y, z)")
        self._src_pos_p = (POINTER(c_double) * n)(*(ptr(a, np.float64, "master position") for a in self._src_pos))
        self._src_quat_p = (POINTER(c_double) * n)(*(ptr(a, np.float64, "master orientation") for a in self._src_quat))
        # (a master whose arrays are not float64 (n,) contiguous gets a converted copy: bound again each tick)
        self._src_pos = [a if a is m.position else None for a, m in zip(self._src_pos, self.masters)]
        self._src_quat = [a if a is m.orientation else None for a, m in zip(self._src_quat, self.masters)]

    def _scalar_views(self, inp: TickInput) -> tuple:
        """Memoryviews of ``inp``'s grasp, pedal and master_ok (made again only for other arrays:
        an element assignment through one costs a fraction of NumPy's)."""
        v = self._views
        if v is None or v[0] is not inp.grasp or v[1] is not inp.pedal or v[2] is not inp.master_ok:
            v = self._views = (inp.grasp, inp.pedal, inp.master_ok, memoryview(inp.grasp), memoryview(inp.pedal),
                               memoryview(inp.master_ok))
        return v[3], v[4], v[5]

    def read_robots(self, inp: TickInput, ideal_pos: np.ndarray, ideal_quat: np.ndarray = None,
                    ideal_jaw: np.ndarray = None) -> None:
        """Every robot's measured tool pose (world: tip and orientation), jaw (rad, NaN: unknown
        or none) and fault state; an ideal robot's are ``ideal_pos``, ``ideal_quat`` and
        ``ideal_jaw`` (its commands; identity orientation and NaN jaw where not given)."""
        if self._host is not None:                 # every arm in one compiled call
            pos, quat, fault, present, jaw, ideal = self._pointers(
                "read_robots", (inp.robot_pos, inp.robot_orientation, inp.robot_fault, inp.robot_present, inp.robot_jaw,
                                self._no_jaw if ideal_jaw is None else ideal_jaw), _ROBOT_KINDS)
            self._host.read_poses(self._T4p, pos, quat, fault, present, jaw, self._jawed_p, ideal)
            return
        np.copyto(inp.robot_present, self.present)
        fault, T4 = inp.robot_fault, self._T4_rows
        for b, r in self.real:
            r.measured_cp(out=T4[b])
            fault[b] = r.state == _FAULT
        jaw, quat = inp.robot_jaw, inp.robot_orientation
        if ideal_jaw is None:
            jaw.fill(math.nan)
        else:                                    # (a robot without a jaw: its jaw is ideal, the command)
            np.copyto(jaw, ideal_jaw)
        qp = self._pointer("robot_orientation", quat, _F4)
        if self._all_real:
            np.copyto(inp.robot_pos, self._tips)
            fast.pf_quats_of_matrices(self._T4p, self._four, self._n64, qp)
        else:
            np.copyto(inp.robot_pos, ideal_pos)
            fast.pf_quats_of_matrices(self._T4p, self._four, self._n64, self._q4p)
            if ideal_quat is None:
                quat[:] = (1.0, 0.0, 0.0, 0.0)
            else:
                np.copyto(quat, ideal_quat)
            for b, _ in self.real:
                inp.robot_pos[b] = self._tip_rows[b]
                quat[b] = self._q4[b]
        for b, r in self.quat_direct:
            quat[b] = r.measured_orientation()
        for b, r in self.jawed:
            jaw[b] = r.measured_jaw()

    def _pointers(self, key: str, arrays: tuple, kinds: tuple) -> tuple:
        """The core's pointers to the per-arm ``arrays`` (``kinds``: each one's dtype and values
        per arm), made again only when one of them is another array than last time's under
        ``key``: one identity check per array a tick. A new array is checked then: (n,) or
        (n, values), C-contiguous, of its dtype."""
        got = self._ptr_sets.get(key)
        if got is None or not all(map(is_, got[0], arrays)):
            for a, (_, k) in zip(arrays, kinds):
                if np.shape(a) != ((self.n,) if k is None else (self.n, k)):
                    raise InputError(f"{key}: an array of shape {np.shape(a)} for {self.n} arms; expected "
                                     f"({self.n},{'' if k is None else f' {k}'})")
            got = self._ptr_sets[key] = (arrays, tuple(ptr(a, dt, f"{key}: array {i}")
                                                       for i, (a, (dt, _)) in enumerate(zip(arrays, kinds))))
        return got[1]

    def _pointer(self, key: str, a: np.ndarray, kind: tuple):
        """``_pointers`` of one array (its pointer), with the look-up of one."""
        got = self._ptr_sets.get(key)
        if got is None or got[0][0] is not a:
            self._pointers(key, (a,), (kind,))
            got = self._ptr_sets[key]
        return got[1][0]

    def read_pedals(self, t: float, pedal: np.ndarray) -> None:
        """Only the pedals (the safe path): a master that cannot be read counts as pedal down."""
        for b, m in enumerate(self.masters):
            try:
                m.poll(t)
                pedal[b] = m.clutch
            except Exception:   # noqa: BLE001 -- unknown pedal: clearing faults stays refused
                pedal[b] = True

    # --- out -----------------------------------------------------------------------------------------
    def send_forces(self, force_master: np.ndarray) -> None:
        """(B, 3) forces in each master's frame (N)."""
        with self.tx_lock:
            if self._stores is not None:
                fast.pf_masters_scatter(self._pointer("send_forces", force_master, _F3), self._n64, self._stores)
                return
            for m, f in zip(self.masters, force_master):
                m.send_force(f)

    def send_zero_forces(self) -> bool:
        """Zero force on every master now (any thread). False if a send is in progress (a tick
        stuck inside one keeps the lock)."""
        if not self.tx_lock.acquire(blocking=False):
            return False
        try:
            for m in self.masters:
                m.send_force(self._zero3)
        finally:
            self.tx_lock.release()
        return True

    def command_robots(self, out: TickOutput, dt: float) -> bool:
        """Resume arms that couple, send the command to coupled arms, hold arms that decouple (they
        stop where they are), then step every robot by ``dt`` (s): every arm's command first, then
        every arm's step (a hosted arm's step sends the commands queued so far, robot/hosted.py:
        one message for the tick). A robot that refuses a command keeps its setpoint: ``refused``
        and ``kept`` say so (the tick's command follows). Returns whether any arm refused."""
        if self._refused_any:
            self.refused[:] = False
            self._refused_any = False
        cmd, ori = self._pointers("command_robots", (out.command, out.orientation), _POSE_KINDS)
        fast.pf_poses_of(cmd, ori, self._n64, self._cmd4p)
        if self._host is not None and not self.jawed:
            return self._command_host(out, dt)
        coupled, engage, release = out.coupled.tolist(), out.engage.tolist(), out.release.tolist()
        poses = self._cmd4_rows
        for b, r in self.real:
            if coupled[b]:
                if engage[b]:
                    r.resume()
                try:
                    r.servo_cp(poses[b])
                except InputError as e:     # unreachable: the robot keeps its setpoint
                    self._refuse(b, r, f"robot {b}: {e}")
            elif release[b]:
                r.hold()
        if self.jawed:
            jaw = out.jaw.tolist()
            for b, r in self.jawed:
                if coupled[b] and not self.refused[b] and math.isfinite(jaw[b]):
                    try:
                        r.servo_jaw(jaw[b])
                    except InputError as e:     # (outside its range: the jaw keeps its setpoint, the arm holds)
                        self._refuse(b, r, f"robot {b} jaw: {e}")
        for b, r in self.real:
            r.step(dt)
        return self._refused_any

    def _command_host(self, out: TickOutput, dt: float) -> bool:
        """``command_robots`` when every robot is an arm of one robot process (``_host``), the
        tick's poses already in ``_cmd4``: the mode commands of arms that couple or decouple first, then every coupled arm's setpoint
        and every arm's step in one compiled call (``RobotHost.command``); an arm whose setpoint
        was not queued answers as its ``servo_cp`` would (``after_servo``)."""
        if not (dt > 0.0) or dt == math.inf:
            raise InputError(f"step: dt = {dt!r}; expected a finite number > 0")
        engage, release = out.engage.tolist(), out.release.tolist()
        if True in engage or True in release:
            coupled = out.coupled.tolist()
            for b, r in self.real:
                if coupled[b] and engage[b]:
                    r.resume()
                elif release[b] and not coupled[b]:
                    r.hold()
        if self._host.command(self._cmd4p, self._pointer("coupled", out.coupled, _B1), self._codes_p):
            for b, code in enumerate(self._codes.tolist()):     # (-1: not coupled; 0: queued)
                if code > 0:
                    r = self.robots[b]
                    try:
                        r.after_servo(code, self._cmd4_rows[b])
                    except InputError as e:     # unreachable: the robot keeps its setpoint
                        self._refuse(b, r, f"robot {b}: {e}")
        return self._refused_any

    def _refuse(self, b: int, r, why: str) -> None:
        """Arm ``b``'s robot ``r`` refused this tick's command: count it, keep its setpoint
        (position and orientation: the tick's command follows, ``kept``) and say why."""
        self.refusals += 1
        self.last_refusal = why
        r.setpoint_cp(out=self._T4[b])
        self.kept[b] = self._T4[b, :3, 3]
        lib.pf_quats_of_matrices(ptr(self._T4[b], np.float64, "setpoint"), 4, 1,
                                 ptr(self.kept_orientation[b], np.float64, "kept"))
        self.refused[b] = True
        self._refused_any = True

    def hold_robots(self, dt: float, coupled: np.ndarray, command: np.ndarray, orientation: np.ndarray = None,
                    jaw: np.ndarray = None) -> None:
        """The safe path: every robot holds where it is and keeps stepping; the command (position,
        and orientation and jaw where given) of an arm that was coupled moves onto its measured one."""
        for b, r in self.real:
            if coupled[b]:
                r.hold()
                r.measured_cp(out=self._T4[b])
                command[b] = self._T4[b, :3, 3]
                if orientation is not None:
                    lib.pf_quats_of_matrices(ptr(self._T4[b], np.float64, "measured"), 4, 1,
                                             ptr(orientation[b], np.float64, "orientation"))
            r.hold()
            r.step(dt)
        if jaw is not None:
            for b, r in self.jawed:
                if coupled[b]:
                    jaw[b] = r.measured_jaw()

    def hold_all_robots(self) -> None:
        for _, r in self.real:
            r.hold()

    def clear_robot_faults(self) -> None:
        """Re-enable robots in FAULT; they hold (their setpoint re-seats: no motion)."""
        for _, r in self.real:
            if r.state == RobotMode.FAULT:
                r.enable()
                r.hold()

    def robot_status(self) -> list:
        return [None if r is None else {"model": r.model, "mode": r.state.name, "fault": r.fault_reason,
                                        "process": "own" if getattr(r, "hosted", False) else "loop"}
                for r in self.robots]


__all__ = ["Devices"]
