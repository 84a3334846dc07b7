"""The service: configuration -> backend, frame pipeline, proxies, forces, robots, masters, and
the per-tick work the haptic loop runs (``Service.tick``).

One tick, for B master-robot pairs (one proxy each):

1. poll every master (position, pedal, validity); a non-finite sample is a device fault;
2. the tick's time on the frames' clock (``frame_time``), the robots' joints into the tool pose
   ring (the self-filter's look-up, ``toolpose``); health (``holds.py``: each reason with its
   SAFETY.md invariant): a late or stalled tick, a published snapshot older than
   ``max_frame_age_s``, a kernel failure, a robot or master fault. A held arm's force gain
   ramps to zero within ``force_ramp_s`` and its robot stops where it is; a condition must be
   clear for ``recover_s``, a latched fault cleared (``clear_faults``), before it comes back;
3. teleoperation (``teleop.Teleop``): master motion -> X_m, re-anchoring of arms that (re)couple
   and of every arm at a change of control law (S1), the HIP by architecture (continuous);
4. ONE proxy launch for all B proxies against the current snapshot (through the publish gate, so
   the snapshot number is exact; with ``[motion] enabled`` the points are predicted to the
   tick's frame time plus the camera latency, ``kernels/motion.py``), then forces
   (``kernels.forces.ForceRenderer``: dead band, contact damping, FIR, saturation) times the
   per-arm gain, sent to the masters;
5. robot commands by architecture, rate-limited, ``servo_cp`` for coupled arms; robots step;
6. publish (a small lock-protected copy for ``status()``) and record.

Nothing in a tick allocates arrays except the robot model's own ``servo_cp`` and the proxy's
input check; there is no logging I/O and no per-point Python loop.
"""
from __future__ import annotations

import math
import threading
from collections import deque
from typing import Optional, Sequence

import numpy as np

from pointfence.kernels import get_backend
from pointfence.kernels.errors import InputError, KernelError
from pointfence.kernels.forces import ForceRenderer
from pointfence.kernels.haptics import haptic_pipeline_params
from pointfence.kernels.params_haptics import HapticParams

from .frames import PublishGate
from .holds import (EXCEPTION, INGEST, KERNEL, LATCHED, MASTER, N_BITS, OVERRUN, REASONS, ROBOT, STALE,  # noqa: F401
                    WATCHDOG, describe, index, reason_names)
from .record import C, Recorder
from .robot.base import RobotMode
from .teleop import Teleop, arch_code


