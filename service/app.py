"""The service: the haptic tick over B master-robot pairs (one proxy each), composed of four
components, each owning one concern:

* ``devices.Devices``: the masters (position and pedal in, force out) and the robots (measured
  pose in, command out);
* ``haptic_scene.HapticScene``: depth frames -> snapshots -> proxies -> forces (ONE kernel
  launch per tick for every proxy), the robot self-filter, runtime reconfiguration;
* ``teleop.Teleop``: registration, clutch and indexing, the architectures I-III, re-anchoring
  at every change of control law (S1), the command's speed limit;
* ``health.Health``: why each arm holds (``holds.HoldReason``: each with its SAFETY.md
  invariant), conditions that clear by themselves and latched faults.

One tick (``Service.tick``, called by ``loop.HapticLoop`` at 1 kHz) reads as four calls::

    self.read(inp, k, t, dt, overrun, now)   # devices, frames, control state -> TickInput
    out = self.step(inp)                     # TickInput -> TickOutput (no device touched)
    self.write(out, inp.dt)                  # forces to the masters, commands to the robots
    self.publish(inp, out)                   # status copy, recording

``step`` is the tick as a function of plain data (``tick_io``): master samples, robot states,
frame time and control state in; forces, proxies, commands and holds with named reasons out.
Its arithmetic runs in the compiled tick core (``native/tick_core.c``): ``pf_step_pre`` before
the proxy kernel (health's masks -> teleoperation, coupling, re-anchoring, HIP, proxy targets)
and ``pf_step_post`` after it (force gains and frames, robot commands, the output's copies), on
the components' own arrays; Python around them decides only what needs Python (the kernel
launch, a re-seat of the proxies, the watchdog's hand-over).
A held arm's force gain ramps to zero within ``force_ramp_s`` and its robot stops where it is;
a condition must be clear for ``recover_s``, a latched fault cleared (``clear_faults``), before
it comes back. Nothing in a tick allocates arrays except the robot model's own ``servo_cp``
and the proxy's input check; there is no logging I/O and no per-point Python loop.

Other threads (the control API, the UDP hub, the watchdog) change the control state through
the methods under "control"; it is applied at the start of the next tick.
"""
from __future__ import annotations

import ctypes
import threading
from operator import is_
from collections import deque
from typing import Optional, Sequence

import numpy as np

from pointfence.kernels import get_backend
from pointfence.kernels.errors import InputError, KernelError
from pointfence.kernels.params_haptics import HapticParams
from pointfence.native import StepCore, as_array, fast, lib, ptr

from .devices import Devices
from .haptic_scene import HapticScene
from .health import Health
from .holds import EXCEPTION, KERNEL, REASONS, WATCHDOG, HoldReason, describe, reason_names
from .recorders import make_recorder
from .teleop import DEFAULT_JAW_RANGE, Teleop, arch_code, quat_mul
from .tick_io import TickInput, TickOutput

RING = 1 << 16


def slip_lift_radius(cfg) -> float:
    """Architecture III's slip lift (``Teleop.slip_lift``, m): the fixture radius where
    ``[teleop] slip_lift`` is on in fixture mode, else 0 (off)."""
    if not cfg.teleop.slip_lift or cfg.mode != "fixture":
        return 0.0
    return float(cfg.pipeline.radius.r_base)


