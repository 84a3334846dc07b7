"""ROS 2 telemetry (service/ros2/telemetry.py, telemetry_node.py): a live run publishes, from a
child process, what a plain rclpy subscriber written here with the standard message types reads:
poses and forces equal to the service's own ticks (read back from the run's MCAP recording, the
same stamps), a fixture cloud on the snapshot's protected points, markers and status; a killed
publisher never stops the loop and the status says telemetry is lost. DDS stays on this machine
(the ``ros2_env`` fixture)."""
from __future__ import annotations

import collections
import json
import os
import signal
import time
import tomllib

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service import config as config_mod

RATE_HZ = 100.0          # the recording's pose_hz: telemetry samples the same ticks (k % 10 == 0)
CLOUD_MAX = 300          # below the balloon's ~800 protected points at stride 4: the cloud is thinned
ARMS = 2


def _config(ros2: dict):
    doc = tomllib.loads(config_mod.embedded_defaults())
    doc["ros2"] = ros2
    return config_mod.parse(doc, "test")


POSES = ("xm", "hip", "proxy", "measured_cp", "servo_cp", "master/measured_cp")
JOINTS = ("jaw/servo_jp", "jaw/measured_js", "master/gripper/measured_js")


def turning(m, i: int):
    """Master ``m`` (a scripted circle) with its handle turning at 0.4 rad/s about an axis of its
    own and its gripper opening and closing between 0.1 and 0.5 rad: the tool turns and its jaw
    moves in the ticks telemetry samples."""
    from pointfence.service.masters import ScriptedMaster

    t = m.times
    axis = np.array([[0.3, -0.2, 1.0], [1.0, 0.5, 0.2]][i % 2])
    axis /= np.linalg.norm(axis)
    a = 0.4 * t
    q = np.concatenate([np.cos(a / 2)[:, None], np.sin(a / 2)[:, None] * axis], 1)
    g = 0.3 + 0.2 * np.sin(2.0 * t + i)
    return ScriptedMaster(t, m.positions, m.clutches, orientations=q, grasps=g, name=m.name)


@pytest.fixture(scope="module")
def live(ros2_env, tmp_path_factory):
    """One live run with 2 arms circling into the balloon's fixture, recorded to MCAP, with
    telemetry on; a subscriber in this process takes every topic; once it has enough of each
    (2.5 s at least) the publisher process is killed and the run goes on for 2.5 s."""
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState, PointCloud2
    from std_msgs.msg import String
    from visualization_msgs.msg import MarkerArray

    from pointfence.bench.loop import circling_master
    from pointfence.service.canned import canned_sources
    from pointfence.service.mcap_read import open_recording
    from pointfence.service.ros2.node import RosNode
    from pointfence.service.runner import LiveRun

    cfg = _config({"telemetry": True, "telemetry_rate_hz": RATE_HZ, "cloud_rate_hz": 10.0,
                   "cloud_max_points": CLOUD_MAX})
    got = collections.defaultdict(list)
    sub = RosNode("pf_telemetry_test")
    topics = {"/pointfence/markers": MarkerArray, "/pointfence/fixtures": PointCloud2}
    for b in range(ARMS):
        topics.update({f"/pointfence/arm{b}/{x}": PoseStamped for x in POSES})
        topics.update({f"/pointfence/arm{b}/{x}": JointState for x in JOINTS})
        topics[f"/pointfence/arm{b}/force"] = WrenchStamped
    for topic, kind in topics.items():
        sub.node.create_subscription(kind, topic, lambda m, t=topic: got[t].append(m), 100)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    sub.node.create_subscription(String, "/pointfence/status", lambda m: got["/pointfence/status"].append(m), latched)
    sub.start()
    path = tmp_path_factory.mktemp("telemetry") / "run.mcap"
    masters = [turning(circling_master(i, ARMS, 20.0), i) for i in range(ARMS)]
    run = LiveRun(cfg, masters, sources=canned_sources(cfg, 5, {}), record_path=path)
    res = {"cfg": cfg}
    stopped = False
    try:
        assert run.telemetry.wait_ready(30.0), run.telemetry.error
        run.start()
        # (at least 2.5 s, and until every kind of message came: a loaded machine publishes late)
        end = time.monotonic() + 30.0
        run.wait(2.5)
        while time.monotonic() < end and not (
                len(got["/pointfence/fixtures"]) >= 5 and len(got["/pointfence/markers"]) >= 10
                and all(len(got[f"/pointfence/arm{b}/{x}"]) >= 30 for b in range(ARMS)
                        for x in (*POSES, *JOINTS, "force"))):
            run.wait(0.1)
        tel = run.telemetry
        res["status_before"] = run.service.status()["telemetry"]
        os.kill(tel.pid, signal.SIGKILL)
        ticks_at_kill, lost_at_kill = run.loop.ticks, tel.rows_lost
        # more ticks than the ring holds (its 2 s of sampled ticks: a loaded machine's loop may take longer)
        end = time.monotonic() + 20.0
        run.wait(2.5)
        while run.loop.ticks < ticks_at_kill + tel.capacity * tel.every + 300 and time.monotonic() < end:
            run.wait(0.1)
        res.update(ticks_at_kill=ticks_at_kill, ticks_after=run.loop.ticks, lost_at_kill=lost_at_kill,
                   status_after=run.service.status()["telemetry"], loop_running=run.loop.running,
                   loop_error=run.loop.error, epoch_ns=tel.epoch_ns, every=tel.every)
        run.stop()
        stopped = True
        pts = [np.frombuffer(bytes(c.data), np.float32).reshape(-1, 3) for c in got["/pointfence/fixtures"]]
        res["cloud_near"] = [run.service.pipeline.neighbors(p, radius=0.003, protected_only=True).count for p in pts
                             if len(p)]
    finally:
        if not stopped:
            run.stop()
        sub.close()
    res["got"] = got
    rec = open_recording(path)
    res["rec"], res["rec_epoch"] = rec, int(rec.meta["epoch_ns"])
    return res


