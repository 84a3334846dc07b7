"""RealSense source without a camera: the SDK itself writes the recordings (a ``software_device``
with a Z16 depth stream of known intrinsics, fed known depth images with known timestamps,
recorded by ``rs.recorder``) and the source plays them back through the SDK's playback device;
a software device also stands in for a live camera (serial, modes, visual presets, global time)."""
import sqlite3
import textwrap
import threading
import time

import numpy as np
import pytest

from pointfence.kernels.camera import Camera
from pointfence.kernels.errors import InputError
from pointfence.service.sources import SCHEMES, open_source
from pointfence.service.sources.threaded import CameraReader

rs = pytest.importorskip("pyrealsense2")
if not hasattr(rs, "recorder"):
    pytest.skip("pyrealsense2 without librealsense in it", allow_module_level=True)

from pointfence.service.sources.realsense import FrameHandoff, RealSenseSource  # noqa: E402

W, H = 64, 48
UNITS = 0.00025  # m per depth unit (a D405's is 0.0001, a D435's 0.001: anything but the default)
K = dict(fx=61.37, fy=60.91, ppx=31.7, ppy=23.3)
COEFFS = [0.11, -0.023, 0.0013, -0.0021, 0.004]
T0_MS = 1_700_000_000_123.456  # global time: ms on the host's system clock
STAMPS = [T0_MS + k * 33.3333 + (0.7 if k % 3 == 1 else 0.0) for k in range(7)]  # jitter: not synthesized from fps


def depth_images(n: int, seed: int = 5) -> list:
    """Known depth images: random codes over the whole uint16 range, with 0 and 65535 placed."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        img = rng.integers(0, 65536, size=(H, W), dtype=np.uint16)
        img[0, 0], img[-1, -1], img[k % H, :] = 0, 65535, k
        out.append(img)
    return out


def intrinsics(width=W, height=H, model=None, coeffs=COEFFS):
    i = rs.intrinsics()
    i.width, i.height = width, height
    i.fx, i.fy, i.ppx, i.ppy = K["fx"], K["fy"], K["ppx"], K["ppy"]
    i.model = rs.distortion.brown_conrady if model is None else model
    i.coeffs = list(coeffs)
    return i


def video_stream(uid, width=W, height=H, fps=30, stream=None, fmt=None, bpp=2, intr=None):
    vs = rs.video_stream()
    vs.type = rs.stream.depth if stream is None else stream
    vs.index, vs.uid = 0, uid
    vs.width, vs.height, vs.fps, vs.bpp = width, height, fps, bpp
    vs.fmt = rs.format.z16 if fmt is None else fmt
    vs.intrinsics = intr if intr is not None else intrinsics(width, height)
    return vs


def software_camera(serial="815412070123", modes=((W, H, 30),), presets=True, global_time=True):
    """(software_device, depth sensor, [profiles]) of a D400-like camera: its modes, visual presets
    (0..7, as rs400_visual_preset) and the global-time option."""
    sd = rs.software_device()
    sd.register_info(rs.camera_info.serial_number, serial)
    sd.register_info(rs.camera_info.name, "Intel RealSense D435 (software)")
    sensor = sd.add_sensor("Stereo Module")
    sensor.add_read_only_option(rs.option.depth_units, UNITS)
    if presets:
        sensor.add_option(rs.option.visual_preset, rs.option_range(0, 7, 1, 1), True)
    if global_time:
        sensor.add_option(rs.option.global_time_enabled, rs.option_range(0, 1, 1, 0), True)
    profiles = [sensor.add_video_stream(video_stream(uid, w, h, fps), uid == 0).as_video_stream_profile()
                for uid, (w, h, fps) in enumerate(modes)]
    return sd, sensor, profiles


def feed(sensor, profile, img, number, stamp_ms, domain=None, bpp=2):
    f = rs.software_video_frame()
    f.pixels = img
    f.bpp, f.stride = bpp, img.shape[1] * bpp
    f.timestamp, f.frame_number = stamp_ms, number
    f.domain = rs.timestamp_domain.global_time if domain is None else domain
    f.profile = profile
    if bpp == 2:
        f.depth_units = UNITS
    sensor.on_video_frame(f)


def record(path, images, stamps, *, first_number=100, pace_s=0.0, intr=None, stream=None, fmt=None, bpp=2):
    """Write ``images`` with ``stamps`` (ms) to an SDK recording at ``path`` (.db3: SDK >= 2.56)
    with the SDK's recorder; returns the path written."""
    sd = rs.software_device()
    sd.register_info(rs.camera_info.serial_number, "815412070123")
    sd.register_info(rs.camera_info.name, "pointfence software camera")
    sensor = sd.add_sensor("Stereo Module")
    sensor.add_read_only_option(rs.option.depth_units, UNITS)
    h, w = images[0].shape[:2]
    profile = sensor.add_video_stream(video_stream(0, w, h, 30, stream=stream, fmt=fmt, bpp=bpp,
                                                   intr=intr if intr is not None else intrinsics(w, h)))
    profile = profile.as_video_stream_profile()
    try:
        rec = rs.recorder(str(path), sd)
    except RuntimeError as e:  # an SDK before 2.56 writes ROS 1 bags
        if ".db3" not in str(e):
            raise
        path = path.with_suffix(".bag")
        rec = rs.recorder(str(path), sd)
    (rsensor,) = rec.query_sensors()
    got = rs.frame_queue(len(images) + 1)
    rsensor.open(rsensor.get_stream_profiles()[0])
    rsensor.start(got)
    try:
        for k, (img, ts) in enumerate(zip(images, stamps)):
            feed(sensor, profile, img, first_number + k, ts, bpp=bpp)
            assert got.wait_for_frame(2000)  # the recorder saw it
            if pace_s:
                time.sleep(pace_s)
    finally:
        rsensor.stop()
        rsensor.close()
        del rsensor, rec  # the recorder writes the file out when released
    return path


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    images = depth_images(len(STAMPS))
    path = record(tmp_path_factory.mktemp("rs") / "seven.db3", images, STAMPS)
    return path, images


