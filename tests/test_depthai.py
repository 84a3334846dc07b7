"""depthai (Luxonis OAK) source: everything that runs without a device.

Pipeline construction runs on a recording stand-in of the ``dai`` module (depthai v3 refuses to
create device nodes without a device); intrinsics and frame conversion use the real depthai
classes (CalibrationHandler, ImgFrame) when the library is installed; the no-device error uses
the real device search.
"""
from datetime import timedelta
from types import SimpleNamespace

import numpy as np
import pytest

from pointfence.kernels.camera import Camera
from pointfence.kernels.errors import InputError
from pointfence.service.sources import open_source
from pointfence.service.sources import depthai_source as das


def _real_dai():
    try:
        return das.import_depthai()
    except das.DepthAIUnavailable as e:
        pytest.skip(f"depthai not installed: {e}")


# -- a stand-in dai module that records what the pipeline builder does ----------------------
class _Rec:
    def __init__(self, log, kind):
        self.log, self.kind = log, kind

    def __getattr__(self, name):
        def call(*a, **k):
            self.log.append((self.kind, name, a, k))
            if name in ("build",):
                return self
            if name in ("requestOutput",):
                return _Rec(self.log, f"{self.kind}.out")
            if name == "createOutputQueue":
                return "QUEUE"
            return None
        if name in ("left", "right"):
            return f"{self.kind}.{name}"
        if name == "depth":
            return _Rec(self.log, f"{self.kind}.depth")
        return call


def _fake_dai(devices=()):
    log = []
    sockets = SimpleNamespace(CAM_A="CAM_A", CAM_B="CAM_B", CAM_C="CAM_C")
    presets = SimpleNamespace(**{p.upper(): f"PRESET_{p.upper()}" for p in das.PRESETS})
    node = SimpleNamespace(Camera="Camera", StereoDepth=SimpleNamespace(PresetMode=presets))
    counter = {"Camera": 0}

    class Pipeline:
        def create(self, cls):
            if cls == "Camera":
                counter["Camera"] += 1
                return _Rec(log, f"cam{counter['Camera']}")
            return _Rec(log, "stereo")

    dai = SimpleNamespace(CameraBoardSocket=sockets, node=node, __version__="3.12.0",
                          Device=SimpleNamespace(getAllAvailableDevices=lambda: list(devices)))
    return dai, Pipeline(), log


def test_pipeline_construction():
    dai, pipe, log = _fake_dai()
    q = das.build_pipeline(dai, pipe, align="rgb", width=640, height=400, fps=15, preset="high_detail")
    assert q == "QUEUE"
    calls = [(k, n, a) for k, n, a, _ in log]
    assert ("cam1", "build", ("CAM_B",)) in calls and ("cam2", "build", ("CAM_C",)) in calls
    assert ("stereo", "setDefaultProfilePreset", ("PRESET_HIGH_DETAIL",)) in calls
    assert ("stereo", "setDepthAlign", ("CAM_A",)) in calls
    assert ("stereo", "setOutputSize", (640, 400)) in calls
    assert ("stereo", "setLeftRightCheck", (True,)) in calls and ("stereo", "setSubpixel", (True,)) in calls
    outs = [(k, a, kw) for k, n, a, kw in log if n == "requestOutput"]
    assert outs == [("cam1", ((640, 400),), {"fps": 15.0}), ("cam2", ((640, 400),), {"fps": 15.0})]
    links = [(k, a) for k, n, a, _ in log if n == "link"]
    assert links == [("cam1.out", ("stereo.left",)), ("cam2.out", ("stereo.right",))]
    assert any(k == "stereo.depth" and n == "createOutputQueue" for k, n, _, _ in log)

    dai, pipe, log = _fake_dai()
    das.build_pipeline(dai, pipe)  # default: aligned to the rectified right camera, no resize
    calls = [(k, n, a) for k, n, a, _ in log]
    assert ("stereo", "setDepthAlign", ("CAM_C",)) in calls
    assert not any(n == "setOutputSize" for _, n, _ in calls)


def test_pipeline_bad_options():
    dai, pipe, _ = _fake_dai()
    with pytest.raises(InputError, match="align"):
        das.build_pipeline(dai, pipe, align="center")
    with pytest.raises(InputError, match="preset"):
        das.build_pipeline(dai, pipe, preset="fastest")


def test_device_selection_lists_what_was_found():
    info = SimpleNamespace(getDeviceId=lambda: "18443010C1A2B3", name="1.3", state="X_LINK_UNBOOTED")
    dai, _, _ = _fake_dai([info])
    assert das.find_device(dai, "") is info
    assert das.find_device(dai, "18443010C1A2B3") is info
    with pytest.raises(InputError, match=r"no device 'nope'; devices found: 18443010C1A2B3 \(1.3, X_LINK_UNBOOTED\)"):
        das.find_device(dai, "nope")
    dai, _, _ = _fake_dai([])
    with pytest.raises(InputError, match="devices found: none"):
        das.find_device(dai, "")