def _rows_by_stamp(live):
    """The recording's tick rows (every tick's TickInput and TickOutput) by stamp (ns)."""
    from pointfence.service.tick_cdr import TickLayout

    rec = live["rec"]
    lay = TickLayout(ARMS)
    c_now = lay.cols[("in", "now")][0]
    ns = live["rec_epoch"] + np.round(rec.rows[:, c_now] * 1e9).astype(np.int64)
    return dict(zip(ns.tolist(), range(len(ns)))), lay


def _col(lay, rows, part, name, i, b, width=3):
    c, _ = lay.cols[(part, name)]
    return rows[i, c + width * b: c + width * b + width]


def _ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def test_poses_and_forces_are_the_service_ticks_in_metres_and_newtons(live):
    assert live["epoch_ns"] == live["rec_epoch"]      # a live run and its recording share their stamps
    index, lay = _rows_by_stamp(live)
    rows, got = live["rec"].rows, live["got"]
    c_k = lay.cols[("in", "k")][0]
    xm, turned = [], collections.defaultdict(list)
    for b in range(ARMS):
        for topic, part, name, qname in (("xm", "out", "xm", None), ("hip", "out", "hip", None),
                                         ("proxy", "out", "proxy", None),
                                         ("measured_cp", "in", "robot_pos", "robot_orientation"),
                                         ("servo_cp", "out", "command", "orientation"),
                                         ("master/measured_cp", "in", "master_pos", "master_orientation"),
                                         ("force", "out", "force", None)):
            msgs = got[f"/pointfence/arm{b}/{topic}"]
            assert len(msgs) >= 30, (topic, len(msgs))
            for m in msgs:
                assert m.header.frame_id == (("MTMR_base", "MTML_base")[b] if topic.startswith("master") else "world")
                i = index[_ns(m.header)]               # the message's stamp is a recorded tick's
                assert int(rows[i, c_k]) % live["every"] == 0
                want = _col(lay, rows, part, name, i, b)
                if topic == "force":
                    v = m.wrench.force
                    assert (m.wrench.torque.x, m.wrench.torque.y, m.wrench.torque.z) == (0.0, 0.0, 0.0)
                else:
                    v = m.pose.position
                    xm += [want] if topic == "xm" else []
                    q = m.pose.orientation
                    if qname is None:                  # points: identity
                        assert (q.x, q.y, q.z, q.w) == (0.0, 0.0, 0.0, 1.0)
                    else:                              # the tick's (w, x, y, z) as ROS's (x, y, z, w)
                        w = _col(lay, rows, part if qname != "orientation" else "out", qname, i, b, 4)
                        assert (q.w, q.x, q.y, q.z) == tuple(w), (topic, i)
                        turned[topic].append(abs(w[0]))
                np.testing.assert_allclose([v.x, v.y, v.z], want, rtol=0, atol=1e-12)
    # real positions, not zeros (the arms start at the tool tip, 17 cm above the table; a loaded machine may
    # hold them all along, so no motion is required)
    assert np.abs(np.array(xm)).max() > 0.1
    # the masters turn (0.4 rad/s): the orientations published are not all identity (the tool's turn only
    # while its arm is coupled: see test_orientations_jaw_and_grasp_reach_their_topics for a fixed case)
    assert min(turned["master/measured_cp"]) < np.cos(0.1)


