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


def test_feedback_force_is_saturated_at_the_session_limit_and_zero_when_not_finite():
    """The C receiver sends the tick's FEEDBACK: the force is scaled down to the session's force
    limit (the lower of the device's and the service's) along its direction, a non-finite force
    is sent as zero, and the device accepts every one (its tag under the session key, its sequence
    number new in the device's window)."""
    hub = UdpHub(KEY, 1, receiver=False, timeout_ms=1000, max_force=10.0)
    c = Client(*hub.address, KEY, 9, timeout_ms=1000, max_force=2.0)
    try:
        c.hello_send()
        hub.pump()
        assert c.hello_wait(0.0) is None
        hub.pump()
        assert c.hello_wait(2.0) is not None
        c.send_state((0.0, 0.0, 0.0))
        hub.pump()
        m = hub.masters[0]
        m.poll(0.001)
        s = m.session
        assert s.max_force == 2.0
        for k, (f, want) in enumerate((((3.0, 4.0, 0.0), (1.2, 1.6, 0.0)), ((0.5, -1.0, 0.25), (0.5, -1.0, 0.25)),
                                       ((np.nan, 1.0, 0.0), (0.0, 0.0, 0.0)), ((np.inf, 0.0, 0.0), (0.0, 0.0, 0.0)))):
            hub.tick(0.001 * (k + 2))
            m.send_force(np.array(f))
            fb = _wait_feedback(c, k + 2)
            assert np.allclose(fb.force, want, atol=1e-12), (f, fb.force)
        assert hub.feedback_sent == 4 and hub.send_errors == 0
    finally:
        c.close()
        hub.close()
