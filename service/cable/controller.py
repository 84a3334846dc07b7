"""The 1 kHz cable-control thread driven by the master's grasp command.

``CableController`` owns a ``CableLoop`` (UKF + iLQG MPC) and a plant interface (an object with
``measure() -> motor angle`` and ``actuate(torque)``; ``SimulatedPlant`` here, the motor
driver on a robot). It ticks on a ``periodic.PeriodicLoop`` (the schedule every 1 kHz loop of
pointfence runs on): absolute deadlines t0 + k dt (no drift), on a ``RealClock`` that sleeps
until ``spin_s`` (1 ms) before the deadline and then spins, yielding the interpreter lock; each
tick's compute time and lateness are measured, and deadline misses counted: a tick that finishes
after its period ends, and every period lost when the loop fell whole periods behind (those are
skipped, never run in a burst). The UKF and the MPC are fixed-step models (``DT``): the tick after
a skip runs one step of them on the newest encoder reading. ``status()`` returns a
``CableStatus`` snapshot for the control API. ``run_ticks(n)`` runs ticks in the calling thread
(tests, on a ``clock.FakeClock``).

Safe behaviour: a non-finite encoder reading, estimate or torque, or an estimated parameter
outside its physical range, latches a fault: the motor torque is zero from that tick on and an
alert says why, until ``clear_fault()``. Without compiled C (no compiler, or compiling failed)
the loop runs interpreted and ``status()`` carries a DEGRADED alert.
"""
from __future__ import annotations

import dataclasses
import math
import threading

import numpy as np

from pointfence.kernels.errors import InputError

from ..clock import RealClock
from ..osthread import name_this_thread
from ..periodic import PeriodicLoop
from .loop import ONLINE_UKF, CableLoop
from .params import DT, GrasperParams
from .tension import TensionMonitor
from .ukf import UKFConfig

_RING = 4096


@dataclasses.dataclass(frozen=True)
class CableStatus:
    running: bool
    ticks: int
    grasp_command: float            # desired link angle [rad]
    link_angle_estimate: float      # [rad]
    motor_torque: float             # last commanded torque [N m]
    estimated_link_torque: float    # external torque on the link (contact) [N m]
    k_e_estimate: float             # cable stiffness used / estimated [N/m]
    estimated_tension_g: float | None
    alerts: tuple                   # human-readable alerts
    fault: str | None
    compute_p50_us: float
    compute_p99_us: float
    compute_max_us: float
    lateness_p99_us: float
    deadline_misses: int            # ticks that ended past their period + periods skipped
    periods: int                    # control periods so far, run or skipped