def test_the_jaw_its_measure_and_the_masters_grasp_are_joint_states_of_the_ticks(live):
    index, lay = _rows_by_stamp(live)
    rows, got = live["rec"].rows, live["got"]
    for b in range(ARMS):
        for topic, part, name, joint in (("jaw/servo_jp", "out", "jaw", "jaw"),
                                         ("jaw/measured_js", "in", "robot_jaw", "jaw"),
                                         ("master/gripper/measured_js", "in", "grasp", "gripper")):
            msgs = got[f"/pointfence/arm{b}/{topic}"]
            assert len(msgs) >= 30, (topic, len(msgs))
            c, _ = lay.cols[(part, name)]
            values = []
            for m in msgs:
                assert list(m.name) == [joint] and len(m.velocity) == len(m.effort) == 0
                i = index[_ns(m.header)]
                assert list(m.position) == [rows[i, c + b]], (topic, i)
                values.append(m.position[0])
            if topic.startswith("master"):
                # the gripper moves (the jaw follows only while the arm is coupled: a loaded machine may
                # hold it). The grasp is 0.3 + 0.2 sin(2 t + i): any 0.29 s (30 samples at 100 Hz) spans
                # >= 0.2 (1 - cos 0.29) = 0.008 of it (a loaded CI machine delivered 0.045 in all)
                span = max(_ns(m.header) for m in msgs) - min(_ns(m.header) for m in msgs)
                assert span >= 0.29e9 and max(values) - min(values) > 0.005, (span, values[:5])


def test_the_fixture_cloud_is_a_consistent_pointcloud2_on_the_protected_points(live):
    clouds = live["got"]["/pointfence/fixtures"]
    assert len(clouds) >= 5
    for c in clouds:
        assert c.header.frame_id == "world" and c.height == 1 and not c.is_bigendian
        assert [(f.name, f.offset, f.datatype, f.count) for f in c.fields] == [("x", 0, 7, 1), ("y", 4, 7, 1),
                                                                               ("z", 8, 7, 1)]
        assert c.point_step == 12 and c.row_step == 12 * c.width and len(c.data) == c.row_step * c.height
        assert 0 < c.width <= CLOUD_MAX
    # thinned from the balloon's protected points (more than CLOUD_MAX of them at stride 4)
    assert max(c.width for c in clouds) > CLOUD_MAX // 2
    ws = live["cfg"].pipeline.workspace
    for c in clouds:
        p = np.frombuffer(bytes(c.data), np.float32).reshape(-1, 3)
        assert np.all((p >= np.asarray(ws.min) - 1e-6) & (p <= np.asarray(ws.max) + 1e-6))
    # every point lies on the fixture: a protected point of the last snapshot within 3 mm
    near = live["cloud_near"]
    assert near and all((n > 0).mean() > 0.95 for n in near)


def test_markers_show_proxies_at_the_fixture_radius_forces_and_the_workspace(live):
    from visualization_msgs.msg import Marker

    arrays = live["got"]["/pointfence/markers"]
    assert len(arrays) >= 10
    radius = live["cfg"].pipeline.radius.r_base
    index, lay = _rows_by_stamp(live)
    rows = live["rec"].rows
    for ma in arrays[-20:]:
        by = {(m.ns, m.id): m for m in ma.markers}
        assert set(by) == {("proxy", 0), ("proxy", 1), ("hip", 0), ("hip", 1), ("force", 0), ("force", 1),
                           ("workspace", 0)}
        assert all(m.header.frame_id == "world" and m.action == Marker.ADD for m in ma.markers)
        i = index[_ns(ma.markers[0].header)]
        for b in range(ARMS):
            p = by[("proxy", b)]
            assert p.type == Marker.SPHERE and p.scale.x == pytest.approx(2 * radius)
            pos = p.pose.position
            np.testing.assert_allclose([pos.x, pos.y, pos.z], _col(lay, rows, "out", "proxy", i, b), atol=1e-12)
            a = by[("force", b)]
            assert a.type == Marker.ARROW
            d = np.array([a.points[1].x - a.points[0].x, a.points[1].y - a.points[0].y, a.points[1].z - a.points[0].z])
            np.testing.assert_allclose(d, 0.01 * _col(lay, rows, "out", "force", i, b), atol=1e-9)
        box = by[("workspace", 0)]
        assert box.type == Marker.LINE_LIST and len(box.points) == 24
        ws = live["cfg"].pipeline.workspace
        corners = {(q.x, q.y, q.z) for q in box.points}
        assert corners == {(x, y, z) for x in (ws.min[0], ws.max[0]) for y in (ws.min[1], ws.max[1])
                           for z in (ws.min[2], ws.max[2])}


