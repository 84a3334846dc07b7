"""Reading a pointfence MCAP recording (``mcap_record``), whole or cut short by a crash.

``open_recording(path)`` reads the file record by record (``mcap_scan.scan``: chunk and data
section CRCs checked, as ``mcap``'s ``StreamReader`` checks them), so a file that ``kill -9``
cut short, which has no summary section, reads up to its last whole chunk (``Recording.torn``:
it ended early). What it returns:

* ``meta``: the ``pointfence/run`` metadata (arms, rate, epoch, cameras, configuration text,
  start state, architecture, backend, ...);
* ``metadata``: every metadata record by name -> {key: value} (JSON values decoded; the newest
  value of a key where a name has several records): ``pointfence/run`` (= ``meta``),
  ``pointfence/end`` (the service died and the writer closed the file), and what callers added
  with ``McapRecorder.add_metadata`` (e.g. end-of-run measures);
* ``rows``: every recorded tick as ``tick_cdr`` ring rows (N, width), in tick order;
* ``snapshots``: snapshot seq -> (frame seq per camera, recorded frame numbers, capture stamps,
  per-frame poses);
* ``frame(camera, index, ...)``: a recorded frame as a ``kernels.frame.DepthFrame`` (decoded on
  demand).

A file that is not an MCAP, not a pointfence recording, or damaged before anything readable
is an ``InputError`` naming the file and what is wrong.
"""
from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError

from pointfence.kernels.errors import InputError
from pointfence.kernels.frame import DepthFrame

from . import depth_png
from .cdr import IMAGE_ENCODINGS
from .mcap_record import FORMAT
from .mcap_scan import scan
from .ros2.cdr import CdrError, decode_compressed_image, decode_image
from .ros2_schemas import SNAPSHOTS, TICK_INPUT, TICK_OUTPUT
from .tick_cdr import TickLayout


class Recording:
    def __init__(self, path, meta, rows, snapshots, images, torn, messages, metadata=None):
        self.path, self.meta, self.rows, self.snapshots = path, meta, rows, snapshots
        self.metadata = metadata if metadata is not None else {"pointfence/run": meta}
        self._images = images              # (camera, kind, frame seq) -> ("raw" | "png", the message's CDR)
        self.torn = torn                   # None, or why the file ends early
        self.messages = messages
        self.layout = TickLayout(int(meta["arms"]))
        # (a camera's model is recorded with its first frame; until then, its name alone)
        self.cameras = [c["name"] if isinstance(c, dict) else str(c) for c in meta.get("cameras", [])]

    def frame(self, cam_index: int, index: int, seq: int, stamp: float, pose=None) -> DepthFrame:
        """Camera ``cam_index``'s recorded frame number ``index`` (its running number in the file),
        as a frame of source number ``seq`` captured at ``stamp`` (s) with pose ``pose`` (16
        numbers, NaN: the camera's own). Raises InputError if it is not in the file."""
        name = self.cameras[cam_index]
        key = (name, "depth", int(index))
        if key not in self._images:
            raise InputError(f"{self.path}: frame {seq} of camera {name!r} (recorded frame {index}) is not in the "
                             "recording (dropped while recording, or after the point where the file ends)")
        where = f"{self.path}: camera {name!r} frame {seq}"
        depth = _pixels(self._images[key], "depth", where)
        color = self._images.get((name, "color", int(index)))
        mask = self._images.get((name, "mask", int(index)))
        T = None if pose is None or len(pose) < 16 or math.isnan(pose[0]) else np.array(pose, float).reshape(4, 4)
        return DepthFrame(camera=name, depth=depth, timestamp=float(stamp), seq=int(seq),
                          color=None if color is None else _pixels(color, "color", where),
                          mask=None if mask is None else _pixels(mask, "mask", where), T_world_cam=T)


#: a raw image's encoding by kind (the writer's ``cdr.raw_image``), and each encoding's dtype and channels
_RAW = {"depth": "16UC1", "color": "rgb8", "mask": "mono8"}
_PIXELS = {enc: key for key, enc in IMAGE_ENCODINGS.items()}


def _pixels(image: tuple, kind: str, where: str) -> np.ndarray:
    """The pixels of a recorded image (``_take``'s entry): a raw ``sensor_msgs/Image`` (this
    recorder's) or a PNG ``CompressedImage`` (recordings made before raw images)."""
    form, data = image
    try:
        img = decode_image(data) if form == "raw" else decode_compressed_image(data)
    except CdrError as e:
        raise InputError(f"{where}: a damaged {kind} image ({e})") from None
    if form == "png":
        if kind == "depth":
            return depth_png.decode_depth(bytes(img.data), img.format, where)
        return depth_png.decode_png(bytes(img.data), 3 if kind == "color" else 1, where)
    enc = _RAW[kind]
    dtype, channels = _PIXELS[enc]
    row = img.width * channels * dtype.itemsize
    if img.encoding != enc or img.is_bigendian or img.step != row or len(img.data) != row * img.height:
        raise InputError(f"{where}: {kind} image {img.width}x{img.height} {img.encoding!r} (big-endian "
                         f"{bool(img.is_bigendian)}, step {img.step}, {len(img.data)} bytes); expected {enc!r}, "
                         f"little-endian, {row} bytes a row")
    shape = (img.height, img.width) + ((channels,) if channels > 1 else ())
    return np.frombuffer(img.data, dtype).reshape(shape).copy()