class Service:
    """Everything one haptic tick touches; see the module docstring.

    Args:
        cfg: a parsed ``config.SceneConfig``.
        masters: one ``masters.Master`` per arm (B = len(masters)).
        robots: one robot per arm (``service.robot`` interface) or None per arm for an ideal
            robot (X_r = X_r*); default: built from ``cfg.robot`` (model "none": ideal).
        backend, device: override the configured compute backend.
        record: ticks to record in memory (0: no recording).
        record_path: stream the recording to this ``.pfrec`` file instead (record.py: a crash
            loses at most the last fraction of a second, S8).
    """

    def __init__(self, cfg, masters: Sequence, robots: Optional[Sequence] = None, backend: Optional[str] = None,
                 device: Optional[str] = None, record: int = 0, architecture: Optional[str] = None,
                 record_path=None):
        self.cfg = cfg
        sc = cfg.service
        self.rate_hz = sc.rate_hz
        self.dt = 1.0 / sc.rate_hz
        self.masters = list(masters)
        n = self.n = len(self.masters)
        if n < 1:
            raise InputError("the service needs at least one master (one per proxy)")
        hp: HapticParams = cfg.haptics if cfg.haptics is not None else HapticParams(mode=cfg.mode)
        self.params = hp.replace(rate_hz=sc.rate_hz) if hp.rate_hz != sc.rate_hz else hp
        pp = cfg.pipeline if cfg.cell_size_given else haptic_pipeline_params(self.params, cfg.pipeline)
        self.backend = get_backend(backend or cfg.backend, device or cfg.device)
        self.pipeline = self.backend.pipeline([c.camera for c in cfg.cameras], pp)
        self.gate = PublishGate(self.pipeline)
        if robots is None:
            robots = [self._make_robot(cfg.robot) for _ in range(n)]
        if len(robots) != n:
            raise InputError(f"{len(robots)} robots for {n} masters; expected one per master (None: ideal robot)")
        self.robots = list(robots)
        # the robot self-filter, where every robot's tool is known (S5); else self_filter_off says why
        from .toolpose import self_filter_for

        self.tool_poses, self.frame_filter, self.self_filter_off = self_filter_for(cfg, pp, self.robots)
        #: this tick's time on the frames' clock (nan while unknown); the proxies' prediction time
        self.frame_time = math.nan
        self._predict = bool(pp.motion.enabled)
        self._frame_time = None
        tc = cfg.teleop
        self.teleop = Teleop(n, tc.T_world_master, tc.scale, tc.max_robot_speed, self.dt,
                             architecture or tc.architecture)
        self.R = self.teleop.R
        # per-arm arrays
        z3 = lambda: np.zeros((n, 3))  # noqa: E731
        self.dev = z3()
        self.xr = z3()
        self.f_out = z3()
        self.f_master = z3()
        self._fin = np.zeros((n, 3), bool)
        self.pedal = np.zeros(n, bool)
        self.m_ok = np.zeros(n, bool)
        self.gain = np.zeros(n)
        self._gtarget = np.zeros(n)
        self._gstep = np.zeros(n)
        self.coupled = np.zeros(n, bool)
        self._coupled_prev = np.zeros(n, bool)
        self._newly = np.zeros(n, bool)
        self._reseat = np.zeros(n, bool)        # arms re-anchored this tick
        self._reseat_pos = np.zeros((n, 3))
        self._phip = np.zeros((n, 3))
        self._arm_ok = np.zeros(n, bool)
        self._rowok = np.zeros(n, bool)
        self._notb = np.zeros(n, bool)
        self._flag = np.zeros(n, bool)
        self._want = np.zeros(n, bool)
        self._tn = np.zeros(n)
        self._ti = np.zeros(n, np.int64)
        self._master_bad_t = np.full(n, -math.inf)
        self._robot_bad_t = np.full(n, -math.inf)
        self._bad_t = np.full(N_BITS, -math.inf)  # last time of each condition, by reason bit index
        self._T4 = np.zeros((n, 4, 4))
        self.hold_mask = 0
        #: latched faults (holds.LATCHED bits) until ``clear_faults``
        self.latched = 0
        self.arm_hold = np.zeros(n, np.int64)
        self._zero3 = np.zeros(3)
        #: set by the tick watchdog's thread (``on_stall``): the loop time the stall was seen at
        self._stall_at: Optional[float] = None
        self.watchdog_trips = 0
        self._tx_lock = threading.Lock()   # the masters' force sends: the tick's and the watchdog's
        # control state (set from other threads through the methods below; applied at tick start)
        self.haptics_on = bool(cfg.teleop.haptics)
        self.teleop_on = bool(cfg.teleop.teleop)
        self._haptics_running = False
        self._teleop_prev = self.teleop_on
        self._pending_arch: Optional[int] = None
        self._reanchor = False   # a change of control law asked for a re-anchoring (S1)
        self._ctl = threading.Lock()
        self._between: deque = deque()   # callables run by the tick thread before the next tick
        # results and counters
        self.kernel_errors = 0
        self.robot_errors = 0
        self.last_error: Optional[str] = None
        self.frame_seq = 0
        self.snapshot_first_tick: dict = {}
        self.feeder = None
        self.scene_time_offset = 0.0   # scene (camera) time at loop time 0
        self._poll_tick = self._poll = False
        self.recorder = (Recorder(n=n, path=record_path) if record_path is not None
                         else Recorder(record, n) if record else None)
        self._pub_lock = threading.Lock()
        self._pub = {k: np.zeros((n, 3)) for k in ("xm", "hip", "proxy", "cmd", "xr", "force")}
        self._pub_state = np.zeros(n, np.int32)
        self._pub_t = 0.0
        self._pub_k = 0
        # initial state
        self.batch = None
        self.renderer = ForceRenderer(n, self.params)
        self._started = False

    # --- construction helpers -----------------------------------------------------------------
    @staticmethod
    def _make_robot(table):
        if table.model == "none":
            return None
        from .robot import robot_from_config

        return robot_from_config(table)

    def attach_frames(self, feeder) -> None:
        """The frame feeder (``frames.LiveFrames``/``SimFrames``/``ScheduledFrames``) whose
        ``max_age(now)`` the ticks check (offline feeders are polled inside the tick)."""
        self.feeder = feeder
        if self.frame_filter is not None:
            feeder.frame_filter = self.frame_filter
        self._frame_time = getattr(feeder, "frame_time", None)
        self._poll_tick = hasattr(feeder, "poll_tick")
        self._poll = hasattr(feeder, "poll")

    def start(self) -> None:
        """Place everything at its initial state (call after the first snapshot exists)."""
        for b, m in enumerate(self.masters):
            m.poll(0.0)
            self.dev[b] = m.position
        xr = None
        if any(r is not None for r in self.robots):
            xr = np.zeros((self.n, 3))
            for b, r in enumerate(self.robots):
                xr[b] = r.measured_cp()[:3, 3] if r is not None else 0.0
            if any(r is None for r in self.robots):
                reg = self.teleop.register(np.nan_to_num(self.dev), np.zeros((self.n, 3)))
                for b, r in enumerate(self.robots):
                    if r is None:
                        xr[b] = reg[b]
        self.teleop.start(self.dev, xr)
        self.xr[:] = self.teleop.cmd
        if self.batch is not None:
            self.batch.close()
        self.batch = self.pipeline.proxies(self.teleop.hip, self.params)
        self.renderer.reset()
        self._haptics_running = self.haptics_on
        for r in self.robots:
            if r is not None:
                r.hold()   # until the arm couples (pedal down, teleoperation engaged, healthy)
        self._started = True

    def warm_up(self) -> None:
        """Launch the proxy kernel once on a throw-away batch (same program and batch size), so
        that a just-in-time compiling runtime (PoCL) compiles it before the loop's first tick."""
        probe = self.pipeline.proxies(self.teleop.hip, self.params)
        with self.gate.lock:
            probe.step(self.teleop.hip)
        probe.close()

    # --- control (any thread; applied at the start of the next tick) ----------------------------
    def set_architecture(self, architecture) -> None:
        with self._ctl:
            self._pending_arch = arch_code(architecture)

    def engage_haptics(self, on: bool = True) -> None:
        with self._ctl:
            self.haptics_on = bool(on)

    def engage_teleop(self, on: bool = True) -> None:
        with self._ctl:
            self.teleop_on = bool(on)

    def request_reanchor(self) -> None:
        """A change of control law made outside the tick (a new radius or selection, a
        re-registration): the next tick re-anchors every arm's goal to its command (S1)."""
        with self._ctl:
            self._reanchor = True

    def clear_faults(self) -> None:
        """Forget latched faults and re-enable robots in FAULT (their setpoint re-seats: no
        motion). Needs every arm decoupled (S3): raises InputError while an arm is coupled or its
        pedal is down with teleoperation engaged (it would couple at once). Call it
        between ticks (``call_between_ticks``: the control API does), where the pedals read are
        this tick's. An arm that couples again is re-anchored: clearing never moves a robot (S1)."""
        with self._ctl:
            down = [b for b in range(self.n) if self.coupled[b] or (self.pedal[b] and self.teleop_on)]
            if down:
                raise InputError(f"clear-faults refused: arm(s) {down} coupled (foot pedal down, teleoperation on); "
                                 "release the pedal(s) or disengage teleoperation first, then clear the faults "
                                 "(SAFETY.md S3)")
            for r in self.robots:
                if r is not None and r.state == RobotMode.FAULT:
                    r.enable()
                    r.hold()
            self._bad_t[:] = -math.inf
            self._robot_bad_t[:] = -math.inf
            self.latched = 0
            self.last_error = None
            restart = getattr(self.feeder, "restart_ingest", None)
            if restart is not None:
                restart()

    def on_stall(self, started: float, now: float) -> None:
        """The tick watchdog (``loop.TickWatchdog``, its own thread): the tick that started at
        ``started`` (loop clock, s) is still running at ``now``. The masters get zero force at
        once; the stalled tick, when it returns, and the ticks after it hold every arm for
        ``recover_s`` (S9). Robots need nothing here: they get no new command while the tick is
        stalled."""
        self._stall_at = now
        self.watchdog_trips += 1
        if self._tx_lock.acquire(blocking=False):   # (a tick stuck inside a send keeps its lock)
            try:
                self.gain[:] = 0.0
                for m in self.masters:
                    m.send_force(self._zero3)
            finally:
                self._tx_lock.release()

    def call_between_ticks(self, fn) -> None:
        """Run ``fn(service)`` in the tick thread at the start of the next tick, before anything
        else (the control API's way to read or change the tick's state; ``fn`` must not raise and
        must be short: it runs inside the tick's deadline)."""
        self._between.append(fn)

    @property
    def architecture(self) -> str:
        return self.teleop.architecture

    # --- the tick --------------------------------------------------------------------------------
    def tick(self, k: int, t: float, dt: float, overrun: bool, now: float) -> None:
        if not self._started:
            self.start()
        while self._between:
            self._between.popleft()(self)
        n, tp = self.n, self.teleop
        with self._ctl:
            law_change = self._reanchor
            self._reanchor = False
            if self._pending_arch is not None:
                tp.set_architecture(self._pending_arch)   # (a switch sets tp.law_changed)
                self._pending_arch = None
            haptics_on, teleop_on = self.haptics_on, self.teleop_on
        law_change |= tp.law_changed or haptics_on != self._haptics_running or teleop_on != self._teleop_prev
        tp.law_changed = False
        self._teleop_prev = teleop_on
        # 1. masters
        for b in range(n):
            m = self.masters[b]
            m.poll(t)
            self.dev[b] = m.position
            self.pedal[b] = m.clutch
            self.m_ok[b] = m.ok
        np.isfinite(self.dev, out=self._fin)
        np.logical_and.reduce(self._fin, axis=1, out=self._rowok)
        np.logical_and(self.m_ok, self._rowok, out=self.m_ok)
        # 2. frame time, tool poses, health
        feeder = self.feeder
        tf = self._frame_time(t, now) if feeder is not None and self._frame_time is not None else None
        self.frame_time = math.nan if tf is None else tf
        if tf is not None and self.tool_poses is not None:
            self.tool_poses.record(tf)
        if feeder is not None:
            if self._poll_tick:
                feeder.poll_tick(k, t)
            elif self._poll:
                feeder.poll(t)
        age = feeder.max_age(now) if feeder is not None else 0.0
        rec = self.cfg.service.recover_s
        if overrun:
            self._bad_t[index(OVERRUN)] = t
        if age > self.cfg.service.max_frame_age_s:   # S2: the newest published snapshot is too old
            self._bad_t[index(STALE if feeder.frames_too_old(now) else INGEST)] = t
        np.logical_not(self.m_ok, out=self._notb)
        np.copyto(self._master_bad_t, t, where=self._notb)
        for b, r in enumerate(self.robots):
            if r is not None and r.state == RobotMode.FAULT:
                self._robot_bad_t[b] = t
        hold = self.latched
        for i in range(N_BITS):
            if t - self._bad_t[i] < rec:
                hold |= 1 << i
        self.hold_mask = hold
        arm = self.arm_hold
        np.subtract(t, self._master_bad_t, out=self._tn)
        np.less(self._tn, rec, out=self._flag)
        np.multiply(self._flag, MASTER, out=arm)
        np.bitwise_or(arm, hold, out=arm)
        np.subtract(t, self._robot_bad_t, out=self._tn)
        np.less(self._tn, rec, out=self._flag)
        np.multiply(self._flag, ROBOT, out=self._ti)
        np.bitwise_or(arm, self._ti, out=arm)
        np.equal(arm, 0, out=self._arm_ok)
        # 3. teleoperation
        # a held arm's X_m does not follow the master (re-coupling must not replay its motion)
        tp.map_masters(self.dev, self.pedal, self._arm_ok)
        np.logical_and(self._arm_ok, self.pedal, out=self.coupled)
        if not teleop_on:
            self.coupled[:] = False
        np.logical_not(self._coupled_prev, out=self._notb)
        np.logical_and(self.coupled, self._notb, out=self._newly)
        # S1: an arm that (re)couples, and every arm at a change of control law, starts from
        # where its robot is commanded
        if law_change:
            self._reseat[:] = True
            tp.reanchor_all()
        else:
            np.copyto(self._reseat, self._newly)
            if self._newly.any():
                tp.reanchor(self._newly)
        for b, r in enumerate(self.robots):
            if r is None:
                continue
            r.measured_cp(out=self._T4[b])
            self.xr[b] = self._T4[b, :3, 3]
        for b, r in enumerate(self.robots):
            if r is None:
                self.xr[b] = tp.cmd[b]
        hip = tp.update_hip(self.xr)
        phip = tp.proxy_hip()
        np.logical_and(self._arm_ok, self.pedal, out=self._want)
        if not self._want.all():     # the proxy of an arm held or unclutched (no force) stays where
            np.copyto(self._phip, phip)           # it is: in III it must not creep off the command
            np.logical_not(self._want, out=self._notb)
            np.copyto(self._phip, self.batch.positions, where=self._notb[:, None])
            phip = self._phip
        # 4. proxies and forces
        if haptics_on and (not self._haptics_running or (tp.arch == 3 and self._reseat.any())):
            # re-anchored arms' proxies start on the command in III (the proxy is the goal there:
            # a proxy that crept along the surface while the arm held must not pull the robot)
            # and on the HIP otherwise; the other arms' proxies stay where they are
            np.copyto(self._reseat_pos, self.batch.positions)
            np.copyto(self._reseat_pos, tp.cmd if tp.arch == 3 else hip, where=self._reseat[:, None])
            self.batch.reset(self._reseat_pos)
            if not self._haptics_running:
                self.renderer.reset()
        self._haptics_running = haptics_on
        if haptics_on:
            try:
                with self.gate.lock:
                    seq = self.gate.front_seq()
                    if self._predict and tf is not None:
                        self.batch.step(phip, now=tf)
                    else:
                        self.batch.step(phip)
                if seq != self.frame_seq:
                    self.frame_seq = seq
                    self.snapshot_first_tick.setdefault(seq, k)
                self.renderer.update(self.batch.positions, hip, self.batch.states)
            except KernelError as e:
                self._hold_all(KERNEL)
                self.latched |= KERNEL
                self.kernel_errors += 1
                self.last_error = f"tick {k}: {e}"
        if self._stall_at is not None:   # the watchdog saw this tick (or the last) stall
            self._hold_all(WATCHDOG)
            self._bad_t[index(WATCHDOG)] = t
            self.gain[:] = 0.0
            self.last_error = f"tick {k}: tick watchdog: a tick ran past {self.cfg.service.max_lateness_s * 1e3:g} ms"
            self._stall_at = None
        F = self.renderer.forces
        np.logical_and(self._arm_ok, self.pedal, out=self._want)
        if not haptics_on:
            self._want[:] = False
        np.subtract(self._want, self.gain, out=self._gstep)
        ramp = dt / self.cfg.service.force_ramp_s
        np.minimum(self._gstep, ramp, out=self._gstep)
        np.maximum(self._gstep, -ramp, out=self._gstep)
        self.gain += self._gstep
        np.multiply(F, self.gain[:, None], out=self.f_out)
        np.matmul(self.f_out, self.R, out=self.f_master)          # world -> master frame: R^T f
        with self._tx_lock:
            for b in range(n):
                self.masters[b].send_force(self.f_master[b])
        # 5. robot commands
        proxies = self.batch.positions
        tp.command_goal(proxies, haptics_on)
        tp.limit_command(self.coupled)
        for b, r in enumerate(self.robots):
            if r is None:
                continue
            if self.coupled[b]:
                if not self._coupled_prev[b]:
                    r.resume()
                try:
                    r.servo_cp(tp.cmd[b])
                except InputError as e:   # unreachable: the robot keeps its setpoint; so does X_r*
                    self.robot_errors += 1
                    self.last_error = f"tick {k}: robot {b}: {e}"
                    r.setpoint_cp(out=self._T4[b])
                    tp.cmd[b] = self._T4[b, :3, 3]
                    self._robot_bad_t[b] = t
            elif self._coupled_prev[b]:
                r.hold()                    # the arm stops where it is, and so does its command
                tp.cmd[b] = self.xr[b]
            r.step(dt)
        for b, r in enumerate(self.robots):
            if r is None and self.coupled[b]:
                self.xr[b] = tp.cmd[b]
        self._coupled_prev[:] = self.coupled
        # 6. publish and record
        self._publish(k, t, proxies)
        self._record(k, t, dt, overrun, age, proxies, haptics_on, teleop_on)

    def _hold_all(self, bit: int) -> None:
        """Every arm holds for reason ``bit`` from this tick on: hold, decouple (S3)."""
        self.hold_mask |= bit
        self.arm_hold |= bit
        self._arm_ok[:] = False
        self.coupled[:] = False

    def safe_tick(self, k: int, t: float, dt: float, now: float) -> None:
        """The loop's fallback after an exception: ramp forces down, hold robots, keep stepping.
        The pedals are still read (clearing the fault needs them up, S3); a master that cannot
        be read counts as pedal down."""
        for b, m in enumerate(self.masters):
            try:
                m.poll(t)
                self.pedal[b] = m.clutch
            except Exception:   # noqa: BLE001 -- unknown pedal: clearing stays refused
                self.pedal[b] = True
        self.latched |= EXCEPTION
        self.hold_mask |= EXCEPTION
        self.arm_hold |= EXCEPTION
        step = dt / self.cfg.service.force_ramp_s
        np.subtract(self.gain, step, out=self.gain)
        np.maximum(self.gain, 0.0, out=self.gain)
        np.multiply(self.renderer.forces, self.gain[:, None], out=self.f_out)
        np.matmul(self.f_out, self.R, out=self.f_master)
        with self._tx_lock:
            for b, m in enumerate(self.masters):
                m.send_force(self.f_master[b])
        for b, r in enumerate(self.robots):
            if r is not None:
                if self._coupled_prev[b]:
                    r.hold()                # the arm stops where it is, and so does its command
                    r.measured_cp(out=self._T4[b])
                    self.teleop.cmd[b] = self._T4[b, :3, 3]
                r.hold()
                r.step(dt)
        self.coupled[:] = False
        self._coupled_prev[:] = False

    # --- publishing ------------------------------------------------------------------------------
    def _publish(self, k, t, proxies) -> None:
        p, tp = self._pub, self.teleop
        with self._pub_lock:
            p["xm"][:] = tp.X_m
            p["hip"][:] = tp.hip
            p["proxy"][:] = proxies
            p["cmd"][:] = tp.cmd
            p["xr"][:] = self.xr
            p["force"][:] = self.f_out
            self._pub_state[:] = self.batch.states
            self._pub_t, self._pub_k = t, k

    def snapshot(self) -> dict:
        """The last tick's published values (copies), for the control API and the demo."""
        with self._pub_lock:
            out = {k: v.copy() for k, v in self._pub.items()}
            out["state"] = self._pub_state.copy()
            out["t"], out["tick"] = self._pub_t, self._pub_k
        return out

    def status(self, now: Optional[float] = None) -> dict:
        st = {
            "architecture": self.architecture, "haptics": self.haptics_on, "teleop": self.teleop_on,
            "hold": reason_names(self.hold_mask), "arms_holding": [reason_names(int(m)) for m in self.arm_hold],
            "hold_causes": describe(self.hold_mask), "latched_faults": reason_names(self.latched),
            "watchdog_trips": self.watchdog_trips,
            "coupled": self.coupled.tolist(), "pedal": self.pedal.tolist(), "force_gain": self.gain.round(3).tolist(),
            "kernel_errors": self.kernel_errors, "robot_errors": self.robot_errors, "last_error": self.last_error,
            "frame_seq": self.frame_seq, "backend": self.backend.name, "device": self.backend.device_name,
            "proxy_device": getattr(self.batch, "device_kind", None) if self.batch is not None else None,
            "robots": [None if r is None else {"model": r.model, "mode": r.state.name, "fault": r.fault_reason,
                                               "process": "own" if getattr(r, "hosted", False) else "loop"}
                       for r in self.robots],
        }
        if self.feeder is not None and now is not None:
            st["frames"] = self.feeder.status(now)
        st["self_filter"] = ({"on": False, "why": self.self_filter_off} if self.frame_filter is None
                             else {"on": True, **self.frame_filter.status()})
        return st

    def _record(self, k, t, dt, overrun, age, proxies, haptics_on, teleop_on) -> None:
        rec = self.recorder
        if rec is None:
            return
        i = rec.next_row()
        if i < 0:
            return
        tp, row = self.teleop, rec.rows[i]
        row[0] = t
        row[1:4] = tp.X_m[0]
        row[4:7] = tp.hip[0]
        row[7:10] = proxies[0]
        row[10:13] = tp.cmd[0]
        row[13:16] = self.xr[0]
        row[16:19] = self.f_out[0]
        row[19] = self.batch.states[0]
        row[20] = self.frame_seq
        inp = rec.inputs[i]
        inp[0], inp[1], inp[2], inp[3] = k, dt, overrun, min(age, 1e9)
        inp[4], inp[5], inp[6], inp[7] = tp.arch, haptics_on, teleop_on, self.frame_time
        m = rec.masters[i]
        m[:, :3] = self.dev
        m[:, 3] = self.pedal
        m[:, 4] = self.m_ok
        rec.robots[i, :, :3] = self.xr
        rec.robots[i, :, 3:] = tp.cmd
        rec.masters_world[i] = tp.X_m
        rec.holds[i, 0] = self.hold_mask
        rec.holds[i, 1:] = self.arm_hold

    def note_tick_us(self, us: float) -> None:
        """The loop's wall-clock compute time of the tick just recorded."""
        if self.recorder is not None:
            self.recorder.note_tick_us(us)

    def close(self) -> None:
        if self.recorder is not None:
            self.recorder.close()   # (streamed: the last rows reach the file)
        if self.batch is not None:
            self.batch.close()   # (Warp: lets a resident proxy kernel go)
        if self.feeder is not None:
            stop = getattr(self.feeder, "stop", None)
            if stop is not None:
                stop()
            self.feeder.close()


__all__ = ["Service", "reason_names", "REASONS"]
