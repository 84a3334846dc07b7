"""CRTK masters over ROS 2 (service/ros2/crtk_master.py, crtk_device.py, master_bridge.py) and the
simulated master node (`pointfence ros2 sim-master`): poses and the pedal arrive, forces go back
in the device's frame, and silence, NaN, a wrong frame, a malformed pedal or a dead bridge make
the master invalid so that the arm holds (S6, S9). Every ROS 2 process runs in the test
session's machine-local DDS environment (the ``ros2_env`` fixture)."""
from __future__ import annotations

import csv
import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service.ros2.crtk_device import CrtkDevice
from pointfence.service.ros2.master_block import REJECT_FRAME, REJECT_NONFINITE, REJECT_RANGE

from service_cases import POINT_MASS, balloon_config, needs_opencl


def wait_for(cond, timeout=10.0, every=0.01):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(every)
    return cond()


def polled(m, cond, timeout=10.0):
    """Poll master ``m`` (as a tick would) until ``cond(m)``."""
    def step():
        m.poll(time.monotonic())
        return cond(m)
    return wait_for(step, timeout)


# --- the device's checks, no ROS ---------------------------------------------------------------------
def test_device_topics_and_checks():
    d = CrtkDevice("/MTMR/")
    assert (d.namespace, d.pose_topic, d.force_topic) == ("MTMR", "/MTMR/measured_cp", "/MTMR/body/servo_cf")
    assert d.cf_orientation_topic == "/MTMR/body/set_cf_orientation_absolute"
    assert d.check_pose("MTMR_base", None, (0.1, 0, 0), (1, 0, 0, 0)) is None
    assert d.check_pose("a", None, (math.nan, 0, 0), (1, 0, 0, 0))[0] == REJECT_NONFINITE
    assert d.check_pose("a", None, (0, 0, 0), (math.inf, 0, 0, 0))[0] == REJECT_NONFINITE
    assert d.check_pose("b", "a", (0, 0, 0), (1, 0, 0, 0))[0] == REJECT_FRAME         # locked to the first frame
    assert CrtkDevice("M", frame_id="base").check_pose("a", None, (0, 0, 0), (1, 0, 0, 0))[0] == REJECT_FRAME
    assert d.check_pose("a", None, (3.0, 0, 0), (1, 0, 0, 0))[0] == REJECT_RANGE      # 3 m from the origin
    assert d.check_pose("a", None, (0, 0, 0), (0.5, 0, 0, 0))[0] == REJECT_RANGE      # not a unit quaternion
    # the pedal: dVRK values 0 released, 1 pressed, 2 quick tap (after a release); anything else is malformed
    assert [d.pedal_state(b) for b in ([1], [0], [2], [7], [])] == [1, 0, 0, None, None]
    assert CrtkDevice("M", clutch_button=2).pedal_state([1, 1]) is None
    clutch, deadman = CrtkDevice("M"), CrtkDevice("M", pedal="couples")
    assert [clutch.coupled(s) for s in (-1, 0, 1)] == [False, True, False]       # released couples
    assert [deadman.coupled(s) for s in (-1, 0, 1)] == [False, False, True]      # pressed couples


@pytest.mark.parametrize("kw, fragment", [
    ({"namespace": " "}, "namespace"),
    ({"namespace": "M", "pedal": "on"}, "pedal = 'on'"),
    ({"namespace": "M", "timeout_ms": 5000}, "timeout = 5000 ms"),
    ({"namespace": "M", "clutch_button": -1}, "clutch button = -1"),
    ({"namespace": "M", "max_position_m": 50.0}, "max_position_m = 50.0"),
    ({"namespace": "M", "pose_topic": "a b"}, "pose topic"),
])
def test_bad_device_settings_are_clear_errors(kw, fragment):
    with pytest.raises(InputError, match=fragment.replace("(", r"\(")):
        CrtkDevice(**kw)


