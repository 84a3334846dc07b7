"""Per-camera reader threads: own rate per camera, stale cameras reported (OpenNI2, synthetic, stand-ins)."""
import time
from typing import Optional

import pytest

from pointfence.kernels.errors import InputError
from pointfence.kernels.frame import DepthFrame
from pointfence.service.sources import DepthSource, default_camera, open_source
from pointfence.service.sources.threaded import CameraReader, CameraRig


class _Stops(DepthSource):
    """Delivers ``n`` frames at its rate, then goes silent (a camera whose cable came out)."""

    def __init__(self, name, n, rate_hz=50.0, fail=False):
        super().__init__(default_camera(name, width=8, height=6), rate_hz, realtime=True)
        self.n, self.fail = n, fail

    def _frame(self, seq) -> Optional[DepthFrame]:
        return DepthFrame(self.camera.name, __import__("numpy").zeros((6, 8), "uint16"), seq / self.rate_hz, seq)

    def read(self, timeout=None):
        if self._seq >= self.n:
            if self.fail:
                raise OSError("USB transfer failed")
            time.sleep(timeout or 0.05)
            return None
        return super().read(timeout)


def test_each_camera_own_thread_and_rate():
    fast = open_source("synthetic:plane", default_camera("fast", width=32, height=24), rate_hz=40)
    slow = open_source("synthetic:plane", default_camera("slow", width=32, height=24), rate_hz=10)
    with CameraRig([fast, slow]) as rig:
        time.sleep(0.6)
        st = rig.status()
        assert rig.stale() == {}
        assert set(rig.latest()) == {"fast", "slow"}
    assert st["fast"].frames > 2 * st["slow"].frames
    assert st["fast"].rate_hz == pytest.approx(40, rel=0.35) and st["slow"].rate_hz == pytest.approx(10, rel=0.35)
    assert fast.closed and slow.closed


def test_stopped_camera_is_reported_stale():
    ok = _Stops("ok", 10 ** 9)
    dead = _Stops("dead", 3)
    broken = _Stops("broken", 2, fail=True)
    rig = CameraRig([ok, dead, broken], stale_after=0.2).start()
    try:
        rig.readers["dead"].wait(after=2, timeout=2)
        time.sleep(0.5)
        stale = rig.stale()
        assert "ok" not in stale
        assert "no new frame for" in stale["dead"]
        assert "USB transfer failed" in stale["broken"]
        assert rig.status()["dead"].frames == 3
    finally:
        rig.stop()


def test_recorded_end_is_stale(shared_data):
    src = open_source(f"recorded:{shared_data / 'pcl_kinect_grabber_seq' / 'tiff'}", loop=False, rate_hz=100)
    r = CameraReader(src).start()
    time.sleep(0.3)
    assert r.status().frames == 3 and r.status().reason == "stream ended"
    r.stop()


def test_openni2_playback_in_reader(shared_data):
    from pointfence.service.sources.openni2 import OpenNI2Unavailable

    try:
        src = open_source(f"openni2:{shared_data / 'oni_3dj' / 'test.oni'}", realtime=True, loop=False)
    except OpenNI2Unavailable as e:
        pytest.skip(str(e))
    got = []
    r = CameraReader(src, on_frame=got.append).start()
    r.wait(after=11, timeout=3)
    time.sleep(0.2)
    s = r.status()
    r.stop()
    assert len(got) == 12 and s.reason == "stream ended"
    assert s.rate_hz == pytest.approx(30, rel=0.3)  # the recording plays at its own 30 Hz


def test_reader_bad_inputs():
    with pytest.raises(InputError, match="DepthSource"):
        CameraReader("synthetic:plane")
    src = open_source("synthetic:plane")
    with pytest.raises(InputError, match="stale_after"):
        CameraReader(src, stale_after=0)
    with pytest.raises(InputError, match="unique"):
        CameraRig([src, open_source("synthetic:plane")])
