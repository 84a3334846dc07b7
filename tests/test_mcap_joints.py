"""Robot joints in an MCAP recording (service/mcap_record.py ``record_joints``, mcap_topics.py
``JointTopics``): a Raven II arm's measured joints are recorded as ``sensor_msgs/JointState`` on
``/<arm>/measured_js`` (CRTK) at the configured rate, and decode with mcap-ros2-support into its
joint names and the exact positions each recorded tick read (their forward kinematics is the tick's
measured_cp); arms without a joint model (a
point mass, an ideal robot) get no topic; a message sent before a tick reaches the file before it
(the writer catches up on control messages before it writes ticks)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service.mcap_record import McapRecorder
from pointfence.service.robot import JOINT_HOME, JOINT_NAMES, make_robot
from pointfence.service.tick_io import TickInput, TickOutput
from test_mcap_record import ros2_messages


def _record(path, robots, ticks: int, joint_hz=None, move=None):
    """``ticks`` ticks of ``len(robots)`` arms; ``move(k, robots)`` before each tick."""
    n = len(robots)
    rec = McapRecorder(path, n, joint_hz=joint_hz)
    rec.record_joints(robots)
    inp, out = TickInput.zeros(n), TickOutput.zeros(n)
    for k in range(ticks):
        if move is not None:
            move(k, robots)
        inp.k = out.k = k
        inp.t = inp.now = out.t = k * 1e-3
        rec.write(inp, out)
    rec.close()
    assert rec.write_error is None, rec.write_error
    return rec


def _q(k: int) -> np.ndarray:
    """A joint configuration of the Raven II near its home, different at every tick."""
    return np.array(JOINT_HOME, float) + np.array([1e-3, -2e-3, 1e-3, 0.01, -0.01, 0.02]) * (k % 37) / 37


def test_raven_joints_decode_into_joint_state_with_names_and_positions(tmp_path):
    raven = make_robot("raven2")
    robots = [raven, make_robot("point-mass"), None]
    path = tmp_path / "joints.mcap"
    rec = _record(path, robots, 300, move=lambda k, r: r[0].reset(_q(k)))
    msgs = list(ros2_messages(path))
    topics = {m.channel.topic for m in msgs}
    assert "/PSM1/measured_js" in topics
    assert "/PSM2/measured_js" not in topics and "/PSM3/measured_js" not in topics   # point mass, ideal: none
    js = [m for m in msgs if m.channel.topic == "/PSM1/measured_js"]
    assert len(js) == 29                # 100 Hz (the pose rate) of 300 ticks at 1 kHz; tick 0 had no tick before it
    for i, m in enumerate(js):
        q = m.ros_msg
        k = 10 * (i + 1)
        assert m.schema.name == "sensor_msgs/JointState"
        assert list(q.name) == list(JOINT_NAMES) == list(raven.joint_names)
        assert list(q.position) == _q(k - 1).tolist()       # what tick k read: the state at tick k-1's end; exact
        assert len(q.velocity) == 0 and len(q.effort) == 0
        ns = rec.epoch_ns + round(k * 1e-3 * 1e9)
        assert (q.header.stamp.sec, q.header.stamp.nanosec) == (ns // 10**9, ns % 10**9) and m.message.log_time == ns


def test_joint_rate_is_configurable_and_zero_turns_it_off(tmp_path):
    raven = make_robot("raven2")
    every = _record(tmp_path / "all.mcap", [raven], 50, joint_hz=1000.0, move=lambda k, r: r[0].reset(_q(k)))
    got = [m.ros_msg for m in ros2_messages(tmp_path / "all.mcap", topics=["/PSM1/measured_js"])]
    assert every.joint_hz == 1000.0 and len(got) == 49
    assert [list(q.position) for q in got] == [_q(k - 1).tolist() for k in range(1, 50)]
    _record(tmp_path / "off.mcap", [raven], 50, joint_hz=0.0)
    assert not list(ros2_messages(tmp_path / "off.mcap", topics=["/PSM1/measured_js"]))
    for bad in (-1.0, math.nan, math.inf):
        with pytest.raises(InputError, match="joint_hz"):
            McapRecorder(tmp_path / "bad.mcap", 1, joint_hz=bad)


def test_the_writer_carries_out_every_message_sent_before_the_ticks_it_writes(tmp_path):
    """The joint block is announced before the first tick, but the pipe may deliver that message
    after the writer could write the tick (a busy machine): a flush first carries out every
    message counted in ``SENT`` (read after ``WRITTEN``), so no tick is written without its
    joints. Here the message reaches the writer's inbox 0.3 s after the flush starts."""
    import queue
    import threading

    from pointfence.service import mcap_shm
    from pointfence.service.mcap_writer import Writer
    from pointfence.service.tick_cdr import TickLayout, TickRows

    lay, cap = TickLayout(1), 64
    tick_path, buf = mcap_shm.create(mcap_shm.TickBlock.nbytes(cap, lay.width), "pointfence-test-ticks-")
    ticks = mcap_shm.TickBlock(buf, cap, lay.width)
    joint_path, jbuf = mcap_shm.create(mcap_shm.JointBlock.nbytes(cap, 1, 6), "pointfence-test-joints-")
    joints = mcap_shm.JointBlock(jbuf, cap, 1, 6)
    fill, inp, out = TickRows(lay, ticks.rows), TickInput.zeros(1), TickOutput.zeros(1)
    for k in range(20):                                   # the service's side: 20 ticks, every one with joints
        inp.k = out.k = k
        inp.now = k * 1e-3
        fill.fill(inp, out, k)
        joints.rows[k, 0] = _q(k)
    ticks.header[mcap_shm.SENT] = 2                       # init, then the joint block, before the ticks
    ticks.header[mcap_shm.WRITTEN] = 20
    inbox: queue.Queue = queue.Queue()
    path = tmp_path / "catch_up.mcap"
    with open(path, "wb") as fh:
        w = Writer({"tick_path": tick_path, "n": 1, "capacity": cap, "flush_s": 0.25, "rate_hz": 1000.0,
                    "pose_hz": 100.0, "cloud_hz": 0.0, "epoch_ns": 0}, fh, inbox)
        late = threading.Timer(0.3, inbox.put, [("joints", joint_path, 6, {"0": list(JOINT_NAMES)}, 1)])
        late.start()
        w.flush(final=True)
        late.join()
        w.finish(service_died=False)
    got = [m.ros_msg for m in ros2_messages(path, topics=["/PSM1/measured_js"])]
    assert len(got) == 20 and [list(q.position) for q in got] == [_q(k).tolist() for k in range(20)]


