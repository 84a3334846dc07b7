"""The CDR codecs of the 1 kHz messages (service/ros2/cdr.py) against rclpy's own serializer: bytes
rclpy reads as the same message (byte for byte they may differ: rclpy leaves padding unset and its
buffer may run past the message), rclpy's bytes read as the same values, for frame ids and joint lists of every
alignment; big-endian input; and damaged bytes refused with CdrError, never another exception."""
from __future__ import annotations

import struct

import numpy as np
import pytest

from pointfence.service.ros2 import cdr


@pytest.fixture(scope="module")
def ros(ros2_env):
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import JointState

    return {"Pose": PoseStamped, "Wrench": WrenchStamped, "Joints": JointState,
            "ser": serialize_message, "de": deserialize_message}


FRAMES = ["", "a", "ab", "abc", "base", "world_0", "PSM1_base_link", "ünïcode"]


def _pose_msg(ros, stamp, frame, v):
    m = ros["Pose"]()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
    m.header.frame_id = frame
    p, o = m.pose.position, m.pose.orientation
    p.x, p.y, p.z, o.x, o.y, o.z, o.w = v
    return m


@pytest.mark.parametrize("frame", FRAMES)
def test_pose_stamped_bytes_equal_rclpys_both_ways(ros, frame):
    rng = np.random.default_rng(len(frame))
    w = cdr.StampedWriter("pose", frame)
    for _ in range(20):
        stamp = int(rng.integers(0, 2**31)) * 1_000_000_000 + int(rng.integers(0, 1_000_000_000))
        v = tuple(rng.normal(size=7).tolist())
        msg = _pose_msg(ros, stamp, frame, v)
        ref, mine = ros["ser"](msg), w.encode(stamp, v)
        assert ros["de"](mine, ros["Pose"]) == msg
        assert cdr.decode_pose_stamped(ref) == (stamp, frame, v)


@pytest.mark.parametrize("frame", FRAMES)
def test_wrench_stamped_bytes_equal_rclpys_both_ways(ros, frame):
    rng = np.random.default_rng(7 + len(frame))
    w = cdr.StampedWriter("wrench", frame)
    for _ in range(20):
        stamp = int(rng.integers(0, 2**31)) * 1_000_000_000 + int(rng.integers(0, 1_000_000_000))
        v = tuple(rng.normal(size=6).tolist())
        m = ros["Wrench"]()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        m.header.frame_id = frame
        f, t = m.wrench.force, m.wrench.torque
        f.x, f.y, f.z, t.x, t.y, t.z = v
        ref, mine = ros["ser"](m), w.encode(stamp, v)
        assert ros["de"](mine, ros["Wrench"]) == m
        assert cdr.decode_wrench_stamped(ref) == (stamp, frame, v)


@pytest.mark.parametrize("names", [(), ("jaw",), ("outer_yaw", "outer_pitch", "insertion"),
                                   ("a", "bb", "ccc", "dddd", "eeeee", "f", "g")])
@pytest.mark.parametrize("present", [(True, True, True), (True, False, False), (True, False, True),
                                     (False, False, False)])
def test_joint_state_bytes_equal_rclpys_both_ways(ros, names, present):
    rng = np.random.default_rng(len(names))
    w = cdr.JointStateWriter(names, frame_id="base")
    n = len(names)
    for _ in range(10):
        stamp = int(rng.integers(0, 2**31)) * 1_000_000_000 + int(rng.integers(0, 1_000_000_000))
        arrays = [tuple(rng.normal(size=n).tolist()) if here else None for here in present]
        m = ros["Joints"]()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        m.header.frame_id = "base"
        m.name = list(names)
        m.position, m.velocity, m.effort = [list(a) if a is not None else [] for a in arrays]
        ref, mine = ros["ser"](m), w.encode(stamp, *arrays)
        assert ros["de"](mine, ros["Joints"]) == m
        assert cdr.decode_joint_state(ref) == (stamp, tuple(names)) + tuple(a or () for a in arrays)


def test_joint_state_writer_refuses_a_wrong_count():
    with pytest.raises(ValueError, match="2 values for 3 joints"):
        cdr.JointStateWriter(("a", "b", "c")).encode(0, (1.0, 2.0))


def test_big_endian_input_reads_as_the_same_values():
    """A big-endian sender (CDR_BE): the same pose and joints, byte order from the header."""
    frame = b"base\x00"
    buf = bytearray(cdr.CDR_BE) + struct.pack(">iII", 5, 6, len(frame)) + frame
    buf += b"\x00" * ((-(len(buf) - 4)) % 8)
    buf += struct.pack(">7d", 1, 2, 3, 0, 0, 0, 1)
    assert cdr.decode_pose_stamped(bytes(buf)) == (5_000_000_006, "base", (1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0))
    js = bytearray(cdr.CDR_BE) + struct.pack(">iII", 1, 2, 1) + b"\x00"
    js += b"\x00" * ((-(len(js) - 4)) % 4)
    js += struct.pack(">I", 1) + struct.pack(">I", 2) + b"q\x00"
    js += b"\x00" * ((-(len(js) - 4)) % 4)
    js += struct.pack(">I", 1)
    js += b"\x00" * ((-(len(js) - 4)) % 8)
    js += struct.pack(">d", 0.5) + struct.pack(">I", 0) + struct.pack(">I", 0)
    assert cdr.decode_joint_state(bytes(js)) == (1_000_000_002, ("q",), (0.5,), (), ())


