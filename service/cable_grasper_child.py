"""The grasper process of a ``cable_grasper.GrasperHost``: the cable-driven grasper controller of
chapters 4-5 (``cable.loop.CableLoop``: UKF + iLQG MPC, generated C) and its plant, stepped on
their own 1 kHz clock, taking the jaw command from the shared block and publishing the estimate.

Started as ``python -m pointfence.service.cable_grasper_child SHM TABLE PARENT PRIO`` (a fresh
interpreter: its 1 kHz Python work never takes the service's interpreter lock); it ends when told
to (``ctl["stop"]``) or when its parent is gone, leaving the motor unpowered. Its schedule is a
``periodic.PeriodicLoop`` (absolute deadlines; lost periods skipped and counted as misses); the
heartbeat ``ctl["ticks"]`` counts periods.

Each tick: the newest command (``cable_block.COMMAND``), the jaw setpoint (the command, clamped to
``[jaw_min, jaw_max]`` and moved towards it at most ``JAW_SPEED`` rad/s, so that a start or a
cleared fault never makes the jaw jump to a command far from where it is: SAFETY.md S1), the
encoder, a step of the stiffness filter (``TENSION_UKF``: k_e, learnt only while the jaw moves fast
in free motion), one ``CableLoop.tick`` (states and external torque), the torque to the plant,
every 100th tick a tension sample through the gate (``cable.tension.OnlineTension``: a tension, or
NaN for unknown), and the state row. Faults latch zero torque (``CableLoop.fault``) until the service clears them:
the loop's own (a non-finite encoder reading, estimate or torque, a parameter out of range), a tick
that started more than ``max_lateness_s`` after its deadline, and a hold the service asked for.
"""
from __future__ import annotations

import json
import math
import os
import sys
import time

import numpy as np

from .cable.loop import ONLINE_UKF, CableLoop
from .cable.params import DT, GrasperParams, true_params_at_tension
from .cable.plant import HuntCrossley, SimulatedPlant
from .cable.tension import OnlineTension, TensionGate, TensionMonitor, sim_filter_curve
from .cable.ukf import UKF, UKFConfig
from .cable_block import ALERT_TEXT, CONTROLLER, FAULT_TEXT, HELD, INJECT_NONE, LATE, GrasperBlock, put_text
from .cable_settings import CableTable, load_curve, load_params
from .clock import RealClock
from .periodic import PeriodicLoop
from .robot.hosted_block import attach_child

#: fastest jaw setpoint motion (rad/s): a grasp command far from the jaw is reached in a ramp
JAW_SPEED = 4.0
#: ticks between two tension samples
TENSION_EVERY = 100
#: the stiffness filter of the tension estimate: states and k_e, the external link torque taken from
#: the control filter (estimating both in one filter lets k_e and tau_l trade off against each other
#: in contact); a low link-velocity process noise so that the cable mode, not a velocity jump,
#: explains the encoder
TENSION_UKF = UKFConfig(estimate=("k_e",), q_param=(1e-8,), p0_param=(0.5,), q_state=(1e-10, 1e-10, 2e-3, 1e-4))
#: ticks after a contact ends before the stiffness filter learns again (the contact estimate settles)
CONTACT_HOLDOFF = 200


def build(table: CableTable):
    """(plant, loop, stiffness filter or None, online tension or None) of ``table``; compiles the
    UKFs and the MPC (cached). The control loop estimates the states and the external link torque
    with the stiffness of ``params`` (chapter 5: the on-line filter runs on the off-line
    parameters); the tension comes from a second filter that estimates k_e in free motion only."""
    params = GrasperParams() if table.params == "nominal" else load_params(table.params)
    contact = None if table.sim_contact_rad is None else HuntCrossley(q_contact=table.sim_contact_rad)
    plant = SimulatedPlant(true_params_at_tension(table.sim_tension_g), contact=contact)
    loop = CableLoop(params, ONLINE_UKF)
    stiffness = online = None
    if table.tension:
        curve = sim_filter_curve() if table.tension_curve is None else load_curve(table.tension_curve)
        stiffness = UKF(params, TENSION_UKF)
        online = OnlineTension(TensionMonitor(curve, table.tension_min_g, table.tension_max_g, axis="grasp"),
                               TensionGate())
    return plant, loop, stiffness, online