def test_a_writer_behind_its_frames_flushes_again_without_waiting(tmp_path):
    """A writer whose last flush's time box ended before the frame ring did encodes on at once;
    one with nothing waiting waits ``flush_s`` for the next (the wait doubled its encoding time
    before, and the ring dropped snapshots on a loaded machine)."""
    import queue

    from pointfence.kernels.camera import Camera
    from pointfence.service import mcap_shm
    from pointfence.service.mcap_writer import Writer
    from pointfence.service.tick_cdr import TickLayout

    lay, cap, shapes, slots = TickLayout(1), 64, [(4, 6)], 8
    tick_path, buf = mcap_shm.create(mcap_shm.TickBlock.nbytes(cap, lay.width), "pointfence-test-ticks-")
    frame_path, fbuf = mcap_shm.create(mcap_shm.FrameBlock.nbytes(shapes, slots), "pointfence-test-frames-")
    ticks, fb = mcap_shm.TickBlock(buf, cap, lay.width), mcap_shm.FrameBlock(fbuf, shapes, slots)
    cam = Camera("cam0", 6, 4, 5.0, 5.0, 2.5, 1.5)
    with open(tmp_path / "behind.mcap", "wb") as fh:
        w = Writer({"tick_path": tick_path, "n": 1, "capacity": cap, "flush_s": 0.5, "rate_hz": 1000.0,
                    "pose_hz": 100.0, "cloud_hz": 0.0, "epoch_ns": 0}, fh, queue.Queue())
        w.control(("frames", frame_path, shapes, slots, [cam], None))
        assert not w.behind and w.wait_s(0.5) == 0.5
        for j in range(3):                     # three snapshots handed over, none encoded yet
            fb.meta[j, 0] = j + 1
            e = fb.cam_meta(j, 0)
            e[mcap_shm.NEW] = j == 0
            e[mcap_shm.FSEQ], e[mcap_shm.INDEX], e[mcap_shm.STAMP] = j, 0, 0.01 * j
            e[mcap_shm.POSE:] = math.nan
            fb.depth[j][0][...] = 500 + j
        ticks.header[mcap_shm.SNAPS_WRITTEN] = 3
        assert w.behind and w.wait_s(0.5) == 0.0
        w.write_frames(None)
        assert not w.behind and w.wait_s(0.5) == 0.5 and int(ticks.header[mcap_shm.SNAPS_CONSUMED]) == 3
        w.finish(service_died=False)