class Service:
    """The haptic service; see the module docstring.

    Args:
        cfg: a parsed ``config.SceneConfig``.
        masters: one ``masters.Master`` per arm (B = len(masters)).
        robots: one robot per arm (``service.robot`` interface) or None per arm for an ideal
            robot (X_r = X_r*); default: built from ``cfg.robot`` (model "none": ideal).
        backend, device: override the configured compute backend.
        record: ticks to record in memory (0: no recording).
        record_path: stream the recording to this ``.pfrec`` or ``.mcap`` file (record.py,
            mcap_record.py: a crash loses at most the last fraction of a second, S8).
    """

    def __init__(self, cfg, masters: Sequence, robots: Optional[Sequence] = None, backend: Optional[str] = None,
                 device: Optional[str] = None, record: int = 0, architecture: Optional[str] = None,
                 record_path=None):
        self._set_cfg(cfg)
        sc = cfg.service
        self.rate_hz = sc.rate_hz
        self.dt = 1.0 / sc.rate_hz
        n = self.n = len(masters)
        if n < 1:
            raise InputError("the service needs at least one master (one per proxy)")
        hp: HapticParams = cfg.haptics if cfg.haptics is not None else HapticParams(mode=cfg.mode)
        self.params = hp.replace(rate_hz=sc.rate_hz) if hp.rate_hz != sc.rate_hz else hp
        if robots is None:
            robots = [self._make_robot(cfg.robot) for _ in range(n)]
        self.devices = Devices(masters, robots)
        self.scene = HapticScene(cfg, self.params, get_backend(backend or cfg.backend, device or cfg.device),
                                 self.devices.robots, n)
        tc = cfg.teleop
        self.teleop = Teleop(n, tc.T_world_master, tc.scale, tc.max_robot_speed, self.dt,
                             architecture or tc.architecture, tc.max_angular_speed, tc.max_jaw_speed,
                             self.devices.jaw_ranges(DEFAULT_JAW_RANGE))
        self.teleop.slip_lift = slip_lift_radius(cfg)
        self._lift_normals = None
        self.health = Health(n, sc.recover_s)
        self.inp = TickInput.zeros(n)
        self.out = TickOutput.zeros(n)
        self.gain = np.zeros(n)                 # force gain per arm, in [0, 1]
        self._coupled_prev = np.zeros(n, bool)
        self._reseat = np.zeros(n, bool)
        self._present = np.array(self.devices.present, bool)
        self._phip = np.zeros((n, 3))
        self._core = self._bind_core()
        self._core_ref = ctypes.byref(self._core)
        self._bound_inp: tuple = ()
        self._teleop_prev = bool(tc.teleop)
        # control state (set from other threads through the methods below; applied at tick start)
        self.haptics_on = bool(tc.haptics)
        self.teleop_on = bool(tc.teleop)
        self._pending_arch: Optional[int] = None
        self._reanchor = False   # a change of control law asked for a re-anchoring (S1)
        self._ctl = threading.Lock()
        self._between: deque = deque()   # callables run by the tick thread before the next tick
        self.kernel_errors = 0
        self.last_error: Optional[str] = None
        self.scene_time_offset = 0.0   # scene (camera) time at loop time 0
        self.recorder = make_recorder(n, record, record_path, sc.rate_hz)
        #: a second per-tick consumer beside the recorder (``ros2.telemetry.Telemetry``: its
        #: ``write(inp, out)`` copies into shared memory, never blocks; ``status()``), or None
        self.telemetry = None
        self._pub_lock = threading.Lock()
        self._published = TickOutput.zeros(n)
        self._pub_core = self._bind_core(self._published)
        self._pub_ref = ctypes.byref(self._pub_core)
        self._pub_master = np.full((n, 3), np.nan)   # the last tick's raw master samples (master frame, m)
        self._pub_master_ok = np.zeros(n, bool)      # and their valid flags (``master_sample``)
        self._pub_core.master_pos = ptr(self._pub_master, float, "published master samples")   # (pf_step_publish
        self._pub_core.master_ok = ptr(self._pub_master_ok, bool, "published master_ok")       # copies them)
        self.kernel_us = np.zeros(RING)         # the kernel's wall-clock time per tick (us), a ring
        self.ticks = 0
        self._started = False
        #: the cable-driven grasper controller of ``[cable]`` (``cable_grasper.GrasperHost``, its own
        #: process), commanded each tick with its arm's jaw; its fault holds that arm (as a robot fault)
        self.grasper = None
        if cfg.cable is not None:
            from .cable_grasper import GrasperHost

            cfg.cable.check_arms(n)
            self.grasper = GrasperHost(cfg.cable)
            self.grasper.start()

    # --- construction helpers -----------------------------------------------------------------
    @staticmethod
    def _make_robot(table):
        if table.model == "none":
            return None
        from .robot import robot_from_config

        return robot_from_config(table)

    def _bind_core(self, out: Optional[TickOutput] = None) -> StepCore:
        """The compiled step's view of this service's arrays and of ``out`` (default: its
        ``TickOutput``; the published copy has a view of its own, for ``pf_step_publish``)."""
        c, out = StepCore(n=self.n), (self.out if out is None else out)
        c.coupled_prev, c.reseat = ptr(self._coupled_prev, bool, "coupled_prev"), ptr(self._reseat, bool, "reseat")
        c.present, c.gain, c.phip = ptr(self._present, bool, "present"), ptr(self.gain, float, "gain"), \
            ptr(self._phip, float, "phip")
        for name in ("xm", "hip", "proxy", "force", "force_master", "command"):
            setattr(c, name, ptr(getattr(out, name), float, f"TickOutput.{name}"))
        c.gain_out, c.robot_pos_out = ptr(out.gain, float, "TickOutput.gain"), ptr(out.robot_pos, float, "robot_pos")
        c.state = ptr(out.state, np.int32, "TickOutput.state")
        for name in ("coupled", "engage", "release"):
            setattr(c, name, ptr(getattr(out, name), bool, f"TickOutput.{name}"))
        c.arm_hold = ptr(out.arm_hold, np.int64, "TickOutput.arm_hold")
        c.orientation, c.jaw = ptr(out.orientation, float, "TickOutput.orientation"), ptr(out.jaw, float, "TickOutput.jaw")
        return c

    def _bind_input(self, inp: TickInput) -> tuple:
        """Point the compiled step at ``inp``'s arrays (again only when they are other arrays than
        last tick's: ``replay_tick`` and tests bring their own); returns the health's pointers."""
        arrays = (inp.master_pos, inp.pedal, inp.master_ok, inp.robot_pos, inp.robot_fault, inp.master_orientation,
                  inp.grasp, inp.robot_orientation, inp.robot_jaw)
        bound = self._bound_inp
        if bound and bound[0] and all(map(is_, arrays, bound[0])):
            return bound[1]
        n, c = self.n, self._core
        want = ((float, (n, 3)), (bool, (n,)), (bool, (n,)), (float, (n, 3)), (bool, (n,)), (float, (n, 4)),
                (float, (n,)), (float, (n, 4)), (float, (n,)))
        own = [as_array(a, dt, shape) for a, (dt, shape) in zip(arrays, want)]
        c.master_pos, c.pedal, c.master_ok, c.robot_pos = (ptr(a, dt, name) for a, (dt, _), name in zip(
            own, want, ("master_pos", "pedal", "master_ok", "robot_pos")))
        c.master_quat, c.grasp, c.robot_quat, c.robot_jaw = (ptr(a, float, name) for a, name in zip(
            own[5:], ("master_orientation", "grasp", "robot_orientation", "robot_jaw")))
        health_in = (c.master_ok, ptr(own[4], bool, "robot_fault"))
        # a converted copy is not the input's own array: bind again next tick (its values may
        # change); the copies live until then (the core's struct holds addresses, not arrays)
        same = all(x is y for x, y in zip(own, arrays))
        self._bound_inp = (arrays if same else (), health_in, own)
        return health_in

    def attach_frames(self, feeder) -> None:
        """The frame feeder the ticks read (``HapticScene.attach_frames``)."""
        self.scene.attach_frames(feeder)

    def start(self) -> None:
        """Place everything at its initial state (call after the first snapshot exists)."""
        inp, tp = self.inp, self.teleop
        self.devices.read_masters(inp)
        dev = inp.master_pos.copy()
        quat = np.where(inp.master_ok[:, None], inp.master_orientation, (1.0, 0.0, 0.0, 0.0))
        grasp = np.where(inp.master_ok, inp.grasp, 0.0)
        xr = qr = jr = None
        if self.devices.present.any():
            reg = tp.register(np.nan_to_num(dev), np.zeros((self.n, 3)))
            ideal_q = quat_mul(tp.qR, quat)
            ideal_j = np.clip(grasp, tp.jaw_lo, tp.jaw_hi)
            self.devices.read_robots(inp, reg, ideal_q, ideal_j)
            xr, qr, jr = inp.robot_pos.copy(), inp.robot_orientation.copy(), inp.robot_jaw.copy()
        tp.start(dev, xr, quat, grasp, qr, jr)
        np.copyto(self.out.robot_pos, tp.cmd)
        self.scene.start(tp.hip, self.haptics_on)
        self.devices.hold_all_robots()   # until the arm couples (pedal down, teleoperation engaged, healthy)
        self._started = True

    def _set_cfg(self, cfg) -> None:
        """The configuration in use, and the tick's copies of its numbers."""
        self.cfg = cfg
        self._max_age_s = cfg.service.max_frame_age_s
        self._ramp = (None, None)       # (dt, dt / force_ramp_s as a C double): ``step``

    def warm_up(self) -> None:
        """Compile and launch the proxy kernel once before the loop's first tick."""
        self.scene.warm_up(self.teleop.hip)

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

    def prepare_reconfiguration(self, radius=None, selection=None):
        """A new radius and/or selection for the snapshots, prepared outside the tick
        (``HapticScene.prepare_reconfiguration``); its ``commit()`` runs between two ticks
        (``call_between_ticks``) and re-anchors every arm (S1). None: nothing changes."""
        change = self.scene.prepare_reconfiguration(self.teleop.hip.copy(), radius, selection)
        if change is not None:
            change.on_commit = self._reconfigured
        return change

    def _reconfigured(self, cfg) -> None:
        self._set_cfg(cfg)
        self.teleop.slip_lift = slip_lift_radius(cfg)
        self.request_reanchor()      # S1: new fixture parameters move no robot by themselves

    def clear_faults(self) -> None:
        """Forget latched faults and re-enable robots in FAULT (their setpoint re-seats: no
        motion). Needs every arm decoupled (S3): raises InputError while an arm is coupled or its
        pedal is down with teleoperation engaged (it would couple at once). Call it
        between ticks (``call_between_ticks``: the control API does), where the pedals read are
        this tick's. An arm that couples again is re-anchored: clearing never moves a robot (S1)."""
        with self._ctl:
            down = [b for b in range(self.n) if self.out.coupled[b] or (self.inp.pedal[b] and self.teleop_on)]
            if down:
                raise InputError(f"clear-faults refused: arm(s) {down} coupled (foot pedal down, teleoperation on); "
                                 "release the pedal(s) or disengage teleoperation first, then clear the faults "
                                 "(SAFETY.md S3)")
            self.devices.clear_robot_faults()
            if self.grasper is not None:
                self.grasper.clear_fault()
            self.health.clear()
            self.last_error = None
            restart = getattr(self.scene.feeder, "restart_ingest", None)
            if restart is not None:
                restart()

    def on_stall(self, started: float, now: float) -> None:
        """The tick watchdog (``watchdog.TickWatchdog``, its own thread): the tick that started at
        ``started`` (loop clock, s) is still running at ``now``. The masters get zero force at
        once; the stalled tick, when it returns, and the ticks after it hold every arm for
        ``recover_s`` (S9). Robots need nothing here: they get no new command while the tick is
        stalled."""
        self.health.note_stall(now)
        self.devices.send_zero_forces()

    def call_between_ticks(self, fn) -> None:
        """Run ``fn(service)`` in the tick thread at the start of the next tick, before anything
        else (the control API's way to read or change the tick's state; ``fn`` must not raise and
        must be short: it runs inside the tick's deadline)."""
        self._between.append(fn)

    # --- the tick --------------------------------------------------------------------------------
    def tick(self, k: int, t: float, dt: float, overrun: bool, now: float) -> None:
        """One haptic tick (``loop.HapticLoop``'s target): see the module docstring."""
        if not self._started:
            self.start()
        while self._between:
            self._between.popleft()(self)
        inp = self.inp
        self.read(inp, k, t, dt, overrun, now)
        out = self.step(inp)
        self.write(out, dt)
        self.publish(inp, out)

    def replay_tick(self, inp: TickInput) -> TickOutput:
        """One tick of a recorded run (``pointfence replay --recording``): ``inp`` holds the
        recorded master samples, timing, frame time and age and control state; the robots and
        the snapshots are this process's (``HapticScene.sense_recorded``)."""
        if not self._started:
            self.start()
        self.devices.read_robots(inp, self.teleop.cmd, self.teleop.q_cmd, self.teleop.jaw_cmd)
        self.scene.sense_recorded(inp)
        out = self.step(inp)
        self.write(out, inp.dt)
        self.publish(inp, out)
        return out

    def read(self, inp: TickInput, k: int, t: float, dt: float, overrun: bool, now: float) -> None:
        """Fill ``inp``: the loop's timing, the control state, the masters, the robots, the frames."""
        inp.k, inp.t, inp.dt, inp.overrun, inp.now = k, t, dt, overrun, now
        inp.watchdog_stall = False
        if self._reanchor or self._pending_arch is not None:    # (a request set after this look is the next tick's)
            with self._ctl:
                inp.law_change = self._reanchor
                self._reanchor = False
                inp.architecture = self._pending_arch if self._pending_arch is not None else self.teleop.arch
                self._pending_arch = None
        else:
            inp.law_change = False
            inp.architecture = self.teleop.arch
        inp.haptics, inp.teleop = self.haptics_on, self.teleop_on
        self.devices.read_masters(inp)
        self.devices.read_robots(inp, self.teleop.cmd, self.teleop.q_cmd, self.teleop.jaw_cmd)
        if self.grasper is not None and self.grasper.faulted:     # (recorded: a replay holds as the run did)
            inp.robot_fault[self.grasper.arm] = True
        self.scene.sense(inp)

    def step(self, inp: TickInput) -> TickOutput:
        """The tick's decisions from its input: holds, teleoperation, proxies and forces, robot
        commands (see the module docstring). Touches no device; returns ``self.out``."""
        out, tp, health, scene = self.out, self.teleop, self.health, self.scene
        out.k, out.t = inp.k, inp.t
        health_in = self._bind_input(inp)
        # control law: a change re-anchors every arm (S1)
        if inp.architecture != tp.arch:
            tp.set_architecture(inp.architecture)     # (sets tp.law_changed)
        law_change = (inp.law_change or tp.law_changed or inp.haptics != scene.running
                      or inp.teleop != self._teleop_prev)
        tp.law_changed = False
        self._teleop_prev = inp.teleop
        health.assess(inp, self._max_age_s, health_in)
        proxies, states, normals = scene.batch_pointers()     # (a re-seat below keeps the batch's storage)
        if normals is not self._lift_normals:        # a new batch: III's slip lift reads its normals
            tp.bind_normals(normals)
            self._lift_normals = normals
        # teleoperation: a held arm's X_m does not follow the master (re-coupling must not replay its
        # motion); coupling; S1: an arm that (re)couples, and every arm at a change of control law,
        # starts from where its robot is commanded; the HIP; where the proxies move
        reseat = fast.pf_step_pre(self._core_ref, tp.ref, health.ref, proxies, int(law_change), int(inp.teleop))
        hip = tp.hip
        if inp.haptics and (not scene.running or (tp.arch == 3 and reseat)):
            # re-anchored arms' proxies start on the command in III (the proxy is the goal there:
            # a proxy that crept along the surface while the arm held must not pull the robot)
            # and on the HIP otherwise; the other arms' proxies stay where they are
            scene.reseat(self._reseat, tp.cmd if tp.arch == 3 else hip)
            if not scene.running:
                scene.renderer.reset()
        scene.running = inp.haptics
        out.kernel_us = 0.0
        if inp.haptics:
            try:
                scene.render(inp, out, self._phip, hip)
            except KernelError as e:
                health.latch(KERNEL)
                out.coupled[:] = False
                self.kernel_errors += 1
                self.last_error = f"tick {inp.k}: {e}"
        if health.take_stall():          # the watchdog saw this tick (or the last) stall
            inp.watchdog_stall = True    # (recorded: a replay of this tick stalls as it did)
        if inp.watchdog_stall:
            health.hold_all(WATCHDOG)
            health.seen(WATCHDOG, inp.t)
            out.coupled[:] = False
            self.gain[:] = 0.0
            self.last_error = (f"tick {inp.k}: tick watchdog: a tick ran past "
                               f"{self.cfg.service.max_lateness_s * 1e3:g} ms")
        # force gains (ramping over force_ramp_s) and frames; robot commands: the goal by
        # architecture, rate-limited, for coupled arms; a robot that decouples stops where it is
        ramp = self._ramp
        if ramp[0] != inp.dt:            # (the ramp's step per tick, as a C double: made again for another dt)
            ramp = self._ramp = (inp.dt, ctypes.c_double(inp.dt / self.cfg.service.force_ramp_s))
        fast.pf_step_post(self._core_ref, tp.ref, health.ref, scene.renderer.ref, proxies, states, int(inp.haptics),
                          ramp[1])
        out.hold = health.mask
        out.frame_seq = scene.frame_seq
        return out

    def _scale_forces(self, out: TickOutput) -> None:
        """The rendered forces times each arm's gain, in the world and each master's frame."""
        lib.pf_step_scale_forces(self._core_ref, self.teleop.ref, self.scene.renderer.ref)

    def write(self, out: TickOutput, dt: float) -> None:
        """Forces to the masters, commands to the robots (which step by ``dt``, s). A robot that
        refuses its command keeps its setpoint, and so does the command; the arm holds (S3)."""
        dev = self.devices
        dev.send_forces(out.force_master)
        if dev.command_robots(out, dt):          # (True: an arm refused its command)
            tp = self.teleop
            for b in np.flatnonzero(dev.refused):
                tp.cmd[b] = dev.kept[b]
                out.command[b] = dev.kept[b]
                tp.q_cmd[b] = dev.kept_orientation[b]
                out.orientation[b] = dev.kept_orientation[b]
                self.health.robot_seen(int(b), out.t)
            self.last_error = f"tick {out.k}: {dev.last_refusal}"
        g = self.grasper
        if g is not None:           # the jaw follows the grasp while the arm is coupled (never waits)
            if out.coupled[g.arm]:                 # (NaN, a jaw not yet known, is refused and counted)
                g.command(float(out.jaw[g.arm]))
            else:
                g.watch()

    def publish(self, inp: TickInput, out: TickOutput) -> None:
        """A copy of the tick's output for other threads (``snapshot``, ``status``); the recording."""
        self.kernel_us[self.ticks & (RING - 1)] = out.kernel_us
        self.ticks += 1
        p = self._published
        with self._pub_lock:
            fast.pf_step_publish(self._core_ref, self._pub_ref)    # xm, hip, proxy, command, robot, force, state,
            #                                          orientation, jaw; the input's master samples and their ok
            p.t, p.k = out.t, out.k
        if self.recorder is not None:
            self.recorder.write(inp, out)
        if self.telemetry is not None:
            self.telemetry.write(inp, out)

    def safe_tick(self, k: int, t: float, dt: float, now: float) -> None:
        """The loop's fallback after an exception: ramp forces down, hold robots, keep stepping.
        The pedals are still read (clearing the fault needs them up, S3); a master that cannot
        be read counts as pedal down."""
        out = self.out
        self.devices.read_pedals(t, self.inp.pedal)
        self.health.latch(EXCEPTION)
        self.gain -= dt / self.cfg.service.force_ramp_s
        np.maximum(self.gain, 0.0, out=self.gain)
        self._scale_forces(out)
        self.devices.send_forces(out.force_master)
        tp = self.teleop
        self.devices.hold_robots(dt, self._coupled_prev, tp.cmd, tp.q_cmd, tp.jaw_cmd)
        out.coupled[:] = False
        self._coupled_prev[:] = False
        out.hold = self.health.mask
        np.copyto(out.arm_hold, self.health.arm)

    def note_tick_us(self, us: float) -> None:
        """The loop's wall-clock compute time of the tick just recorded."""
        if self.recorder is not None:
            self.recorder.note_tick_us(us)

    # --- reading the service (any thread) ---------------------------------------------------------
    @property
    def architecture(self) -> str:
        return self.teleop.architecture

    @property
    def fixture_params(self):
        """The snapshots' parameters in use (``kernels.params.PipelineParams``: radius, selection,
        workspace, cell size)."""
        return self.scene.pipeline.params

    @property
    def last_tick(self) -> int:
        """The number (k) of the last tick published."""
        return self._published.k

    def snapshot(self) -> dict:
        """The last tick's published values (copies), for the control API and the demo."""
        with self._pub_lock:
            p = self._published
            out = {"xm": p.xm.copy(), "hip": p.hip.copy(), "proxy": p.proxy.copy(), "cmd": p.command.copy(),
                   "xr": p.robot_pos.copy(), "force": p.force.copy(), "state": p.state.copy(), "t": p.t,
                   "tick": p.k, "orientation": p.orientation.copy(), "jaw": p.jaw.copy()}
        return out

    def master_sample(self) -> dict:
        """The last published tick's raw master samples (copies): ``position`` (B, 3) in each
        master's own frame (m; NaN where it gave none), ``valid`` (B,), the tick's loop time ``t``
        (s) and number ``tick``. Read under the publish lock, never in the tick."""
        with self._pub_lock:
            p = self._published
            return {"position": self._pub_master.copy(), "valid": self._pub_master_ok.copy(), "t": p.t, "tick": p.k}

    def kernel_timing(self, since: int = 0) -> dict:
        """The kernel's share of the ticks since tick number ``since``: p50 and p99 (us) of the
        ticks that launched it."""
        lo = max(since, self.ticks - RING)
        us = self.kernel_us[np.arange(lo, self.ticks) & (RING - 1)]
        us = us[us > 0]
        if us.size == 0:
            return {"kernel_us_p50": 0.0, "kernel_us_p99": 0.0}
        return {"kernel_us_p50": float(np.percentile(us, 50)), "kernel_us_p99": float(np.percentile(us, 99))}

    def status(self, now: Optional[float] = None) -> dict:
        out, h = self.out, self.health
        st = {
            "architecture": self.architecture, "haptics": self.haptics_on, "teleop": self.teleop_on,
            "hold": reason_names(out.hold), "arms_holding": [reason_names(int(m)) for m in out.arm_hold],
            "hold_causes": describe(out.hold), "latched_faults": reason_names(h.latched),
            "watchdog_trips": h.watchdog_trips,
            "coupled": out.coupled.tolist(), "pedal": self.inp.pedal.tolist(), "force_gain": self.gain.round(3).tolist(),
            "kernel_errors": self.kernel_errors, "robot_errors": self.devices.refusals, "last_error": self.last_error,
        }
        st.update(self.scene.status(now))
        st["robots"] = self.devices.robot_status()
        if hasattr(self.recorder, "status"):   # MCAP: the writer process's health and losses
            st["recording"] = self.recorder.status()
        if self.telemetry is not None:          # ROS 2 telemetry: its publisher process's health
            st["telemetry"] = self.telemetry.status()
        if self.grasper is not None:            # [cable]: the grasper's estimate, alerts, fault
            st["grasper"] = self.grasper.snapshot().as_dict()
        return st

    def close(self) -> None:
        if self.recorder is not None:
            self.recorder.close()   # (streamed: the last rows reach the file)
        if self.grasper is not None:
            self.grasper.close()
        self.scene.close()

    # --- the components' parts, by their old names (tools and tests read them) ---------------------
    masters = property(lambda self: self.devices.masters)
    robots = property(lambda self: self.devices.robots)
    pipeline = property(lambda self: self.scene.pipeline)
    gate = property(lambda self: self.scene.gate)
    batch = property(lambda self: self.scene.batch)
    renderer = property(lambda self: self.scene.renderer)
    backend = property(lambda self: self.scene.backend)
    feeder = property(lambda self: self.scene.feeder)
    frame_filter = property(lambda self: self.scene.frame_filter)
    tool_poses = property(lambda self: self.scene.tool_poses)
    self_filter_off = property(lambda self: self.scene.self_filter_off)
    frame_seq = property(lambda self: self.scene.frame_seq)
    snapshot_first_tick = property(lambda self: self.scene.snapshot_first_tick)
    frame_time = property(lambda self: self.inp.frame_time)
    hold_mask = property(lambda self: self.out.hold)
    arm_hold = property(lambda self: self.out.arm_hold)
    coupled = property(lambda self: self.out.coupled)
    pedal = property(lambda self: self.inp.pedal)
    xr = property(lambda self: self.out.robot_pos)
    f_out = property(lambda self: self.out.force)
    f_master = property(lambda self: self.out.force_master)
    latched = property(lambda self: self.health.latched)
    watchdog_trips = property(lambda self: self.health.watchdog_trips)
    robot_errors = property(lambda self: self.devices.refusals)
    R = property(lambda self: self.teleop.R)


__all__ = ["Service", "reason_names", "REASONS", "HoldReason"]