# --- a sim-master process drives a CRTK master here ------------------------------------------------------
def test_sim_master_drives_a_crtk_master_and_receives_its_forces(ros2_env, tmp_path):
    from pointfence.service.ros2.crtk_master import CrtkMasterHost

    traj = tmp_path / "traj.csv"      # pedal coupled for 1.5 s, then decoupled (a dVRK clutch: pressed)
    traj.write_text("t,x,y,z,clutch\n0,0,0,0,1\n1.5,0.01,0.02,-0.03,1\n1.51,0.01,0.02,-0.03,0\n60,0.01,0.02,-0.03,0\n")
    forces = tmp_path / "forces.csv"
    sim = subprocess.Popen([sys.executable, "-m", "pointfence.cli", "ros2", "sim-master", "--namespace", "MTMR",
                            "--trajectory", str(traj), "--rate", "500", "--forces", str(forces), "--status-every", "0", "--start-on-force"],
                           env={**os.environ, **ros2_env}, stdout=subprocess.PIPE, text=True)
    host = CrtkMasterHost([CrtkDevice("MTMR", timeout_ms=200)])
    m = host.masters[0]
    try:
        assert polled(m, lambda m: (m.send_force(np.zeros(3)), m.ok and m.clutch)[1], 20), host.status()
        z0 = m.position[2]
        assert polled(m, lambda m: m.position[2] < z0 - 0.005), "measured_cp positions do not move"
        np.testing.assert_allclose(m.orientation, [1, 0, 0, 0])
        end = time.monotonic() + 0.3
        while time.monotonic() < end:                    # the tick's forces, N, master frame
            m.send_force(np.array([1.5, -0.5, 2.0]))
            time.sleep(0.002)
        assert polled(m, lambda m: not m.clutch, 5), "the pedal's press (declutch) did not arrive"
        assert m.ok                                       # declutched, still a valid device
        st = host.status()["devices"][0]
        assert st["frame_id"] == "MTMR_base" and st["forces_sent"] > 50
        # no new force for the timeout: the bridge zeroes the last one (the service stalled or died)
        assert wait_for(lambda: host.status()["devices"][0]["forces_zeroed"] >= 1, 5)
        published = host.status()["devices"][0]["forces_published"]
        m.send_force(np.array([0.0, 3.0, 0.0]))           # and a force the bridge holds when it is closed:
        assert wait_for(lambda: host.status()["devices"][0]["forces_published"] > published, 5)
        zeroed = host.status()["devices"][0]["forces_zeroed"]
    finally:
        host.close()                                     # it ends with a zero wrench, before its watchdog would
        sim.send_signal(signal.SIGTERM)
        out, _ = sim.communicate(timeout=10)
    summary = json.loads(out.strip().splitlines()[-1])
    rows = list(csv.DictReader(forces.open()))
    pushed = [r for r in rows if float(r["fx"]) == 1.5]
    assert len(pushed) > 20, summary
    assert {r["frame_id"] for r in rows} == {"MTMR_base"}
    assert all((float(r["fy"]), float(r["fz"])) == (-0.5, 2.0) for r in pushed)
    f = [(float(r["fx"]), float(r["fy"]), float(r["fz"])) for r in rows]
    assert (0.0, 0.0, 0.0) in f[f.index((1.5, -0.5, 2.0)):f.index((0.0, 3.0, 0.0))]    # the watchdog's zero
    assert f[-2:] == [(0.0, 3.0, 0.0), (0.0, 0.0, 0.0)] and zeroed == 1               # the closing zero
    assert summary["forces_received"] == len(rows) and summary["max_force_n"] == pytest.approx(3.0, abs=1e-3)