# -- playback ------------------------------------------------------------------------------
def test_scheme_registered():
    assert "realsense" in SCHEMES


def test_playback_bit_exact(recording):
    path, images = recording
    with open_source(f"realsense:{path}", name="d435") as src:
        assert isinstance(src, RealSenseSource) and src.is_file and not src.realtime
        cam = src.camera
        assert cam.name == "d435" and (cam.width, cam.height) == (W, H)
        # the SDK keeps intrinsics and units as float32: exactly those values, nothing re-derived
        assert (cam.fx, cam.fy, cam.cx, cam.cy) == tuple(float(np.float32(K[k])) for k in ("fx", "fy", "ppx", "ppy"))
        assert cam.dist == tuple(float(np.float32(c)) for c in COEFFS)
        assert cam.depth_scale == float(np.float32(UNITS)) == src.depth_scale
        assert src.fps == 30 and src.rate_hz == 30
        frames = list(src)
        assert src.ended and src.read() is None and src.clock == "recorded"
        assert src.last_frame_number == 100 + len(STAMPS) - 1 and src.dropped == 0
    assert len(frames) == len(images)
    for k, (f, img) in enumerate(zip(frames, images)):
        assert f.seq == k and f.camera == "d435"
        assert f.depth.dtype == np.uint16 and np.array_equal(f.depth, img)  # bit for bit
        assert f.timestamp == STAMPS[k] / 1000.0  # the recorded ms, in seconds


def test_playback_repeats_identically(recording):
    """Two plays of one recording give the same frames: nothing depends on thread timing."""
    path, _ = recording
    runs = []
    for _ in range(2):
        with open_source(f"realsense:{path}") as src:
            runs.append([(f.timestamp, f.depth.tobytes()) for f in src])
    assert runs[0] == runs[1] and len(runs[0]) == len(STAMPS)