def _decode_snapshot(data: bytes):
    """(seq, (frame seqs, frame indices, stamps, poses)) of a ``pointfence_msgs/Snapshot`` message."""
    from mcap_ros2._dynamic import generate_dynamic

    from .ros2_schemas import msgdef

    dec = _DEC.get("snap")
    if dec is None:
        dec = _DEC["snap"] = generate_dynamic("pointfence_msgs/Snapshot", msgdef("pointfence_msgs/Snapshot"))
        dec = _DEC["snap"] = dec["pointfence_msgs/Snapshot"]
    m = dec(data)
    return int(m.seq), (list(m.frame_seq), list(m.frame_index), list(m.frame_stamp), list(m.t_world_cam))


_DEC: dict = {}


def open_recording(path) -> Recording:
    """Read a recording; see the module docstring."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"recording {str(p)!r} not found; expected an .mcap file that `pointfence serve --record` or "
                         "`demo --record` wrote")
    with p.open("rb") as fh:
        head = fh.read(8)
        if head != b"\x89MCAP0\r\n":
            raise InputError(f"{p}: not an MCAP file (its first bytes are {head!r}, expected b'\\x89MCAP0\\r\\n')")
        fh.seek(0)
        channels: dict = {}
        metadata: dict = {"pointfence/run": {}}
        meta = metadata["pointfence/run"]
        ticks = {"in": [], "out": []}
        snapshots: dict = {}
        images: dict = {}
        torn = None
        count = 0
        try:
            for rec in scan(fh):
                if rec[0] == "message":
                    count += 1
                    _take(channels.get(rec[1], ""), rec[2], rec[3], ticks, snapshots, images)
                elif rec[0] == "channel":
                    channels[rec[1]] = rec[2]
                else:
                    metadata.setdefault(rec[1].name, {}).update(_decode_metadata(rec[1]))
        except (McapError, struct.error, ValueError, EOFError, OSError, Exception) as e:   # noqa: BLE001
            # a torn or damaged tail: everything before it is kept (S8)
            torn = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
    if meta.get("format") != FORMAT:
        raise InputError(f"{p}: not a pointfence recording (no 'pointfence/run' metadata with format {FORMAT!r}"
                         + (f"; the file is damaged near its start: {torn}" if torn else "") + ")")
    try:
        rows = _tick_rows(TickLayout(int(meta["arms"])), ticks)
    except ValueError as e:
        raise InputError(f"{p}: {e} (a damaged recording, or one of another pointfence version)") from None
    return Recording(p, meta, rows, snapshots, images, torn, count, metadata)


def _decode_metadata(rec) -> dict:
    """A metadata record's map with its JSON values decoded (a value that is not JSON, written by
    another tool, is kept as its text)."""
    out = {}
    for k, v in rec.metadata.items():
        try:
            out[k] = json.loads(v)
        except ValueError:
            out[k] = v
    return out


def _tick_rows(lay: TickLayout, ticks: dict) -> np.ndarray:
    """Ring rows of the ticks whose input and output are both in the file, in tick order."""
    parts = {}
    for part in ("in", "out"):
        r = np.zeros((len(ticks[part]), lay.width))
        lay.decode(part, ticks[part], r)
        parts[part] = r
    kin, kout = (parts[p][:, lay.cols[(p, "k")][0]] for p in ("in", "out"))
    common, i_in, i_out = np.intersect1d(kin, kout, return_indices=True)
    rows = parts["in"][i_in]
    for name in lay.names("out"):
        c, k = lay.cols[("out", name)]
        rows[:, c: c + k] = parts["out"][i_out, c: c + k]
    return rows


def _take(topic: str, sequence: int, data: bytes, ticks: dict, snapshots: dict, images: dict) -> None:
    """One message (its MCAP sequence number and CDR bytes) into the reader's tables, by topic."""
    if topic in (TICK_INPUT, TICK_OUTPUT):
        ticks["in" if topic == TICK_INPUT else "out"].append(data)
    elif topic == SNAPSHOTS:
        seq, entry = _decode_snapshot(data)
        snapshots[seq] = entry
    elif topic.endswith(("/image_raw", "/compressed")):
        parts = topic.strip("/").split("/")
        if len(parts) == 3:          # /<camera>/<depth|color|mask>/<image_raw|compressed>; sequence: the frame's number
            images[(parts[0], parts[1], int(sequence))] = ("raw" if parts[2] == "image_raw" else "png", data)


__all__ = ["open_recording", "Recording"]
