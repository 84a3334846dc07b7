"""Lossless image payloads of ``sensor_msgs/CompressedImage`` messages.

Depth is ROS's ``compressedDepth`` form, as ``compressed_depth_image_transport`` writes a
16UC1 image (github.com/ros-perception/image_transport_plugins, ``codec.cpp``
``encodeCompressedDepthImage``): format ``"16UC1; compressedDepth png"``, the data a 12-byte
``ConfigHeader`` {int32 format (INV_DEPTH = 0), float32 depthQuantA, depthQuantB (0 for 16UC1:
not quantised)} then a 16-bit grey PNG of the raw depth codes (the camera's units: metres =
code x ``depth_scale``, in the camera's ``CameraInfo``). Unlike ROS's encoder nothing beyond a
maximum depth is zeroed: the codes are kept exactly. Colour is a plain ``png`` (RGB, written
as OpenCV's BGR PNG), a selection mask a grey ``png``.

``decode_compressed_depth`` reads what ROS drivers publish in that form: 16UC1 (the PNG holds
the depth in mm) and 32FC1 (the PNG holds quantised inverse depth ``v``, depth in m =
``depthQuantA / (v - depthQuantB)``, 0 = no reading, as ``decodeCompressedDepthImage``).
"""
from __future__ import annotations

import struct

import cv2
import numpy as np

from pointfence.kernels.errors import InputError

DEPTH_FORMAT = "16UC1; compressedDepth png"
INV_DEPTH = 0
_CONFIG = struct.Struct("<iff")
#: PNG zlib level: 1 is 3-4x faster than OpenCV's default 3 for a few per cent more bytes
PNG_LEVEL = 1
#: no PNG row filter: libpng's adaptive choice (OpenCV's default) tries every filter on every row,
#: and at zlib level 1 the filtered rows of depth codes compress no better than the raw ones
#: (the option exists from OpenCV 4.10; older ones keep their default)
_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, PNG_LEVEL] + (
    [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE] if hasattr(cv2, "IMWRITE_PNG_FILTER") else [])


def _png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img, _PARAMS)
    if not ok:
        raise InputError(f"PNG encoding of a {img.dtype} {img.shape} image failed")
    return buf.tobytes()


def encode_depth(depth: np.ndarray) -> bytes:
    """``compressedDepth`` data of a uint16 (H, W) depth image."""
    if depth.dtype != np.uint16 or depth.ndim != 2:
        raise InputError(f"depth image {depth.dtype} {depth.shape}; expected uint16 (H, W)")
    return _CONFIG.pack(INV_DEPTH, 0.0, 0.0) + _png(depth)


def decode_depth(data: bytes, fmt: str, where: str) -> np.ndarray:
    """The uint16 (H, W) depth codes of a ``compressedDepth`` message (``where`` names it in errors)."""
    if "compressedDepth" not in fmt or not fmt.startswith("16UC1"):
        raise InputError(f"{where}: depth format {fmt!r}; expected {DEPTH_FORMAT!r} (16-bit raw depth)")
    if len(data) <= _CONFIG.size:
        raise InputError(f"{where}: compressedDepth data of {len(data)} bytes; expected a 12-byte header and a PNG")
    img = cv2.imdecode(np.frombuffer(data, np.uint8, offset=_CONFIG.size), cv2.IMREAD_UNCHANGED)
    if img is None or img.dtype != np.uint16 or img.ndim != 2:
        raise InputError(f"{where}: the depth PNG does not decode to a 16-bit grey image (a damaged recording)")
    return img


def decode_compressed_depth(data: bytes, fmt: str, where: str) -> tuple:
    """(encoding, image) of a ROS ``compressedDepth`` payload (``where`` names it in errors):
    ("16UC1", uint16 (H, W) mm) or ("32FC1", float32 (H, W) m with NaN where there is no reading).
    A damaged, truncated or foreign payload is an ``InputError``."""
    enc, _, rest = str(fmt).partition(";")
    enc, rest = enc.strip(), rest.strip()
    if enc not in ("16UC1", "32FC1") or not rest.startswith("compressedDepth") or rest not in ("compressedDepth", "compressedDepth png"):
        raise InputError(f"{where}: CompressedImage format {fmt!r}; expected '16UC1; compressedDepth png' or "
                         "'32FC1; compressedDepth png' (the PNG form of compressed_depth_image_transport; RVL is not read)")
    if len(data) <= _CONFIG.size:
        raise InputError(f"{where}: compressedDepth data of {len(data)} bytes; expected a 12-byte ConfigHeader and a PNG")
    kind, quant_a, quant_b = _CONFIG.unpack_from(data)
    if kind != INV_DEPTH:
        raise InputError(f"{where}: compressedDepth ConfigHeader format {kind}; expected {INV_DEPTH} (INV_DEPTH)")
    png = np.frombuffer(data, np.uint8, offset=_CONFIG.size)
    if png.size < 8 or png[:8].tobytes() != b"\x89PNG\r\n\x1a\n":
        raise InputError(f"{where}: compressedDepth payload after the 12-byte header is not a PNG")
    img = cv2.imdecode(png, cv2.IMREAD_UNCHANGED)
    if img is None or img.dtype != np.uint16 or img.ndim != 2:
        raise InputError(f"{where}: the compressedDepth PNG ({png.size} bytes) does not decode to a 16-bit grey image "
                         "(truncated or damaged in transit)")
    if enc == "16UC1":
        return enc, img
    if not (np.isfinite(quant_a) and np.isfinite(quant_b) and quant_a != 0):
        raise InputError(f"{where}: 32FC1 compressedDepth with depthQuantA = {quant_a}, depthQuantB = {quant_b}; expected finite, A != 0")
    with np.errstate(divide="ignore", invalid="ignore"):
        m = np.float32(quant_a) / (img.astype(np.float32) - np.float32(quant_b))
    return enc, np.where(img > 0, m, np.float32(np.nan)).astype(np.float32)


def encode_color(rgb: np.ndarray) -> bytes:
    """PNG data of a uint8 (H, W, 3) RGB image (stored as OpenCV's BGR PNG)."""
    return _png(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def encode_mask(mask: np.ndarray) -> bytes:
    return _png(np.ascontiguousarray(mask, dtype=np.uint8))


def decode_png(data: bytes, channels: int, where: str) -> np.ndarray:
    """An 8-bit PNG: RGB (H, W, 3) for ``channels`` 3, grey (H, W) for 1."""
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.dtype != np.uint8 or (img.ndim == 3) != (channels == 3):
        raise InputError(f"{where}: the PNG does not decode to an 8-bit {'RGB' if channels == 3 else 'grey'} image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if channels == 3 else img


__all__ = ["DEPTH_FORMAT", "encode_depth", "decode_depth", "decode_compressed_depth", "encode_color", "encode_mask", "decode_png"]