def test_status_names_architecture_haptics_and_each_arm(live):
    msgs = live["got"]["/pointfence/status"]
    assert msgs
    st = json.loads(msgs[-1].data)
    assert st["schema"] == "pointfence/status/1"
    assert st["architecture"] == "III" and st["haptics"] is True and st["teleop"] is True
    assert [a["arm"] for a in st["arms"]] == [0, 1]
    assert all(set(a) >= {"hold", "invariants", "coupled", "in_contact", "robot_fault"} for a in st["arms"])
    assert st["holding"] == bool(st["hold"] or any(a["hold"] for a in st["arms"]))


def test_a_killed_publisher_never_stops_the_loop_and_status_says_telemetry_is_lost(live):
    before, after = live["status_before"], live["status_after"]
    assert before["lost"] is False and before["publisher_alive"] and before["messages_published"] > 0
    assert before["rows_lost"] == 0
    assert after["lost"] is True and not after["publisher_alive"]
    assert "signal 9" in after["error"] and "runs on" in after["error"]
    # the loop went on, and the tick kept sampling into the full ring without waiting: rows lost
    assert live["loop_running"] and live["loop_error"] is None
    assert live["ticks_after"] > live["ticks_at_kill"] + 100
    assert after["rows_lost"] > live["lost_at_kill"]
    assert after["clouds_dropped"] > before["clouds_dropped"]     # the ingest side did not wait either


def test_ros2_settings_are_checked():
    cfg = _config({})
    assert cfg.ros2.telemetry is False and cfg.ros2.frame_id == "world" and cfg.ros2.namespace == ""
    for bad, match in (({"namespace": "rig2"}, "namespace"), ({"namespace": "/2rig"}, "namespace"),
                       ({"frame_id": "my frame"}, "frame_id"), ({"telemetry_rate_hz": 0}, "telemetry_rate_hz"),
                       ({"cloud_max_points": 0}, "cloud_max_points"), ({"telemetry_rate_hz": 5000.0}, "telemetry_rate_hz"),
                       ({"telemetri": True}, "telemetry")):
        with pytest.raises(InputError, match=match):
            _config(bad)
    assert _config({"namespace": "/rig_2/left"}).ros2.namespace == "/rig_2/left"


def test_telemetry_faster_than_the_loop_is_refused():
    from pointfence.service.ros2.telemetry import Telemetry
    from pointfence.service.settings import Ros2Table

    with pytest.raises(InputError, match="telemetry_rate_hz = 600"):
        Telemetry(Ros2Table(telemetry=True, telemetry_rate_hz=600.0), 1, 500.0, 0.02, None)