def test_no_device_attached_real_library():
    _real_dai()
    if das.list_devices():
        pytest.skip("an OAK device is attached here")
    with pytest.raises(InputError, match="no OAK device found.*devices found: none"):
        open_source("depthai:")
    with pytest.raises(InputError, match="devices found: none"):
        open_source("depthai:18443010C1A2B3")


def test_intrinsics_from_calibration():
    dai = _real_dai()
    calib = dai.CalibrationHandler()
    K_right = [[860.0, 0.0, 645.0], [0.0, 861.0, 402.0], [0.0, 0.0, 1.0]]  # at 1280x800
    K_rgb = [[3090.0, 0.0, 1930.0], [0.0, 3088.0, 1080.0], [0.0, 0.0, 1.0]]  # at 3840x2160
    calib.setCameraIntrinsics(dai.CameraBoardSocket.CAM_C, K_right, 1280, 800)
    calib.setCameraIntrinsics(dai.CameraBoardSocket.CAM_A, K_rgb, 3840, 2160)
    coeffs = [0.1, -0.2, 0.001, 0.002, 0.05] + [0.0] * 9
    calib.setDistortionCoefficients(dai.CameraBoardSocket.CAM_A, coeffs)
    cam = das.camera_from_calibration(dai, calib, "right", 640, 400, name="oak", z_max=8.0)
    assert (cam.width, cam.height, cam.name, cam.depth_scale, cam.z_max) == (640, 400, "oak", 0.001, 8.0)
    assert cam.fx == pytest.approx(430.0, rel=1e-3) and cam.fy == pytest.approx(430.5, rel=1e-3)
    assert cam.cx == pytest.approx(322.5, abs=1.0) and cam.cy == pytest.approx(201.0, abs=1.0)
    assert cam.dist == (0.0,) * 5
    cam = das.camera_from_calibration(dai, calib, "rgb", 640, 360)
    assert cam.fx == pytest.approx(3090.0 / 6, rel=2e-3) and cam.cx == pytest.approx(1930 / 6, abs=1.0)
    assert cam.dist == pytest.approx((0.1, -0.2, 0.001, 0.002, 0.05))


def test_intrinsics_conversion_rejects_garbage():
    dai = SimpleNamespace(CameraBoardSocket=SimpleNamespace(CAM_A="A", CAM_B="B", CAM_C="C"))
    bad = SimpleNamespace(getCameraIntrinsics=lambda s, w, h: [[0, 0, 0], [0, 0, 0], [0, 0, 1]])
    with pytest.raises(InputError, match="positive focal"):
        das.camera_from_calibration(dai, bad, "left", 640, 400)

    def missing(s, w, h):
        raise RuntimeError("There is no Intrinsic matrix available for the the requested cameraID")

    with pytest.raises(InputError, match="no calibration for CAM_B"):
        das.camera_from_calibration(dai, SimpleNamespace(getCameraIntrinsics=missing), "left", 640, 400)


def test_frame_conversion_real_imgframe():
    dai = _real_dai()
    cam = Camera("oak", 640, 400, 430.0, 430.0, 320.0, 200.0)
    depth = (np.arange(400 * 640, dtype=np.uint32) % 5000).astype(np.uint16).reshape(400, 640)
    msg = dai.ImgFrame()
    msg.setFrame(depth)
    msg.setWidth(640)
    msg.setHeight(400)
    msg.setType(dai.ImgFrame.Type.RAW16)
    msg.setTimestamp(timedelta(seconds=12.5))
    f = das.frame_from_message(msg, cam, seq=7)
    f.check(640, 400)
    assert np.array_equal(f.depth, depth) and f.timestamp == pytest.approx(12.5) and f.seq == 7 and f.camera == "oak"
    small = Camera("oak", 320, 200, 215.0, 215.0, 160.0, 100.0)
    with pytest.raises(InputError, match="expected 320x200"):
        das.frame_from_message(msg, small, 0)


def test_frame_conversion_rejects_disparity():
    cam = Camera("oak", 4, 2, 4.0, 4.0, 2.0, 1.0)
    msg = SimpleNamespace(getFrame=lambda: np.zeros((2, 4), np.uint8), getTimestamp=lambda: timedelta(seconds=1))
    with pytest.raises(InputError, match="uint16"):
        das.frame_from_message(msg, cam, 0)


def test_old_depthai_is_refused(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "depthai", SimpleNamespace(__version__="2.24.0"))
    with pytest.raises(das.DepthAIUnavailable, match="depthai>=3"):
        das.import_depthai()
    monkeypatch.setitem(sys.modules, "depthai", None)
    with pytest.raises(das.DepthAIUnavailable, match="pip install"):
        das.import_depthai()