# --- bad messages, silence and a dead bridge make the master invalid --------------------------------------
def test_nan_wrong_frame_bad_pedal_silence_and_a_dead_bridge_make_the_master_invalid(ros2_env):
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import Joy

    from pointfence.service.ros2 import cdr
    from pointfence.service.ros2.crtk_master import CrtkMasterHost
    from pointfence.service.ros2.node import RosNode

    host = CrtkMasterHost([CrtkDevice("PFT", frame_id="pft_base", clutch_topic="/pft/pedal", pedal="couples",
                                      timeout_ms=100)])
    m = host.masters[0]
    lab = RosNode("pf_test_lab").start()
    pose_pub = lab.node.create_publisher(PoseStamped, "/PFT/measured_cp", 10)
    pedal_pub = lab.node.create_publisher(Joy, "/pft/pedal", 10)

    def send(x=0.01, frame="pft_base", w=1.0, pedal=(1,)):
        p = PoseStamped()
        p.header.frame_id = frame
        p.pose.position.x, p.pose.orientation.w = x, w
        pose_pub.publish(p)
        pedal_pub.publish(Joy(buttons=list(pedal)))

    ok_pose = PoseStamped()
    ok_pose.header.frame_id = "pft_base"
    ok_pose.pose.position.x, ok_pose.pose.orientation.w = 0.01, 1.0

    def until(cond, **kw):
        return polled(m, lambda m: (send(**kw), cond(m))[1], 15)

    try:
        assert until(lambda m: m.ok and m.clutch and m.position[0] == 0.01)
        assert until(lambda m: not m.ok, x=math.nan)                            # NaN: invalid at once
        st = m.status()
        assert st["rejected"]["non_finite"] >= 1 and "non-finite" in st["last_rejection"]
        assert m.position[0] == 0.01                                            # the NaN never reached it
        assert until(lambda m: m.ok, x=0.02)
        # a wrong frame_id (waited for by its reason: on a loaded machine the master may first go
        # invalid by silence, as in a clean clone's suite once)
        assert until(lambda m: not m.ok and "'world'" in (m.status()["last_rejection"] or ""), x=0.5, frame="world")
        assert m.position[0] == 0.02
        assert until(lambda m: m.ok, x=0.02)
        assert until(lambda m: not m.ok, x=0.02, w=2.0)                         # not a unit quaternion
        assert until(lambda m: m.ok and m.clutch)
        before = m.position[0]
        junk = bytearray(cdr.StampedWriter("pose", "pft_base").encode(0, (0.03, 0, 0, 0, 0, 0, 1)))
        junk[12:16] = (4000).to_bytes(4, "little")                              # frame_id's length: past the end
        assert polled(m, lambda m: (pose_pub.publish(bytes(junk)), not m.ok)[1], 15)   # bytes no pose: refused
        st = m.status()
        assert st["rejected"]["unreadable"] >= 1 and "frame_id: length 4000" in st["last_rejection"]
        assert m.position[0] == before                                          # (the 0.03 in the junk never reached it)
        assert until(lambda m: m.ok and m.clutch)
        junk = cdr.CDR_LE + (0).to_bytes(8, "little") + (1).to_bytes(4, "little") + b"\0\0\0\0" + (10**6).to_bytes(4, "little")
        assert polled(m, lambda m: (pose_pub.publish(ok_pose), pedal_pub.publish(junk), not m.clutch)[2], 15)
        assert "the message could not be read" in m.status()["last_rejection"]  # (a Joy of 10**6 axes in 24 bytes)
        assert until(lambda m: m.ok and m.clutch)
        assert until(lambda m: not m.clutch, pedal=())                          # no button 0: decoupled
        assert m.status()["rejected"]["pedal"] >= 1
        assert until(lambda m: m.ok and m.clutch)
        assert polled(m, lambda m: not m.ok, 5)                                 # silence: stale after 100 ms
        assert m.status()["stale_ticks"] >= 1
        assert until(lambda m: m.ok)
        os.kill(host.status()["bridge"]["pid"], signal.SIGKILL)                 # the bridge dies
        assert until(lambda m: not m.ok)
        assert not host.alive and host.status()["bridge"]["exit_code"] == -signal.SIGKILL
    finally:
        lab.close()
        host.close()