class CableController:
    """The cable controller's 1 kHz thread (see the module docstring). ``clock``: the loop's
    clock (default ``RealClock(spin_s, spin_yield=True)``)."""

    def __init__(self, plant, params: GrasperParams, *, ukf_config: UKFConfig | None = None,
                 tension_monitor: TensionMonitor | None = None, angle_limits=(-1.2, 1.2),
                 dt: float = DT, spin_s: float = 1e-3, clock=None):
        if abs(dt - DT) > 1e-12:
            raise InputError(f"the cable controller runs at dt={DT} s (the model's step); got {dt!r}")
        lo, hi = angle_limits
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise InputError(f"angle_limits={angle_limits!r} must be two finite angles lo < hi [rad]")
        self.plant = plant
        self.loop = CableLoop(params, ukf_config or ONLINE_UKF)
        self.monitor = tension_monitor
        self.limits = (float(lo), float(hi))
        self.dt, self.spin_s = dt, spin_s
        self.clock = clock if clock is not None else RealClock(spin_s, spin_yield=True)
        self._cmd = 0.0
        self._lock = threading.Lock()
        self._periodic = PeriodicLoop(dt, self.clock, ring=_RING)
        self._thread: threading.Thread | None = None
        self._u = 0.0
        self._tension: float | None = None
        self._tension_alert = None
        self.error: BaseException | None = None

    # -- commands --------------------------------------------------------------------------
    def set_grasp_command(self, angle: float) -> None:
        """Desired link (jaw) angle [rad] from the master's grasp DoF, clamped to the limits."""
        a = float(angle)
        if not math.isfinite(a):
            raise InputError(f"grasp command {angle!r} rad must be finite")
        self._cmd = min(max(a, self.limits[0]), self.limits[1])

    def clear_fault(self) -> None:
        with self._lock:
            self.loop.reset(self.plant.measure())

    def start(self) -> None:
        if self._thread is not None and self._thread.is_alive():
            raise InputError("cable controller is already running; stop() it first")
        self._periodic = PeriodicLoop(self.dt, self.clock, ring=_RING)   # a new schedule from now
        self.loop.reset(self.plant.measure())
        self._thread = threading.Thread(target=self._run, name="pointfence-cable-1kHz", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._periodic.stop()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._thread = None
        try:
            self.plant.actuate(0.0)  # leave the motor unpowered
        except Exception:  # noqa: BLE001 - best effort on shutdown
            pass

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc):
        self.stop()

    # -- the loop --------------------------------------------------------------------------
    def _run(self) -> None:
        name_this_thread("pf-cable-1kHz")
        try:
            self._periodic.run(self._tick)
        except BaseException as e:  # noqa: BLE001 - report, make the motor safe
            self.error = e
            self.loop.fault = f"control thread crashed: {e!r}"
            try:
                self.plant.actuate(0.0)
            except Exception:  # noqa: BLE001
                pass

    def run_ticks(self, n: int) -> None:
        """Run ``n`` ticks in the calling thread, on the controller's schedule (tests on a
        ``FakeClock``; not while the thread runs)."""
        if self._thread is not None and self._thread.is_alive():
            raise InputError("run_ticks: the cable controller's thread is running; stop() it first")
        sched = self._periodic
        for _ in range(int(n)):
            sched.begin()
            try:
                self._tick(sched.tick_k)
            finally:
                sched.end()

    def _tick(self, k: int) -> None:
        """One control period: the grasp command over the horizon, the encoder, the torque."""
        with self._lock:
            self.loop.qd.fill(self._cmd)
            u = self.loop.tick(self.plant.measure())
            self.plant.actuate(u)
            self._u = u
        if (self._periodic.ticks + 1) % 100 == 0:
            self._update_tension()

    def _update_tension(self) -> None:
        if self.monitor is None:
            return
        k_e = self.loop.k_e_estimate
        if math.isfinite(k_e) and k_e > 0:
            self._tension, self._tension_alert = self.monitor.check(k_e)

    # -- status ----------------------------------------------------------------------------
    def status(self) -> CableStatus:
        with self._lock:
            late, comp = self._periodic.recent(0)
            sched = self._periodic
            ticks, misses, periods = sched.ticks, sched.misses, sched.periods
            fault = self.loop.fault
            x = self.loop.ukf.x.copy()
            tau_l = self.loop.tau_l_estimate
            k_e = self.loop.k_e_estimate
            u = self._u
        alerts = []
        if fault:
            alerts.append(f"FAULT: {fault}; motor torque is held at zero (clear_fault() to resume)")
        if "interpreted" in (self.loop.ukf.how, self.loop.mpc.how):
            alerts.append("DEGRADED: C code generation failed or no C compiler (POINTFENCE_CC); the UKF/MPC "
                          "run in CasADi's interpreter, several times slower (see the CodegenFallbackWarning)")
        if self._tension_alert is not None:
            alerts.append(self._tension_alert.message)
        if misses:
            alerts.append(f"{misses} of {periods} control periods missed their 1 ms deadline")
        pct = (lambda a, q: float(np.percentile(a, q) * 1e6) if a.size else float("nan"))
        return CableStatus(
            running=self._thread is not None and self._thread.is_alive(), ticks=ticks,
            grasp_command=self._cmd, link_angle_estimate=float(x[1]), motor_torque=u,
            estimated_link_torque=tau_l, k_e_estimate=k_e, estimated_tension_g=self._tension,
            alerts=tuple(alerts), fault=fault, compute_p50_us=pct(comp, 50), compute_p99_us=pct(comp, 99),
            compute_max_us=float(comp.max() * 1e6) if comp.size else float("nan"),
            lateness_p99_us=pct(late, 99), deadline_misses=misses, periods=periods)