def test_namespace_frame_id_and_the_sampled_ticks(ros2_env):
    """Without a live run: ticks written straight into a Telemetry reach a subscriber under
    ``namespace``, with ``frame_id``, and only every ``every``-th tick (k % every == 0)."""
    from geometry_msgs.msg import WrenchStamped

    from pointfence.kernels.params import Workspace
    from pointfence.service.ros2.node import RosNode
    from pointfence.service.ros2.telemetry import Telemetry
    from pointfence.service.settings import Ros2Table
    from pointfence.service.tick_io import TickInput, TickOutput

    got = []
    sub = RosNode("pf_telemetry_ns_test")
    sub.node.create_subscription(WrenchStamped, "/rig2/pointfence/arm0/force", got.append, 100)
    sub.start()
    tel = Telemetry(Ros2Table(telemetry=True, telemetry_rate_hz=100.0, frame_id="base", namespace="/rig2"), 1,
                    1000.0, 0.02, Workspace((-0.1, -0.1, 0.0), (0.1, 0.1, 0.2)))
    try:
        assert tel.wait_ready(30.0), tel.error
        tel.attach(_Feeder(), _config({}), epoch_ns=10**18)
        inp, out = TickInput.zeros(1), TickOutput.zeros(1)
        deadline = time.monotonic() + 20.0
        k = 0
        while len(got) < 20 and time.monotonic() < deadline:
            inp.k, inp.now = k, k * 1e-3
            out.force[0] = (k * 1e-3, -2.0, 0.5)
            tel.write(inp, out)
            k += 1
            time.sleep(0.001)
        assert tel.every == 10 and tel.rows_sent == (k + 9) // 10 and tel.rows_lost == 0
    finally:
        tel.close()
        sub.close()
    assert len(got) >= 20
    for m in got:
        assert m.header.frame_id == "base"
        ns = _ns(m.header) - 10**18
        assert ns % 10_000_000 == 0                     # a sampled tick: k = 10 j at 1 ms a tick
        assert (m.wrench.force.x, m.wrench.force.y, m.wrench.force.z) == (ns // 1_000_000 * 1e-3, -2.0, 0.5)
    assert tel.status()["lost"] is False          # closed on purpose: not lost


class _Feeder:
    on_snapshot = None


def test_orientations_jaw_and_grasp_reach_their_topics(ros2_env):
    """Without a live run: ticks with known orientations and angles written straight into a
    Telemetry reach the pose and joint topics (w, x, y, z as ROS's x, y, z, w); a master that gave
    no sample (NaN) and an unknown jaw (NaN) publish nothing on their topics."""
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import JointState

    from pointfence.kernels.params import Workspace
    from pointfence.service.ros2.node import RosNode
    from pointfence.service.ros2.telemetry import Telemetry
    from pointfence.service.settings import Ros2Table
    from pointfence.service.tick_io import TickInput, TickOutput

    got = collections.defaultdict(list)
    sub = RosNode("pf_telemetry_orientation_test")
    for name, kind in (*((x, PoseStamped) for x in POSES), *((x, JointState) for x in JOINTS)):
        sub.node.create_subscription(kind, f"/pointfence/arm1/{name}", lambda m, t=name: got[t].append(m), 100)
    sub.start()
    tel = Telemetry(Ros2Table(telemetry=True, telemetry_rate_hz=1000.0), 2, 1000.0, 0.02,
                    Workspace((-0.1, -0.1, 0.0), (0.1, 0.1, 0.2)))
    inp, out = TickInput.zeros(2), TickOutput.zeros(2)
    q_robot, q_cmd, q_master = ((0.6, 0.0, 0.8, 0.0), (0.0, 1.0, 0.0, 0.0), (0.5, 0.5, -0.5, 0.5))
    inp.robot_orientation[1], out.orientation[1], inp.master_orientation[1] = q_robot, q_cmd, q_master
    inp.robot_pos[1], out.command[1], inp.master_pos[1] = (0.01, 0.02, 0.03), (0.04, 0.05, 0.06), (0.07, 0.08, 0.09)
    try:
        assert tel.wait_ready(30.0), tel.error
        k, deadline = 0, time.monotonic() + 20.0
        while min(len(got[x]) for x in (*POSES, *JOINTS)) < 20 and time.monotonic() < deadline:
            inp.k, inp.now = k, k * 1e-3
            out.jaw[1], inp.robot_jaw[1], inp.grasp[1] = 0.1 + 1e-4 * k, 0.2 + 1e-4 * k, 0.3 + 1e-4 * k
            tel.write(inp, out)
            k += 1
            time.sleep(0.001)
        inp.master_pos[1, 0] = np.nan          # then: no master sample, the jaw's angle unknown
        out.jaw[1] = inp.robot_jaw[1] = np.nan
        for j in range(k, k + 200):
            inp.k, inp.now = j, j * 1e-3
            tel.write(inp, out)
            time.sleep(0.001)
        time.sleep(0.5)
        ticks = k
    finally:
        tel.close()
        sub.close()
    for name, q in (("measured_cp", q_robot), ("servo_cp", q_cmd), ("master/measured_cp", q_master),
                    ("xm", (1.0, 0.0, 0.0, 0.0))):
        assert got[name], name
        for m in got[name]:
            o = m.pose.orientation
            assert (o.w, o.x, o.y, o.z) == q, name
    assert {m.header.frame_id for m in got["master/measured_cp"]} == {"MTML_base"}     # arm 1's master's frame
    p = got["servo_cp"][0].pose.position
    assert (p.x, p.y, p.z) == (0.04, 0.05, 0.06)
    for name, base in (("jaw/servo_jp", 0.1), ("jaw/measured_js", 0.2), ("master/gripper/measured_js", 0.3)):
        for m in got[name]:
            k = round((_ns(m.header) - tel.epoch_ns) / 1e6)       # (the tick's number: 1 ms a tick)
            assert list(m.position) == [base + 1e-4 * min(k, ticks - 1)], name
    # NaN: nothing more on the master's pose and the jaw's topics, while the grasp and tool poses go on
    def tick_numbers(name):
        return [round((_ns(m.header) - tel.epoch_ns) / 1e6) for m in got[name]]
    for name in ("master/measured_cp", "jaw/servo_jp", "jaw/measured_js"):
        assert max(tick_numbers(name)) < ticks, name
    for name in ("master/gripper/measured_js", "servo_cp", "measured_cp"):
        assert max(tick_numbers(name)) >= ticks + 100, name
