"""``RosNode.polled`` (service/ros2/node.py): a subscription no executor serves; its owner takes the
messages in arrival order, each with the middleware's reception time as its arrival, so one that
waited for its taker reads as old as it is (the CRTK arm's freshness checks rest on it)."""
from __future__ import annotations

import time


def test_a_polled_message_keeps_its_reception_time_and_order(ros2_env):
    from geometry_msgs.msg import PoseStamped

    from pointfence.service.ros2 import cdr
    from pointfence.service.ros2 import crtk_wire as wire
    from pointfence.service.ros2.node import RosNode

    pub_node = RosNode("pf_test_polled_pub").start()
    sub_node = RosNode("pf_test_polled_sub", executor="events").start()
    try:
        sub = sub_node.polled(PoseStamped, "/pf_test_polled/cp", wire.qos_stream(8))
        pub = pub_node.node.create_publisher(PoseStamped, "/pf_test_polled/cp", wire.qos_reliable(8))
        w = cdr.StampedWriter("pose", "base")
        end = time.monotonic() + 10
        while sub.take() is None and time.monotonic() < end:     # (until both sides have matched)
            pub.publish(w.encode(99, (0, 0, 0, 0, 0, 0, 1)))
            time.sleep(0.02)
        time.sleep(0.05)
        while sub.take() is not None:
            pass
        sent = time.monotonic()
        for k in range(3):
            pub.publish(w.encode(k, (k, 0, 0, 0, 0, 0, 1)))
        time.sleep(0.4)                                     # the taker comes late
        got = [sub.take() for _ in range(3)]
        assert sub.take() is None
        assert [cdr.decode_pose_stamped(raw)[0] for raw, _ in got] == [0, 1, 2]
        now = time.monotonic()
        for _, arrival in got:
            assert sent - 0.01 <= arrival <= sent + 0.2 and now - arrival >= 0.2   # received then, not taken now
    finally:
        pub_node.close()
        sub_node.close()
