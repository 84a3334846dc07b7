"""OpenNI2 source: playback of a real .oni recording through the OpenNI2 library's file driver."""
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service.sources import SCHEMES, open_source
from pointfence.service.sources.openni2 import (OpenNI2Unavailable, depth_scale_of, focal_from_fov,
                                                 focal_from_zero_plane, load_openni2)


def _need_openni2():
    try:
        load_openni2()
    except OpenNI2Unavailable as e:
        pytest.skip(f"OpenNI2 not installed here: {e}")


@pytest.fixture
def oni(shared_data):
    path = shared_data / "oni_3dj" / "test.oni"
    if not path.is_file():
        pytest.skip(f"{path} missing")
    _need_openni2()
    return path


def test_scheme_registered():
    assert "openni2" in SCHEMES and "depthai" in SCHEMES


def test_intrinsics_formulas():
    # PS1080 zero plane: 120 mm, 0.1042 mm at 1280 px -> 575.8 px at 640 px.
    assert focal_from_zero_plane(120, 0.1042, 640) == pytest.approx(575.816, abs=1e-2)
    assert focal_from_zero_plane(120, 0.1042, 320) == pytest.approx(287.908, abs=1e-2)
    # 58.1 deg horizontal field of view at 640 px -> about 575.8 px (the recording's reported FOV).
    assert focal_from_fov(640, 1.0144686698913574) == pytest.approx(575.8, abs=0.2)
    assert depth_scale_of("ONI_PIXEL_FORMAT_DEPTH_1_MM") == 0.001
    assert depth_scale_of("ONI_PIXEL_FORMAT_DEPTH_100_UM") == 0.0001
    with pytest.raises(InputError, match="SHIFT_9_2"):
        depth_scale_of("ONI_PIXEL_FORMAT_SHIFT_9_2")


def test_playback_12_frames(oni):
    with open_source(f"openni2:{oni}?loop=false", name="kinect") as src:
        cam = src.camera
        assert (cam.width, cam.height) == (640, 480)
        assert src.intrinsics_source == "zero-plane"
        assert cam.fx == pytest.approx(575.8157, abs=1e-3) and cam.fy == cam.fx
        assert (cam.cx, cam.cy) == (320.0, 240.0)
        assert cam.depth_scale == 0.001
        frames = list(src)
        assert src.ended and src.read() is None
    assert len(frames) == 12
    ts = np.array([f.timestamp for f in frames])
    assert ts[0] == pytest.approx(0.01168, abs=1e-5) and ts[-1] == pytest.approx(0.378742, abs=1e-6)
    assert np.allclose(np.diff(ts), 1 / 30, atol=1e-3)
    assert [f.seq for f in frames] == list(range(12))
    for f in frames:
        f.check(640, 480)
        valid = f.depth[f.depth > 0]
        assert 0.70 < valid.size / f.depth.size < 0.80
        assert 600 <= valid.min() and valid.max() <= 5000  # a room seen from 0.6-4.6 m
        assert 2.3 < valid.mean() * cam.depth_scale < 2.9
    # a static scene: frames differ by sensor noise only
    both = (frames[0].depth > 0) & (frames[-1].depth > 0)
    diff = np.abs(frames[0].depth[both].astype(float) - frames[-1].depth[both])
    assert np.median(diff) < 20


def test_loop_and_color(oni):
    with open_source(f"openni2:{oni}", color=True, name="c") as src:
        frames = [src.read() for _ in range(30)]
    assert all(f is not None for f in frames)
    ts = [f.timestamp for f in frames]
    assert all(b > a for a, b in zip(ts, ts[1:])), "timestamps keep increasing across loops"
    assert np.array_equal(frames[0].depth, frames[12].depth)
    assert frames[0].color is not None and frames[0].color.shape == (480, 640, 3)
    frames[0].check(640, 480)


def test_unmirror_flips(oni):
    with open_source(f"openni2:{oni}?loop=false") as a, open_source(f"openni2:{oni}?loop=false&unmirror=false") as b:
        fa, fb = a.read(), b.read()
    assert a.software_unmirror and not b.software_unmirror
    assert np.array_equal(fa.depth, fb.depth[:, ::-1])


def test_config_with_openni2(oni, tmp_path):
    from pointfence.service import config

    toml = tmp_path / "c.toml"
    toml.write_text(textwrap.dedent(f"""
        [[camera]]
        name = "oni"
        source = "openni2:{oni}?loop=false"
        fx = 575.8157
        fy = 575.8157
        cx = 320.0
        cy = 240.0
        width = 640
        height = 480
    """))
    cfg = config.load(toml)
    (src,) = cfg.open_sources()
    try:
        assert src.camera.name == "oni"
        assert sum(1 for _ in src) == 12
    finally:
        src.close()


def test_bad_inputs(oni, tmp_path):
    with pytest.raises(InputError, match="not found"):
        open_source(f"openni2:{tmp_path / 'missing.oni'}")
    junk = tmp_path / "junk.oni"
    junk.write_bytes(b"not an oni file" * 10)
    with pytest.raises(InputError, match="cannot play"):
        open_source(f"openni2:{junk}")
    with pytest.raises(InputError, match="registration"):
        open_source(f"openni2:{oni}", registration="sideways")
    with pytest.raises(InputError, match="depth_to_color"):
        open_source(f"openni2:{oni}", registration="depth_to_color")  # a recording cannot re-register
    with pytest.raises(InputError, match="unknown option"):
        open_source(f"openni2:{oni}", colour=True)
    from pointfence.kernels.camera import Camera

    with pytest.raises(InputError, match="640x480"):
        open_source(f"openni2:{oni}", Camera("small", 320, 240, 300, 300, 160, 120))


def test_no_device_lists_what_was_found():
    _need_openni2()
    with pytest.raises(InputError, match="devices attached"):
        open_source("openni2:any")


def test_missing_library_says_how_to_install(tmp_path):
    code = textwrap.dedent(f"""
        from pointfence.service.sources.openni2 import load_openni2, OpenNI2Unavailable
        try:
            load_openni2(redist={str(tmp_path)!r})
        except OpenNI2Unavailable as e:
            print("ERR", e)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60).stdout
    assert "ERR" in out and "apt-get install libopenni2-0" in out and "pip install openni" in out
    code = "import sys; sys.modules['openni'] = None\n" + code
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60).stdout
    assert "ERR" in out and "pip install openni" in out