# --- a lab's own rclpy node drives a live run and feels the fixture -----------------------------------------
LAB = textwrap.dedent("""
    # a lab's own code: rclpy and the standard messages only
    import json, math, sys, threading, time
    import rclpy
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from sensor_msgs.msg import Joy

    rclpy.init()
    node = rclpy.create_node("lab_master")
    pose_pub = node.create_publisher(PoseStamped, "/LAB/measured_cp", 10)
    pedal_pub = node.create_publisher(Joy, "/lab/deadman", 10)
    got = {"n": 0, "max": 0.0, "frames": set()}
    def on_wrench(m):
        f = m.wrench.force
        got["n"] += 1
        got["max"] = max(got["max"], math.sqrt(f.x * f.x + f.y * f.y + f.z * f.z))
        got["frames"].add(m.header.frame_id)
    node.create_subscription(WrenchStamped, "/LAB/body/servo_cf", on_wrench, 10)
    threading.Thread(target=rclpy.spin, args=(node,), daemon=True).start()
    mode = {"now": "still", "since": time.monotonic()}
    def commands():
        for line in sys.stdin:
            cmd = line.strip()
            if cmd == "report":
                print(json.dumps({"n": got["n"], "max": got["max"], "frames": sorted(got["frames"])}), flush=True)
            elif cmd:
                mode["now"], mode["since"] = cmd, time.monotonic()
        mode["now"] = "quit"
    threading.Thread(target=commands, daemon=True).start()
    msg = PoseStamped()
    msg.pose.orientation.w = 1.0
    depth = 0.0
    while mode["now"] != "quit":
        now = time.monotonic()
        if mode["now"] == "push":          # 12 cm down in 1 s (the robot: half), then stay
            depth = min(0.12, (now - mode["since"]) * 0.12)
        msg.header.frame_id = "world" if mode["now"] == "frame" else "lab_base"
        msg.header.stamp = node.get_clock().now().to_msg()
        msg.pose.position.z = math.nan if mode["now"] == "nan" else -depth
        if mode["now"] != "silent":
            pose_pub.publish(msg)
            pedal_pub.publish(Joy(buttons=[1]))   # the dead-man pedal, pressed
        time.sleep(0.002)
    node.destroy_node()
    rclpy.shutdown()
""")


@needs_opencl
def test_a_labs_rclpy_node_drives_a_live_run_and_reads_forces_and_faults_hold_the_arm(ros2_env, tmp_path):
    from pointfence.service.canned import canned_sources
    from pointfence.service.ros2.crtk_master import CrtkMasterHost
    from pointfence.service.runner import LiveRun

    cfg = balloon_config(tmp_path, arch="III", robot=POINT_MASS, extra="max_lateness_s = 1.0\n")
    lab = subprocess.Popen([sys.executable, "-c", LAB], env={**os.environ, **ros2_env}, stdin=subprocess.PIPE,
                           stdout=subprocess.PIPE, text=True, bufsize=1)
    host = CrtkMasterHost([CrtkDevice("LAB", frame_id="lab_base", clutch_topic="/lab/deadman", pedal="couples",
                                      timeout_ms=100)])
    m = host.masters[0]
    run = None

    def tell(cmd):
        lab.stdin.write(cmd + "\n")
        lab.stdin.flush()

    def report():
        tell("report")
        return json.loads(lab.stdout.readline())

    def holding():
        return "master input invalid" in run.service.status()["arms_holding"][0]

    try:
        assert polled(m, lambda m: m.ok and m.clutch, 20), host.status()
        run = LiveRun(cfg, host.masters, sources=canned_sources(cfg, 10))
        run.start()
        run.wait_ticks(200)
        # not holding: the lab's samples arrive (on a loaded machine a 100-ms gap in them holds the
        # arm for a while; it is released once they come again)
        assert wait_for(lambda: not holding(), 5), run.service.status()
        tell("push")
        assert wait_for(lambda: report()["max"] > 0.5, 15, 0.2), (report(), run.service.status())
        got = report()
        assert got["frames"] == ["lab_base"]                       # forces in the device's own frame
        for fault in ("nan", "frame", "silent"):                   # each holds the arm; a valid pose clears it
            tell(fault)
            assert wait_for(holding, 5), fault
            cmd = run.service.snapshot()["cmd"][0].copy()
            time.sleep(0.1)
            np.testing.assert_array_equal(run.service.snapshot()["cmd"][0], cmd)    # the arm stays put
            tell("push")
            assert wait_for(lambda: not holding(), 5), (fault, run.service.status())
        st = m.status()
        assert st["rejected"]["non_finite"] >= 1 and st["rejected"]["frame_id"] >= 1 and st["stale_ticks"] >= 1
    finally:
        if run is not None:
            run.stop()
        host.close()
        lab.stdin.close()
        try:
            lab.wait(timeout=5)
        except subprocess.TimeoutExpired:
            lab.kill()
            lab.wait()