def test_a_writer_whose_frame_ring_is_more_than_half_full_encodes_the_frames_first(tmp_path):
    """The frame ring holds two seconds of snapshots, the tick ring sixteen of ticks: a starved
    writer with more than half its frame ring waiting encodes the frames before the ticks, so it
    drops fewer snapshots; otherwise the ticks go first (they carry every tick's state)."""
    import queue

    from pointfence.kernels.camera import Camera
    from pointfence.service import mcap_shm
    from pointfence.service.mcap_writer import Writer
    from pointfence.service.tick_cdr import TickLayout, TickRows

    lay, cap, shapes, slots = TickLayout(1), 64, [(4, 6)], 8
    tick_path, buf = mcap_shm.create(mcap_shm.TickBlock.nbytes(cap, lay.width), "pointfence-test-ticks-")
    frame_path, fbuf = mcap_shm.create(mcap_shm.FrameBlock.nbytes(shapes, slots), "pointfence-test-frames-")
    ticks, fb = mcap_shm.TickBlock(buf, cap, lay.width), mcap_shm.FrameBlock(fbuf, shapes, slots)
    fill, inp, out = TickRows(lay, ticks.rows), TickInput.zeros(1), TickOutput.zeros(1)
    cam = Camera("cam0", 6, 4, 5.0, 5.0, 2.5, 1.5)
    order: list = []
    with open(tmp_path / "pressed.mcap", "wb") as fh:
        w = Writer({"tick_path": tick_path, "n": 1, "capacity": cap, "flush_s": 0.5, "rate_hz": 1000.0,
                    "pose_hz": 100.0, "cloud_hz": 0.0, "epoch_ns": 0}, fh, queue.Queue())
        w.control(("frames", frame_path, shapes, slots, [cam], None))
        for name in ("write_ticks", "write_frames"):
            f = getattr(w, name)
            setattr(w, name, lambda *a, _f=f, _n=name: (order.append(_n), _f(*a))[1])
        k = 0
        for pending in (4, 5):                 # half the ring waiting, then more than half
            for j in range(pending):
                s = (w.consumed + j) % slots
                fb.meta[s, 0] = w.consumed + j + 1
                e = fb.cam_meta(s, 0)
                e[mcap_shm.NEW] = True
                e[mcap_shm.FSEQ], e[mcap_shm.INDEX], e[mcap_shm.STAMP] = j, j, 0.01 * j
                e[mcap_shm.POSE:] = math.nan
            ticks.header[mcap_shm.SNAPS_WRITTEN] = w.consumed + pending
            for _ in range(10):
                inp.k = out.k = k
                inp.now = k * 1e-3
                fill.fill(inp, out, k % cap)
                k += 1
            ticks.header[mcap_shm.WRITTEN] = k
            assert w.pressed == (pending > slots // 2)
            order.clear()
            w.flush(final=False)
            assert order == (["write_frames", "write_ticks"] if pending > slots // 2 else ["write_ticks", "write_frames"])
            assert not w.behind and int(ticks.header[mcap_shm.SNAPS_CONSUMED]) == w.consumed
        w.finish(service_died=False)
