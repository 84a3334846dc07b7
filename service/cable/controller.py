"""The 1 kHz cable-control thread driven by the master's grasp command.

``CableController`` owns a ``CableLoop`` (UKF + iLQG MPC) and a plant interface (an object with
``measure() -> motor angle`` and ``actuate(torque)``; ``SimulatedPlant`` here, the motor
driver on a robot). It runs on absolute deadlines t0 + k dt (no drift), sleeping with
``time.sleep`` until ~1 ms before the deadline and spinning on ``time.perf_counter`` for the
rest; it measures each tick's compute time and lateness and counts deadline misses (a tick that
finishes after its period ends). ``status()`` returns a ``CableStatus`` snapshot for the
control API.

Safe behaviour: a non-finite encoder reading, estimate or torque, or an estimated parameter
outside its physical range, latches a fault: the motor torque is zero from that tick on and an
alert says why, until ``clear_fault()``. Without compiled C (no compiler, or compiling failed)
the loop runs interpreted and ``status()`` carries a DEGRADED alert.
"""
from __future__ import annotations

import dataclasses
import math
import threading
import time

import numpy as np

from pointfence.kernels.errors import InputError

from ..osthread import name_this_thread
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
    deadline_misses: int


class CableController:
    def __init__(self, plant, params: GrasperParams, *, ukf_config: UKFConfig | None = None,
                 tension_monitor: TensionMonitor | None = None, angle_limits=(-1.2, 1.2),
                 dt: float = DT, spin_s: float = 1e-3):
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
        self._cmd = 0.0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._compute = np.zeros(_RING)
        self._late = np.zeros(_RING)
        self._ticks = 0
        self._misses = 0
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
        self._stop.clear()
        self.loop.reset(self.plant.measure())
        self._thread = threading.Thread(target=self._run, name="pointfence-cable-1kHz", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
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
            self._loop()
        except BaseException as e:  # noqa: BLE001 - report, make the motor safe
            self.error = e
            self.loop.fault = f"control thread crashed: {e!r}"
            try:
                self.plant.actuate(0.0)
            except Exception:  # noqa: BLE001
                pass

    def _loop(self) -> None:
        dt, spin = self.dt, self.spin_s
        perf, sleep = time.perf_counter, time.sleep
        loop, plant, qwin = self.loop, self.plant, self.loop.qd
        start = perf()
        k = 0
        while not self._stop.is_set():
            deadline = start + (k + 1) * dt
            t0 = perf()
            with self._lock:
                qwin.fill(self._cmd)
                u = loop.tick(plant.measure())
                plant.actuate(u)
                self._u = u
            t1 = perf()
            i = self._ticks % _RING
            self._compute[i] = t1 - t0
            self._late[i] = t0 - (start + k * dt)
            self._ticks += 1
            if t1 > deadline:
                self._misses += 1
            if self._ticks % 100 == 0:
                self._update_tension()
            k += 1
            now = perf()
            if now > deadline + 5 * dt:  # hopelessly behind (e.g. a debugger): resynchronise
                start = now - k * dt
                continue
            rem = deadline - now
            if rem > spin:
                sleep(rem - spin)
            while perf() < deadline:
                sleep(0)

    def _update_tension(self) -> None:
        if self.monitor is None:
            return
        k_e = self.loop.k_e_estimate
        if math.isfinite(k_e) and k_e > 0:
            self._tension, self._tension_alert = self.monitor.check(k_e)

    # -- status ----------------------------------------------------------------------------
    def status(self) -> CableStatus:
        with self._lock:
            n = min(self._ticks, _RING)
            comp = self._compute[:n].copy()
            late = self._late[:n].copy()
            fault = self.loop.fault
            x = self.loop.ukf.x.copy()
            tau_l = self.loop.tau_l_estimate
            k_e = self.loop.k_e_estimate
            ticks, misses, u = self._ticks, self._misses, self._u
        alerts = []
        if fault:
            alerts.append(f"FAULT: {fault}; motor torque is held at zero (clear_fault() to resume)")
        if "interpreted" in (self.loop.ukf.how, self.loop.mpc.how):
            alerts.append("DEGRADED: C code generation failed or no C compiler (POINTFENCE_CC); the UKF/MPC "
                          "run in CasADi's interpreter, several times slower (see the CodegenFallbackWarning)")
        if self._tension_alert is not None:
            alerts.append(self._tension_alert.message)
        if misses:
            alerts.append(f"{misses} of {ticks} control ticks missed their 1 ms deadline")
        pct = (lambda a, q: float(np.percentile(a, q) * 1e6) if a.size else float("nan"))
        return CableStatus(
            running=self._thread is not None and self._thread.is_alive(), ticks=ticks,
            grasp_command=self._cmd, link_angle_estimate=float(x[1]), motor_torque=u,
            estimated_link_torque=tau_l, k_e_estimate=k_e, estimated_tension_g=self._tension,
            alerts=tuple(alerts), fault=fault, compute_p50_us=pct(comp, 50), compute_p99_us=pct(comp, 99),
            compute_max_us=float(comp.max() * 1e6) if comp.size else float("nan"),
            lateness_p99_us=pct(late, 99), deadline_misses=misses)