# --- serve --ros2-masters ---------------------------------------------------------------------------------
def _serve_args(*argv):
    import argparse

    from pointfence.service import serve

    p = argparse.ArgumentParser()
    serve.add_arguments(p)
    return p.parse_args(list(argv))


@pytest.mark.parametrize("argv, fragment", [
    (["--ros2-masters", "MTMR,MTML", "--ros2-master-slots", "0"], "one distinct slot in 0..1 per namespace"),
    (["--ros2-masters", "MTMR", "--ros2-master-slots", "2"], "one distinct slot in 0..1"),
    (["--ros2-masters", "MTMR,MTML", "--ros2-master-slots", "1,1"], "one distinct slot"),
    (["--ros2-masters", "MTMR", "--ros2-master-slots", "x"], "one distinct slot"),
    (["--ros2-masters", "MTMR", "--itp", "127.0.0.1:0", "--itp-slots", "0"], "none of the ITP's [0]"),
    (["--ros2-masters", "MTMR", "--ros2-pedal", "couples", "--ros2-clutch-button", "99"], "clutch button = 99"),
])
def test_serve_refuses_ros2_master_slots_it_cannot_give(argv, fragment, tmp_path):
    from pointfence.service import serve

    key = tmp_path / "pf.key"
    serve.new_key(key)
    with pytest.raises(InputError, match=fragment.replace("[", r"\[").replace("]", r"\]").replace(".", r"\.")):
        serve.run(_serve_args("--key-file", str(key), "--port", "0", "--no-control", "--clients", "2", *argv))