def test_loop_keeps_time_increasing(recording):
    path, images = recording
    n = len(images)
    with open_source(f"realsense:{path}?loop=true") as src:
        frames = [src.read() for _ in range(2 * n + 2)]
        assert not src.ended and src.passes == 3
    assert all(f is not None for f in frames)
    ts = np.array([f.timestamp for f in frames])
    assert np.all(np.diff(ts) > 0)
    assert ts[n] == pytest.approx(ts[n - 1] + 1 / 30, abs=1e-6)  # the next pass starts one period later
    assert ts[n + 1] - ts[n] == pytest.approx((STAMPS[1] - STAMPS[0]) / 1000, abs=1e-6)
    for k, f in enumerate(frames):
        assert np.array_equal(f.depth, images[k % n]) and f.seq == k


def test_realtime_playback_delivers_recorded_frames_and_ends(tmp_path):
    """At the recorded pace the SDK may drop frames a slow reader misses; what arrives is exact."""
    images = depth_images(6, seed=9)
    stamps = [T0_MS + k * 1000 / 30 for k in range(6)]
    path = record(tmp_path / "paced.db3", images, stamps, first_number=0, pace_s=1 / 30)
    with open_source(f"realsense:{path}", realtime=True) as src:
        assert src.realtime
        frames = []
        while not src.ended:
            f = src.read(timeout=1.0)
            if f is not None:
                frames.append((src.last_frame_number, f))
    assert frames, "real-time playback delivered nothing"
    numbers = [n for n, _ in frames]
    assert numbers == sorted(set(numbers)) and numbers[-1] <= 5
    for n, f in frames:
        assert np.array_equal(f.depth, images[n]) and f.timestamp == stamps[n] / 1000.0


def test_camera_reader_runs_a_recording_to_its_end(recording):
    path, _ = recording
    src = open_source(f"realsense:{path}", rate_hz=500)
    reader = CameraReader(src, poll=0.05).start()
    try:
        deadline = time.monotonic() + 20
        while reader.status().reason != "stream ended" and time.monotonic() < deadline:
            time.sleep(0.02)
        st = reader.status()
        assert st.frames == len(STAMPS) and st.reason == "stream ended" and st.error is None
        assert reader.latest().timestamp == STAMPS[-1] / 1000.0
    finally:
        reader.stop()


def test_scene_config_takes_intrinsics_from_the_recording(recording, tmp_path):
    from pointfence.service import config

    path, images = recording
    toml = tmp_path / "scene.toml"
    toml.write_text(textwrap.dedent(f"""
        [[camera]]
        name = "rs0"
        source = "realsense:{path}"
        z_max = 3.0
    """))
    cfg = config.load(toml)
    cam = cfg.cameras[0].camera
    assert (cam.name, cam.width, cam.fx, cam.depth_scale, cam.z_max) == ("rs0", W, float(np.float32(K["fx"])),
                                                                          float(np.float32(UNITS)), 3.0)
    (src,) = cfg.open_sources()
    try:
        assert src.camera is cam
        assert np.array_equal(src.read().depth, images[0])
    finally:
        src.close()


# -- options and errors --------------------------------------------------------------------
def test_recording_options(recording):
    path, _ = recording
    with open_source(f"realsense:{path}?width={W}&height={H}&fps=30") as src:
        assert (src.camera.width, src.camera.height) == (W, H)
    with pytest.raises(InputError, match=rf"no depth stream 848x480@\*; it offers {W}x{H}@30"):
        open_source(f"realsense:{path}?width=848&height=480")
    with pytest.raises(InputError, match="preset .* applies to a camera"):
        open_source(f"realsense:{path}?preset=high_accuracy")
    with pytest.raises(InputError, match="unknown option.*colour.*it accepts"):
        open_source(f"realsense:{path}", colour=True)
    with pytest.raises(InputError, match="timeout"):
        open_source(f"realsense:{path}?timeout=0")
    with pytest.raises(InputError, match="loop = 'yes please'"):
        open_source(f"realsense:{path}", loop="yes please")
    with pytest.raises(InputError, match=f"depth stream is {W}x{H} but camera 'c' is 640x480"):
        open_source(f"realsense:{path}", Camera("c", 640, 480, 500, 500, 320, 240, depth_scale=UNITS))
    with pytest.raises(InputError, match="depth_scale = 0.001"):
        open_source(f"realsense:{path}", Camera("c", W, H, 50, 50, 32, 24, depth_scale=0.001))
    given = Camera("c", W, H, 50, 50, 32, 24, depth_scale=float(np.float32(UNITS)))
    with open_source(f"realsense:{path}", given) as src:
        assert src.camera is given and src.read().depth.shape == (H, W)