def test_every_cut_and_many_corruptions_are_refused_with_cdr_error(ros):
    """A message cut at any byte, or with random bytes changed, reads as CdrError or as some
    message: never another exception (the bridge counts and refuses a CdrError)."""
    pose = cdr.StampedWriter("pose", "PSM1_base").encode(123, (0, 0, 0, 0, 0, 0, 1))
    js = cdr.JointStateWriter(("a", "b", "c")).encode(9, (1, 2, 3), (4, 5, 6), (7, 8, 9))
    wrench = cdr.StampedWriter("wrench", "tip").encode(1, (1, 2, 3, 0, 0, 0))
    rng = np.random.default_rng(3)
    for buf, dec in ((pose, cdr.decode_pose_stamped), (js, cdr.decode_joint_state), (wrench, cdr.decode_wrench_stamped)):
        for n in range(len(buf)):
            with pytest.raises(cdr.CdrError):
                dec(buf[:n])
        for _ in range(3000):
            b = bytearray(buf)
            for i in rng.integers(0, len(b), size=int(rng.integers(1, 4))):
                b[i] = int(rng.integers(0, 256))
            try:
                dec(bytes(b))
            except cdr.CdrError:
                pass


def test_errors_name_what_was_wrong():
    with pytest.raises(cdr.CdrError, match="expected a CDR encapsulation header"):
        cdr.decode_pose_stamped(b"\x07\x01\x00\x00" + b"\x00" * 80)
    bad = bytearray(cdr.StampedWriter("pose", "ab").encode(0, (0,) * 7))
    struct.pack_into("<I", bad, 12, 5000)
    with pytest.raises(cdr.CdrError, match="frame_id: length 5000"):
        cdr.decode_pose_stamped(bytes(bad))
    js = bytearray(cdr.JointStateWriter(("a",)).encode(0, (1.0,)))
    struct.pack_into("<I", js, 20, 100000)          # the name count
    with pytest.raises(cdr.CdrError, match="100000 elements"):
        cdr.decode_joint_state(bytes(js))


@pytest.mark.parametrize("encoding, frame", [("16UC1", "cam0"), ("32FC1", "depth_optical_frame"), ("mono16", "")])
def test_images_read_as_rclpy_reads_them(ros2_env, encoding, frame):
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import CompressedImage, Image

    rng = np.random.default_rng(5)
    m = Image()
    m.header.stamp.sec, m.header.stamp.nanosec = 1_700_000_000, 123_456_789
    m.header.frame_id = frame
    m.height, m.width, m.encoding, m.is_bigendian = 3, 5, encoding, 0
    m.step = 5 * (4 if encoding == "32FC1" else 2) + 2        # (a padded row)
    m.data = rng.integers(0, 256, size=m.step * 3).astype(np.uint8).tobytes()
    got = cdr.decode_image(serialize_message(m))
    assert got.header == ((1_700_000_000, 123_456_789), frame)
    assert (got.height, got.width, got.encoding, got.is_bigendian, got.step) == (3, 5, encoding, 0, m.step)
    assert bytes(got.data) == bytes(m.data)
    c = CompressedImage()
    c.header.frame_id, c.format = frame, "16UC1; compressedDepth png"
    c.data = b"\x89PNG" + bytes(range(50))
    got = cdr.decode_compressed_image(serialize_message(c))
    assert got.header.frame_id == frame and got.format == c.format and bytes(got.data) == bytes(c.data)
    for buf, dec in ((serialize_message(m), cdr.decode_image), (serialize_message(c), cdr.decode_compressed_image)):
        for n in range(len(buf) - 20):        # (rclpy's buffer may run past the message: cut well inside it)
            with pytest.raises(cdr.CdrError):
                dec(buf[:n])


@pytest.mark.parametrize("frame", FRAMES)
@pytest.mark.parametrize("model,n_d", [("plumb_bob", 5), ("rational_polynomial", 8), ("", 0)])
def test_camera_info_reads_rclpys_bytes(ros2_env, frame, model, n_d):
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import CameraInfo

    rng = np.random.default_rng(n_d + len(frame))
    m = CameraInfo()
    m.header.stamp.sec, m.header.stamp.nanosec = 1_700_000_000, 123_456_789
    m.header.frame_id = frame
    m.height, m.width = 480, 640
    m.distortion_model = model
    m.d = rng.normal(size=n_d).tolist()
    m.k, m.r, m.p = rng.normal(size=9).tolist(), rng.normal(size=9).tolist(), rng.normal(size=12).tolist()
    m.binning_x, m.binning_y = 2, 3
    m.roi.x_offset, m.roi.y_offset, m.roi.height, m.roi.width, m.roi.do_rectify = 4, 5, 6, 7, True
    got = cdr.decode_camera_info(serialize_message(m))
    assert got.header.frame_id == frame and (got.header.stamp.sec, got.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert (got.height, got.width, got.distortion_model) == (480, 640, model)
    assert got.d == tuple(m.d) and got.k == tuple(m.k) and got.r == tuple(m.r) and got.p == tuple(m.p)
    assert (got.binning_x, got.binning_y) == (2, 3) and got.roi == (4, 5, 6, 7, True)
    raw = serialize_message(m)
    for cut in (3, 20, len(raw) // 2, len(raw) - 30):      # damaged: CdrError, never another exception
        with pytest.raises(cdr.CdrError):
            cdr.decode_camera_info(raw[:cut])