@needs_opencl
def test_serve_with_a_ros2_master_renders_forces_back_to_the_sim_master(ros2_env, tmp_path):
    from pointfence.service import serve

    key = tmp_path / "pf.key"
    serve.new_key(key)
    balloon_config(tmp_path, arch="III", robot=POINT_MASS, extra="max_lateness_s = 1.0\n")   # writes scene.toml
    traj = tmp_path / "push.csv"                                 # 12 cm down in 1 s (the robot: 6 cm)
    traj.write_text("t,x,y,z\n0,0,0,0\n1,0,0,-0.12\n60,0,0,-0.12\n")
    env = {**os.environ, **ros2_env, "PYTHONUNBUFFERED": "1"}
    stats, forces = tmp_path / "stats.json", tmp_path / "forces.csv"
    sim = subprocess.Popen([sys.executable, "-m", "pointfence.cli", "ros2", "sim-master", "--namespace", "MTMR",
                            "--trajectory", str(traj), "--rate", "500", "--status-every", "0", "--start-on-force",
                            "--forces", str(forces)], env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    srv = subprocess.Popen([sys.executable, "-m", "pointfence.service.serve", "--key-file", str(key), "--port", "0",
                            "--no-control", "--config", str(tmp_path / "scene.toml"), "--clients", "1",
                            "--ros2-masters", "MTMR", "--timeout-ms", "200", "--status-every", "0", "--prerender", "5",
                            "--stats-file", str(stats)], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                           text=True)

    def pushed_back():                                           # a force of more than 0.5 N has arrived
        rows = forces.read_text().splitlines()[1:] if forces.exists() else []
        try:
            return any(sum(float(v) ** 2 for v in r.split(",")[2:]) > 0.25 for r in rows[:-1])   # (whole rows)
        except ValueError:
            return False

    try:
        assert wait_for(lambda: pushed_back() or srv.poll() is not None, 90, 0.2) and srv.poll() is None
    finally:
        srv.send_signal(signal.SIGTERM)
        _, err = srv.communicate(timeout=60)
        sim.send_signal(signal.SIGTERM)
        out, _ = sim.communicate(timeout=10)
    assert srv.returncode == 0 and "ROS 2 masters MTMR" in err, err[-2000:]
    summary = json.loads(out.strip().splitlines()[-1])
    dev = json.loads(stats.read_text())["ros2_masters"]["devices"][0]
    assert dev["poses"] > 100 and dev["frame_id"] == "MTMR_base" and dev["forces_published"] > 100, dev
    assert summary["force_frames"].keys() == {"MTMR_base"}
    assert summary["max_force_n"] > 0.5, summary                 # the fixture pushed back on the operator's hand


# --- the MTM's gripper and orientation -------------------------------------------------------------------
def test_gripper_settings_and_checks():
    from pointfence.service.ros2.crtk_device import GRASP_LIMIT_RAD
    from pointfence.service.ros2.master_block import REJECT_GRIPPER

    d = CrtkDevice("MTML")
    assert (d.gripper_topic, d.gripper) == ("/MTML/gripper/measured_js", "auto")   # the dVRK MTM's topic
    assert d.check_grip([0.4]) is None and d.check_grip([-0.2, 7.0]) is None           # (the first joint)
    assert d.check_grip([])[0] == REJECT_GRIPPER
    assert d.check_grip([math.nan])[0] == REJECT_NONFINITE and d.check_grip([math.inf])[0] == REJECT_NONFINITE
    assert d.check_grip([GRASP_LIMIT_RAD + 0.01])[0] == REJECT_GRIPPER
    with pytest.raises(InputError, match="gripper = 'always'"):
        CrtkDevice("M", gripper="always")


def _lab_publishers(lab, ns, pedal_topic):
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import JointState, Joy

    pose_pub = lab.node.create_publisher(PoseStamped, f"/{ns}/measured_cp", 10)
    grip_pub = lab.node.create_publisher(JointState, f"/{ns}/gripper/measured_js", 10)
    pedal_pub = lab.node.create_publisher(Joy, pedal_topic, 10)

    def send(q=(1.0, 0.0, 0.0, 0.0), grip=None, x=0.01):
        p = PoseStamped()
        p.header.frame_id = f"{ns}_base"
        p.pose.position.x = x
        o = p.pose.orientation
        o.w, o.x, o.y, o.z = q
        pose_pub.publish(p)
        if grip is not None:
            grip_pub.publish(JointState(name=["gripper"], position=list(grip)))
        pedal_pub.publish(Joy(buttons=[1]))
    return send


def test_the_mtm_gripper_is_the_masters_grasp_and_a_bad_or_silent_gripper_makes_it_invalid(ros2_env):
    from pointfence.service.ros2.crtk_master import CrtkMasterHost
    from pointfence.service.ros2.node import RosNode

    host = CrtkMasterHost([CrtkDevice("GRP", clutch_topic="/grp/pedal", pedal="couples", timeout_ms=100)])
    m = host.masters[0]
    lab = RosNode("pf_test_gripper").start()
    send = _lab_publishers(lab, "GRP", "/grp/pedal")
    # a turned handle: 40 degrees about (1, 2, -2)/3, w x y z as the tick reads it (ROS's x y z w in the message)
    a = math.radians(40.0)
    q = (math.cos(a / 2), *(math.sin(a / 2) * np.array([1.0, 2.0, -2.0]) / 3.0))

    def until(cond, **kw):
        return polled(m, lambda m: (send(**kw), cond(m))[1], 15)

    try:
        assert until(lambda m: m.ok and m.clutch, q=q)        # no gripper heard yet ("auto"): grasp 0, valid
        assert m.grasp == 0.0
        np.testing.assert_allclose(m.orientation, q, atol=1e-12)
        assert until(lambda m: m.grasp == 0.37, q=q, grip=(0.37,))
        assert m.ok and m.status()["grips"] >= 1 and m.status()["grasp"] == 0.37
        assert until(lambda m: not m.ok, q=q, grip=(math.nan,))                   # a NaN gripper: invalid
        assert m.grasp == 0.37 and m.status()["rejected"]["non_finite"] >= 1       # the NaN never reached it
        assert "gripper" in m.status()["last_rejection"]
        assert until(lambda m: m.ok and m.grasp == 0.5, q=q, grip=(0.5,))
        assert until(lambda m: not m.ok, q=q, grip=())                            # no angle in it
        assert m.status()["rejected"]["gripper"] >= 1
        assert until(lambda m: m.ok, q=q, grip=(0.5,))
        stale = m.stale_ticks
        assert until(lambda m: not m.ok, q=q)                 # poses on, the gripper silent: stale after 100 ms
        assert m.stale_ticks > stale
        assert until(lambda m: m.ok, q=q, grip=(0.1,))
    finally:
        lab.close()
        host.close()


def test_a_required_gripper_holds_until_heard_and_none_ignores_it(ros2_env):
    from pointfence.service.ros2.crtk_master import CrtkMasterHost
    from pointfence.service.ros2.node import RosNode

    host = CrtkMasterHost([CrtkDevice("REQ", clutch_topic="/req/pedal", pedal="couples", gripper="required"),
                           CrtkDevice("NOG", clutch_topic="/nog/pedal", pedal="couples", gripper="none")])
    req, nog = host.masters
    lab = RosNode("pf_test_gripper_modes").start()
    send_req, send_nog = _lab_publishers(lab, "REQ", "/req/pedal"), _lab_publishers(lab, "NOG", "/nog/pedal")
    try:
        assert polled(req, lambda m: (send_req(), m.status()["poses"] > 5)[1], 15)
        assert not req.ok                                     # poses, but no gripper yet: the arm holds
        assert polled(req, lambda m: (send_req(grip=(0.25,)), m.ok)[1], 15) and req.grasp == 0.25
        assert polled(nog, lambda m: (send_nog(grip=(0.9,)), m.ok and m.status()["poses"] > 5)[1], 15)
        time.sleep(0.1)
        nog.poll(time.monotonic())
        assert nog.grasp == 0.0 and nog.status()["grips"] == 0    # not subscribed
    finally:
        lab.close()
        host.close()


GRIP_LAB = textwrap.dedent("""
    # a scripted MTM: a turned handle, a dead-man pedal pressed, the gripper angle told on stdin
    import math, sys, threading, time
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import JointState, Joy

    rclpy.init()
    node = rclpy.create_node("lab_mtm")
    pose_pub = node.create_publisher(PoseStamped, "/GMTM/measured_cp", 10)
    grip_pub = node.create_publisher(JointState, "/GMTM/gripper/measured_js", 10)
    pedal_pub = node.create_publisher(Joy, "/gmtm/deadman", 10)
    state = {"grip": 0.0, "run": True}
    def commands():
        for line in sys.stdin:
            if line.strip():
                state["grip"] = float(line)
        state["run"] = False
    threading.Thread(target=commands, daemon=True).start()
    msg = PoseStamped()
    msg.header.frame_id = "GMTM_base"
    msg.pose.orientation.w = 1.0
    while state["run"]:
        msg.header.stamp = node.get_clock().now().to_msg()
        pose_pub.publish(msg)
        grip_pub.publish(JointState(name=["gripper"], position=[state["grip"]]))
        pedal_pub.publish(Joy(buttons=[1]))
        time.sleep(0.002)
    node.destroy_node()
    rclpy.shutdown()
""")


@needs_opencl
def test_the_jaw_follows_the_mtm_gripper_rate_limited_and_a_nan_gripper_holds_it(ros2_env, tmp_path):
    from pointfence.service.canned import canned_sources
    from pointfence.service.ros2.crtk_master import CrtkMasterHost
    from pointfence.service.runner import LiveRun

    cfg = balloon_config(tmp_path, arch="III", robot=POINT_MASS, extra="max_lateness_s = 1.0\n")
    lab = subprocess.Popen([sys.executable, "-c", GRIP_LAB], env={**os.environ, **ros2_env}, stdin=subprocess.PIPE,
                           text=True, bufsize=1)
    # (a master silent for 1 s reads stale: the lab's process shares 2 cores with the service here)
    host = CrtkMasterHost([CrtkDevice("GMTM", clutch_topic="/gmtm/deadman", pedal="couples", timeout_ms=1000)])
    m = host.masters[0]
    run = None

    def tell(grip):
        lab.stdin.write(f"{grip}\n")
        lab.stdin.flush()

    def jaw():
        s = run.service.snapshot()
        return s["tick"], float(s["jaw"][0])

    def holding():
        return "master input invalid" in run.service.status()["arms_holding"][0]

    try:
        tell(0.2)
        assert polled(m, lambda m: m.ok and m.clutch and m.grasp == 0.2, 20), host.status()
        run = LiveRun(cfg, host.masters, sources=canned_sources(cfg, 10))
        run.start()
        assert wait_for(lambda: run.service.out.coupled[0] and abs(jaw()[1] - 0.2) < 1e-12, 15), jaw()
        vmax, dt = run.service.cfg.teleop.max_jaw_speed, run.service.dt
        stuck = []
        for _ in range(3):
            tell(0.8)                                 # 0.6 rad at 3 rad/s: 0.2 s of ramp
            seen, end = [jaw()], time.monotonic() + 5.0
            while seen[-1][1] < 0.8 - 1e-12 and time.monotonic() < end:
                time.sleep(0.0002)       # (a busy poll would take the interpreter from the loop)
                s = jaw()
                if s[0] != seen[-1][0]:
                    seen.append(s)
            if abs(seen[-1][1] - 0.8) < 1e-12:
                break
            # A hold in the ramp (a stall of this loaded machine) re-anchored the arm: its jaw waits
            # for the grasp to come back to it, as the dVRK's does. Bring the grasp back and ramp again.
            stuck.append((seen[-1], run.service.status()["arms_holding"]))
            tell(0.2)
            assert wait_for(lambda: abs(jaw()[1] - 0.2) < 1e-12, 15), (jaw(), stuck)
        assert abs(seen[-1][1] - 0.8) < 1e-12, (seen[-5:], stuck)
        ramp = [j for _, j in seen if 0.2 + 1e-9 < j < 0.8 - 1e-9]
        assert len(ramp) >= 3, seen                  # it ramped (not a jump)
        for (k0, j0), (k1, j1) in zip(seen, seen[1:]):
            assert j1 - j0 <= vmax * dt * (k1 - k0) + 1e-12, (k0, j0, k1, j1)
        tell("nan")                                   # a NaN gripper: the master's sample is invalid, the arm holds
        assert wait_for(holding, 5), run.service.status()
        assert m.status()["rejected"]["non_finite"] >= 1
        held = jaw()[1]
        time.sleep(0.1)
        assert jaw()[1] == held == run.service.snapshot()["jaw"][0]
        tell(0.3)                                     # a valid one again: it recovers
        assert wait_for(lambda: not holding(), 5), run.service.status()
    finally:
        if run is not None:
            run.stop()
        host.close()
        lab.stdin.close()
        try:
            lab.wait(timeout=5)
        except subprocess.TimeoutExpired:
            lab.kill()
            lab.wait()