class ChildGrasper:
    """The controller over block ``blk``: ``tick(sched)`` runs one control period."""

    def __init__(self, blk: GrasperBlock, table: CableTable):
        self.blk, self.table = blk, table
        self.plant, self.loop, self.stiffness, self.online = build(table)
        self.S, self.C = blk.state_layout, blk.command_layout
        self.row = np.zeros(self.S.size)
        self.row_mv = memoryview(self.row)
        self.cmd = np.zeros(self.C.size)
        self.cmd_mv = memoryview(self.cmd)
        self.seq = self.clears = 0.0
        self.lo, self.hi = table.jaw_min, table.jaw_max
        self.fault_shown = None
        self.fault_code = 0             # the kind of a fault this process set (``cable_block.FAULT_CODES``)
        self.alert_shown = None
        self.tension = math.nan
        self.alert_code = 0
        self.late_max = self.compute_max = 0.0
        self.free_for = 0               # ticks since the last contact (the stiffness filter learns past CONTACT_HOLDOFF)
        self.contact_ticks = self.moving_ticks = 0      # over the current tension interval
        self.degraded = 1.0 if "interpreted" in (self.loop.ukf.how, self.loop.mpc.how) else 0.0
        self.reset_estimates()
        self.setpoint = self.target = float(self.loop.ukf.x[1])
        self.publish(0.0, 0.0, None)

    def reset_estimates(self) -> None:
        """Both filters restart at rest on the encoder; the tension is unknown until it is seen again
        (an alert stays until a confident estimate clears it)."""
        y = self.plant.measure()
        self.loop.reset(y)
        if self.stiffness is not None:
            self.stiffness.reset(y)
            self.online.restart()
            self.tension = math.nan
        self.free_for = self.contact_ticks = self.moving_ticks = 0

    def clear(self) -> None:
        """The service cleared the fault: the estimator restarts at rest on the encoder, the
        setpoint at the jaw (no jump: it ramps to the command)."""
        self.reset_estimates()
        self.fault_code = 0
        self.setpoint = float(self.loop.ukf.x[1])

    def tick(self, sched: PeriodicLoop) -> None:
        blk, C, loop = self.blk, self.C, self.loop
        if blk.cmd.read(self.cmd_mv):
            c = self.cmd
            if c[C.clear_seq] != self.clears:
                self.clears = c[C.clear_seq]
                self.clear()
            if c[C.hold] and loop.fault is None:
                loop.fault = "held by the service (it saw a grasper fault); clear faults to resume"
                self.fault_code = HELD
            if c[C.seq] != self.seq:
                self.seq = c[C.seq]
                jaw = c[C.jaw]
                if math.isfinite(jaw):
                    self.target = min(max(jaw, self.lo), self.hi)
        late = sched.late_s
        if late > self.table.max_lateness_s and loop.fault is None:
            loop.fault = (f"grasper loop late: a tick started {late * 1e3:.1f} ms after its deadline (bound "
                          f"[cable] max_lateness_s = {self.table.max_lateness_s * 1e3:g} ms)")
            self.fault_code = LATE
        step = JAW_SPEED * sched.dt
        sp = self.setpoint + min(max(self.target - self.setpoint, -step), step)
        self.setpoint = sp
        loop.qd.fill(sp)
        y = self.plant.measure() if blk.ctl["inject"] == INJECT_NONE else math.nan
        if self.stiffness is not None and loop.fault is None and math.isfinite(y):
            self.track_stiffness(y)
        u = loop.tick(y)
        self.plant.actuate(u)
        if self.stiffness is not None and sched.ticks % TENSION_EVERY == 0 and loop.fault is None:
            self.sample_tension()
        self.publish(late, time.perf_counter() - sched.started, sched)

    def track_stiffness(self, y: float) -> None:
        """One step of the stiffness filter on the torque of the last period and encoder ``y``, with
        the control filter's external torque; it learns k_e only in free motion (``CONTACT_HOLDOFF``
        ticks after a contact), where the model has every load the link feels."""
        loop, gate = self.loop, self.online.gate
        tau_l = loop.tau_l_estimate
        if abs(tau_l) > gate.contact_nm:
            self.free_for = 0
            self.contact_ticks += 1
        else:
            self.free_for += 1
        moving = abs(loop.ukf.x[3]) > gate.min_speed
        if moving:
            self.moving_ticks += 1
        st = self.stiffness
        st.set_fixed("tau_l", tau_l)
        st.step(loop.u_prev, y, learn=moving and self.free_for > CONTACT_HOLDOFF)
        if not st.healthy():            # a diverged stiffness filter restarts; control is unaffected
            st.reset(y)
            self.online.restart()

    def sample_tension(self) -> None:
        """Every ``TENSION_EVERY`` ticks: the stiffness estimate through the gate
        (``cable.tension.OnlineTension``) to the tension (NaN: unknown) and the alert."""
        k_e, k_std = self.stiffness.estimate(0), self.stiffness.estimate_std()["k_e"]
        free = self.contact_ticks == 0 and self.free_for > CONTACT_HOLDOFF
        moving = self.moving_ticks * 2 >= TENSION_EVERY
        self.contact_ticks = self.moving_ticks = 0
        self.tension = self.online.sample(k_e, k_std, free, moving)
        alert = self.online.alert
        self.alert_code = 0 if alert is None else (1 if alert.direction == "increase" else 2)
        self.show_alert(None if alert is None else alert.message)

    @property
    def k_e(self) -> float:
        """Cable stiffness [N/m]: the stiffness filter's estimate, or the control model's."""
        return self.loop.k_e_estimate if self.stiffness is None else self.stiffness.estimate(0)

    def show_alert(self, text) -> None:
        if text != self.alert_shown:
            self.alert_shown = text
            put_text(self.blk.text[ALERT_TEXT], text)
            self.row[self.S.alert_ver] += 1

    def publish(self, late: float, compute: float, sched) -> None:
        """The state row (``cable_block.STATE``) and, where it changed, the fault text."""
        S, r, loop, blk = self.S, self.row, self.loop, self.blk
        fault = loop.fault
        if fault != self.fault_shown:
            self.fault_shown = fault
            put_text(blk.text[FAULT_TEXT], fault)
            r[S.fault_ver] += 1
        blk.ctl["faulted"] = 0 if fault is None else 1
        self.late_max = max(self.late_max, late)
        self.compute_max = max(self.compute_max, compute)
        x = loop.ukf.x
        r[S.t] = time.perf_counter()
        if sched is not None:
            r[S.ticks], r[S.periods], r[S.misses] = sched.ticks + 1, sched.periods + 1, sched.misses
        r[S.cmd_seq], r[S.clear_seq], r[S.setpoint] = self.seq, self.clears, self.setpoint
        r[S.motor_angle], r[S.jaw], r[S.jaw_velocity] = x[0], x[1], x[3]
        r[S.motor_torque], r[S.link_torque], r[S.k_e] = loop.u_prev, loop.tau_l_estimate, self.k_e
        r[S.tension_g], r[S.tension_alert] = self.tension, self.alert_code
        r[S.late], r[S.late_max], r[S.compute], r[S.compute_max] = late, self.late_max, compute, self.compute_max
        r[S.faulted], r[S.degraded] = 0.0 if fault is None else 1.0, self.degraded
        r[S.fault_code] = 0 if fault is None else (self.fault_code or CONTROLLER)
        r[S.true_jaw], r[S.true_link_torque] = self.plant.link_angle, self.plant.env_torque
        blk.state.write(self.row_mv)


def main(shm_name: str, table: dict, parent: int, rt_priority: int) -> None:
    shm = attach_child(shm_name)
    grasper = None
    try:
        blk = GrasperBlock(shm.buf)
        grasper = ChildGrasper(blk, CableTable(**table))
        if rt_priority > 0:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(rt_priority)))
            except (AttributeError, OSError):
                pass
        ctl = blk.ctl
        ctl["pid"] = os.getpid()
        ctl["ready"] = 1
        sched = PeriodicLoop(DT, RealClock(spin_s=0.0))

        def body(k: int) -> None:
            grasper.tick(sched)
            ctl["ticks"] += sched.elapsed

        sched.run(body, keep_going=lambda: int(ctl["stop"]) == 0 and os.getppid() == parent)
    finally:
        if grasper is not None:
            grasper.plant.actuate(0.0)      # leave the motor unpowered
        shm.close()


if __name__ == "__main__":
    _shm, _table, _parent, _prio = sys.argv[1:5]
    main(_shm, json.loads(_table), int(_parent), int(_prio))