def test_bad_paths_and_foreign_files(tmp_path):
    with pytest.raises(InputError, match="recording .*missing.db3.* not found"):
        open_source(f"realsense:{tmp_path / 'missing.db3'}")
    with pytest.raises(InputError, match="is a folder"):
        open_source(f"realsense:{tmp_path}")
    text = tmp_path / "notes.bag"
    text.write_text("not a bag\n" * 20)
    noise = tmp_path / "noise.db3"
    noise.write_bytes(np.random.default_rng(1).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    other = tmp_path / "other.db3"  # a SQLite file, but no ROS 2 bag of the SDK's
    con = sqlite3.connect(other)
    con.execute("create table frames (x)")
    con.commit()
    con.close()
    for f in (text, noise, other):
        with pytest.raises(InputError, match="is not a RealSense recording the SDK can play"):
            open_source(f"realsense:{f}")


def test_recording_without_depth_stream(tmp_path):
    rgb = [np.full((H, W, 3), k, np.uint8) for k in range(2)]
    path = record(tmp_path / "color.db3", rgb, STAMPS[:2], stream=rs.stream.color, fmt=rs.format.rgb8, bpp=3)
    with pytest.raises(InputError, match=rf"no depth \(Z16\) stream; it has Color {W}x{H}@30 RGB8"):
        open_source(f"realsense:{path}")


def test_distortion_models(tmp_path):
    img = depth_images(1)
    inv = intrinsics(model=rs.distortion.inverse_brown_conrady)
    path = record(tmp_path / "inverse.db3", img, STAMPS[:1], intr=inv)
    with pytest.raises(InputError, match="lens model is inverse_brown_conrady.*calib intrinsics"):
        open_source(f"realsense:{path}")
    with open_source(f"realsense:{path}", dist=(0.0, 0.0, 0.0, 0.0, 0.0)) as src:  # calibrated elsewhere
        assert src.camera.dist == (0.0,) * 5
    plain = record(tmp_path / "plain.db3", img, STAMPS[:1], intr=intrinsics(model=rs.distortion.modified_brown_conrady,
                                                                             coeffs=[0] * 5))
    with open_source(f"realsense:{plain}") as src:
        assert src.camera.dist == (0.0,) * 5


def test_no_camera_with_that_serial():
    try:
        attached = list(rs.context().query_devices())
    except RuntimeError:
        attached = []
    with pytest.raises(InputError, match="cameras attached") as e:
        open_source("realsense:000000000000")
    if not attached:
        assert "(cameras attached: none)" in str(e.value)


# -- a software device as the live camera --------------------------------------------------
def test_live_modes_presets_and_global_time():
    sd, sensor, profiles = software_camera(modes=((W, H, 30), (W, H, 15), (32, 24, 30)))
    src = open_source("realsense:", device=sd, width=W, height=H, fps=15, preset="high_accuracy", name="live")
    try:
        assert not src.is_file and src.realtime and src.global_time and src.preset == "high_accuracy"
        assert sensor.get_option(rs.option.visual_preset) == int(rs.rs400_visual_preset.high_accuracy)
        assert sensor.get_option(rs.option.global_time_enabled) == 1
        assert src.fps == 15 and src.camera.depth_scale == float(np.float32(UNITS))
        images = depth_images(3, seed=11)
        got = []
        for k, img in enumerate(images):
            fed_mono = time.monotonic()
            feed(sensor, profiles[1], img, k, time.time() * 1000.0)  # global time: the host's system clock, ms
            f = src.read(timeout=2.0)
            got.append((f, fed_mono))
        for k, (f, fed_mono) in enumerate(got):
            assert np.array_equal(f.depth, images[k])
            # mapped onto time.monotonic: without the mapping it would be ~1.7e9 s off
            assert abs(f.timestamp - fed_mono) < 0.25
        assert src.clock == "host-monotonic" and src.last_domain == "global_time"
        feed(sensor, profiles[1], images[0], 9, 123456.5, domain=rs.timestamp_domain.hardware_clock)
        f = src.read(timeout=2.0)
        assert f.timestamp == 123.4565 and src.clock == "device"
    finally:
        src.close()
    assert src.closed
    with pytest.raises(InputError, match="is closed"):
        src.read()


def test_live_keeps_the_newest_frame():
    sd, sensor, (profile,) = software_camera()
    images = depth_images(5, seed=3)
    with open_source("realsense:", device=sd) as src:
        for k, img in enumerate(images):
            feed(sensor, profile, img, k, T0_MS + k * 33.3, domain=rs.timestamp_domain.hardware_clock)
        deadline = time.monotonic() + 5
        while src.dropped < 4 and time.monotonic() < deadline:
            time.sleep(0.01)
        f = src.read(timeout=1.0)
        assert src.dropped == 4 and np.array_equal(f.depth, images[-1]) and src.last_frame_number == 4
        assert src.read(timeout=0.05) is None and not src.ended  # a camera waits for its next frame


def test_live_option_errors():
    sd, _, _ = software_camera(modes=((W, H, 30), (W, H, 15)))
    with pytest.raises(InputError, match=r"preset = 'sharpest'; this camera offers custom, default, hand, high_accuracy"):
        open_source("realsense:", device=sd, preset="sharpest")
    with pytest.raises(InputError, match=rf"no depth stream \*x\*@60; it offers {W}x{H}@15, {W}x{H}@30"):
        open_source("realsense:", device=sd, fps=60)
    with pytest.raises(InputError, match="expected a pyrealsense2 device"):
        open_source("realsense:?device=cam1")
    with pytest.raises(InputError, match="loop applies to recordings"):
        open_source("realsense:", device=sd, loop=True)
    bare, _, _ = software_camera(presets=False, global_time=False)
    with pytest.raises(InputError, match="no visual presets"):
        open_source("realsense:", device=bare, preset="default")
    with open_source("realsense:", device=bare) as src:  # no global time: the device's clock, said so
        assert not src.global_time and src.clock == "device"


def test_handoff_close_releases_a_waiting_callback():
    """A full keep-all handoff makes the SDK's callback wait; closing releases it at once."""
    h = FrameHandoff(keep_all=True, capacity=2)
    h.push(1)
    h.push(2)
    done = threading.Event()
    t = threading.Thread(target=lambda: (h.push(3), done.set()), daemon=True)
    t.start()
    assert not done.wait(0.2)  # waits for room: the playback waits for the reader
    assert h.pop(0) == 1 and done.wait(2.0)  # room made: the frame goes in, none dropped
    assert [h.pop(0), h.pop(0), h.pop(0)] == [2, 3, None] and h.dropped == 0
    h.push(4)
    h.push(5)
    t = threading.Thread(target=h.push, args=(6,), daemon=True)
    t.start()
    h.close()
    t.join(2.0)
    assert not t.is_alive() and h.dropped == 1


def test_closing_mid_play_never_aborts_the_process(recording):
    """librealsense 2.59 corrupts the heap or aborts ("pure virtual method called", "malloc_consolidate():
    unaligned fastbin chunk") now and then when a playback is destroyed while playing, or while the
    sensor's stop and close are still queued on its reading thread. The source pauses the playback
    before stopping it and waits for that thread after closing the sensor. Without the wait, this loop
    (in its own process, so an abort fails the test instead of pytest) died in 8 of 15 runs on a 2-core
    VM; with it, in none of 15 (nor in 90 runs of a 40-pass form). Passes are closed before their first frame, after one or
    two, and, looping, after the recording restarted (9 reads of its 7 frames)."""
    import subprocess
    import sys

    path, _ = recording
    code = textwrap.dedent(f"""
        from pointfence.service.sources import open_source
        for i in range(80):
            with open_source("realsense:" + {str(path)!r}, loop=bool(i % 2)) as src:
                for _ in range((0, 1, 2, 9)[(i // 2) % 4]):
                    src.read()
        print("closed 80")
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and "closed 80" in proc.stdout, proc.stderr[-2000:]
