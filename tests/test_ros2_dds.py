"""The ROS 2 environment of tests, benches and CI keeps DDS on this machine (service/ros2/dds.py),
and two processes exchange standard messages through it (service/ros2/node.py)."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
import xml.etree.ElementTree as ET

import pytest

from pointfence.kernels.errors import InputError
from pointfence.service.ros2 import dds

NS = "{http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles}"


def test_local_profile_allows_loopback_only(tmp_path):
    env = dds.local_env(17, tmp_path)
    assert env["ROS_DOMAIN_ID"] == "17" and env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert env["ROS_LOG_DIR"].startswith(str(tmp_path))
    root = ET.parse(env["FASTRTPS_DEFAULT_PROFILES_FILE"]).getroot()
    part = root.find(f"{NS}participant")
    assert part.get("is_default_profile") == "true"
    rtps = part.find(f"{NS}rtps")
    assert rtps.find(f"{NS}useBuiltinTransports").text == "false"   # no SHM, no default UDP on every interface
    peers = [a.text for a in rtps.iter(f"{NS}address")]
    assert peers == ["127.0.0.1"]
    descs = {d.find(f"{NS}transport_id").text: d for d in root.find(f"{NS}transport_descriptors")}
    types = {i: d.find(f"{NS}type").text for i, d in descs.items()}
    assert sorted(types.values()) == ["SHM", "UDPv4"]            # shared memory never leaves the machine
    (udp,) = [d for d in descs.values() if d.find(f"{NS}type").text == "UDPv4"]
    assert [a.text for a in udp.iter(f"{NS}address")] == ["127.0.0.1"]
    assert sorted(t.text for t in rtps.find(f"{NS}userTransports")) == sorted(descs)


@pytest.mark.parametrize("bad", [-1, 233, "7a", 1.5, None])
def test_domain_id_out_of_range_is_refused(bad, tmp_path):
    with pytest.raises(InputError, match="ROS_DOMAIN_ID"):
        dds.local_env(bad, tmp_path)


def test_unique_domain_ids_stay_in_range():
    assert {dds.unique_domain_id(s) for s in range(1000)} <= set(range(1, 233))


PUBLISHER = textwrap.dedent("""
    import time
    from geometry_msgs.msg import PoseStamped
    from pointfence.service.ros2.node import RosNode
    with RosNode("pf_test_pub") as n:
        pub = n.node.create_publisher(PoseStamped, "/pf_test/pose", 10)
        for i in range(200):
            m = PoseStamped(); m.header.frame_id = "world"; m.pose.position.x = float(i)
            pub.publish(m); time.sleep(0.02)
""")


def test_two_processes_exchange_pose_stamped(ros2_env):
    from geometry_msgs.msg import PoseStamped

    from pointfence.service.ros2.node import RosNode

    got = []
    with RosNode("pf_test_sub") as n:
        n.node.create_subscription(PoseStamped, "/pf_test/pose", lambda m: got.append((m.header.frame_id, m.pose.position.x)), 10)
        child = subprocess.Popen([sys.executable, "-c", PUBLISHER], env={**os.environ, **ros2_env})
        try:
            end = time.monotonic() + 20
            while len(got) < 5 and time.monotonic() < end and child.poll() is None:
                time.sleep(0.05)
        finally:
            child.kill()
            child.wait()
    assert len(got) >= 5, "no PoseStamped crossed between the two processes on the loopback profile"
    assert got[0][0] == "world" and all(b[1] > a[1] for a, b in zip(got, got[1:]))
