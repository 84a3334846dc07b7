"""FEEDBACK carries the state of the tick that sent it: the proxy, the robot position, the
contact, the hold mask and the fixture flags of its arm, as the service's ``out`` holds them
after that tick, and the robot's mode when it was sent (before the tick's robot command) (``UdpHub.send_feedback`` reads them once a tick)."""
import time

import numpy as np

from pointfence.clients import Client
from pointfence.clients import protocol as P
from pointfence.service.app import Service
from pointfence.service.frames import SimFrames
from pointfence.service.udp_server import UdpHub

from service_cases import POINT_MASS, balloon_config

KEY = bytes(range(7, 39))


def _wait_feedback(c: Client, tick: int) -> P.Feedback:
    end = time.monotonic() + 2.0
    while time.monotonic() < end:
        fb = c.poll()
        if fb is not None and fb.tick == tick:
            return fb
        time.sleep(0.0005)
    raise AssertionError(f"no FEEDBACK for tick {tick} within 2 s")


def test_feedback_carries_this_ticks_proxy_robot_contact_hold_and_flags(tmp_path):
    cfg = balloon_config(tmp_path, arch="III", robot=POINT_MASS)
    hub = UdpHub(KEY, 1, receiver=False, timeout_ms=1000)
    svc = Service(cfg, list(hub.masters), backend="numpy")
    hub.attach(svc)
    sources = cfg.open_sources()
    feeder = SimFrames(svc.pipeline, sources, cfg.service.stale_s, cfg.service.max_frame_age_s)
    svc.attach_frames(feeder)
    feeder.poll(0.0)
    svc.start()
    c = Client(*hub.address, KEY, 9, timeout_ms=1000)
    seen = {"coupled": set(), "hold": set(), "contact": set()}
    try:
        c.hello_send()
        hub.pump()
        assert c.hello_wait(0.0) is None        # the cookie round
        hub.pump()
        assert c.hello_wait(2.0) is not None
        period = 1.0 / cfg.service.rate_hz
        for k in range(1, 700):
            # pedal down from tick 50, pushing down into the balloon below; pedal up near the end
            depth = min(max(k - 50, 0) * 2e-4, 0.12)
            c.send_state((0.0, 0.0, -depth), clutch=50 <= k < 650)
            deadline = time.monotonic() + 1.0
            while hub.pump() == 0 and time.monotonic() < deadline:
                time.sleep(0.0002)
            t = k * period
            feeder.poll(t)
            mode = int(svc.robots[0].state)      # FEEDBACK goes out before the tick commands the robot
            svc.tick(k, t, period, 300 <= k < 305, t)      # five late ticks (overruns): the arm holds
            fb = _wait_feedback(c, int(round(t * cfg.service.rate_hz)))
            out = svc.out
            assert fb.proxy == tuple(out.proxy[0].tolist())
            assert fb.robot == tuple(out.robot_pos[0].tolist())
            assert fb.contact == int(out.state[0])
            assert fb.hold == int(out.arm_hold[0])
            coupled = bool(fb.fixture & P.FX_COUPLED)
            assert coupled == bool(out.coupled[0])
            assert fb.fixture & P.FX_HAPTICS and fb.fixture & P.FX_TELEOP and fb.fixture & P.FX_FIXTURE
            assert fb.robot_mode == (P.ROBOT_ENABLED, P.ROBOT_HOLDING, P.ROBOT_FAULT)[mode]
            assert np.allclose(fb.force, out.force_master[0])
            seen["coupled"].add(coupled)
            seen["hold"].add(fb.hold != 0)
            seen["contact"].add(fb.contact != P.CONTACT_FREE)
    finally:
        c.close()
        hub.close()
        svc.close()
    # the run went through both sides of each field (the comparisons above were not all of zeros)
    assert seen == {"coupled": {False, True}, "hold": {False, True}, "contact": {False, True}}, seen
