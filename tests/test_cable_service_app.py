"""The ``[cable]`` grasper in the running service (app.py wiring, control_api metrics, MCAP
recording): the service starts the grasper process, commands the jaw while the arm is coupled,
shows the estimate in its status and metrics, holds the arm on a grasper fault with the fault
named (SAFETY.md S3) and clears it with the other faults; the recording carries the jaw as
``sensor_msgs/JointState`` (effort: the estimated external torque) and the grasper's health as
``diagnostic_msgs/DiagnosticArray``."""
from __future__ import annotations

import time

import numpy as np

from pointfence.service.cable_grasper import RECORD_FIELDS, GrasperHost
from pointfence.service.cable_settings import CableTable
from pointfence.service.control_api import Controller
from pointfence.service.holds import ROBOT
from pointfence.service.mcap_record import McapRecorder
from pointfence.service.replay import simulate
from pointfence.service.tick_io import TickInput, TickOutput
from service_cases import POINT_MASS, balloon_config, needs_opencl, push
from test_mcap_record import ros2_messages


def _wait_fault(svc, seconds=3.0):
    end = time.monotonic() + seconds
    while time.monotonic() < end and not svc.grasper.faulted:
        svc.grasper.command(0.0)
        time.sleep(0.001)
    return svc.grasper.faulted


@needs_opencl
def test_the_service_runs_the_grasper_reports_it_and_holds_the_arm_on_its_fault(tmp_path):
    cfg = balloon_config(tmp_path, robot=POINT_MASS, extra="[cable]\nmax_lateness_s = 0.1\n")
    seen = {}

    def inject(svc):
        seen["before"] = svc.status()
        svc.grasper.inject("nan")
        assert _wait_fault(svc)

    def after(svc):
        seen["after"] = svc.status()
        svc.grasper.inject("none")

    svc, loop, sources = simulate(cfg, [push(0.02, t_end=0.4, hold=0.4)], 0.9, events={500: inject, 600: after})
    try:
        for s in sources:
            s.close()
        g = seen["before"]["grasper"]
        assert g["arm"] == 0 and g["fault"] is None and g["commands"] > 100 and g["running"]
        assert set(g) >= {"jaw", "motor_torque", "link_torque", "tension_g", "alerts", "deadline_misses", "late_max_ms"}
        st = seen["after"]
        assert "motor encoder reading is not finite" in st["grasper"]["fault"]
        assert st["grasper"]["motor_torque"] == 0.0
        assert "robot fault or rejected command" in st["arms_holding"][0]     # the arm holds (S3)
        rec = svc.recorder
        holds = rec.holds[: rec.count, 1].astype(np.int64)
        assert not (holds[100:500] & ROBOT).any() and (holds[510:600] & ROBOT).all()
        # the master's force ramps out and the robot gets no new command while it holds
        assert not svc.out.coupled[0]
        # clearing needs the arm decoupled (S3): the scripted pedal stays down, so teleoperation goes off
        svc.engage_teleop(False)
        svc.clear_faults()
        end = time.monotonic() + 3.0
        while time.monotonic() < end and svc.grasper.faulted:
            svc.grasper.command(0.0)
            time.sleep(0.001)
        assert not svc.grasper.faulted and svc.status()["grasper"]["fault"] is None
    finally:
        svc.close()
    assert svc.grasper.pid is None                       # close() ended the grasper process


@needs_opencl
def test_metrics_carry_the_grasper(tmp_path):
    cfg = balloon_config(tmp_path, robot=POINT_MASS, extra="[cable]\nmax_lateness_s = 0.1\n")
    out = {}

    def metrics(svc):
        c = Controller(svc)
        c._in_tick = lambda fn, what, leave_safe_mode=False: fn(svc)    # (no loop thread here: run it in place)
        out["m"] = c.get_metrics({})

    svc, loop, sources = simulate(cfg, [push(0.02, t_end=0.3, hold=0.2)], 0.3, events={250: metrics})
    try:
        for s in sources:
            s.close()
        m = out["m"]["grasper"]
        assert m["arm"] == 0 and m["fault"] is None and "tension_g" in m and "deadline_misses" in m
    finally:
        svc.close()


def test_the_recording_carries_the_jaw_estimate_and_the_grasper_health(tmp_path):
    host = GrasperHost(CableTable(max_lateness_s=0.1))
    host.start()
    path = tmp_path / "grasper.mcap"
    try:
        rec = McapRecorder(path, 1)
        rec.record_grasper(host)
        inp, out = TickInput.zeros(1), TickOutput.zeros(1)
        rows = {}
        for k in range(1200):
            inp.k = out.k = k
            inp.t = inp.now = out.t = k * 1e-3
            host.command(0.25)
            if k == 900:
                host.inject("nan")
                end = time.monotonic() + 3.0
                while not host.faulted and time.monotonic() < end:
                    host.command(0.25)
                    time.sleep(0.001)
            rec.write(inp, out)
            if k % 10 == 0:
                rows[k] = rec._grasper[1].rows[k % rec.capacity, 0].copy()   # what the tick copied
            time.sleep(0.0005)
        rec.close()
        assert rec.write_error is None, rec.write_error
    finally:
        host.close()
    msgs = list(ros2_messages(path))
    js = [m for m in msgs if m.channel.topic == "/PSM1/jaw/measured_js"]
    sp = [m for m in msgs if m.channel.topic == "/PSM1/jaw/setpoint_js"]
    diag = [m for m in msgs if m.channel.topic == "/pointfence/arm0/grasper"]
    assert len(js) == len(sp) == 120 and js[0].schema.name == "sensor_msgs/JointState"
    col = {f: i for i, f in enumerate(RECORD_FIELDS)}
    for i, m in enumerate(js):
        r, q = rows[10 * i], m.ros_msg
        assert list(q.name) == ["jaw"]
        assert (q.position[0], q.velocity[0], q.effort[0]) == (r[col["jaw"]], r[col["jaw_velocity"]], r[col["link_torque"]])
        assert (sp[i].ros_msg.position[0], sp[i].ros_msg.effort[0]) == (r[col["setpoint"]], r[col["motor_torque"]])
    assert diag[0].schema.name == "diagnostic_msgs/DiagnosticArray"
    levels = [m.ros_msg.status[0].level for m in diag]
    first_err = levels.index(2)
    assert set(levels[:first_err]) <= {0, 1} and set(levels[first_err:]) == {2}
    st = diag[first_err].ros_msg.status[0]
    assert st.message == "fault: controller; grasper torque is zero" and st.hardware_id == "PSM1 jaw"
    kv = {v.key: v.value for v in st.values}
    assert kv["fault"] == "controller" and float(kv["motor_torque"]) == 0.0
    after = [m.ros_msg.effort[0] for m in sp if m.message.log_time >= diag[first_err].message.log_time]
    assert after and all(e == 0.0 for e in after)     # zero torque recorded from the fault on
