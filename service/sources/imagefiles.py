"""Reading single depth and colour images: 16-bit PNG / TIFF (through Pillow) and PCLZF.

Depth images come back as uint16 (H, W) in the file's units (millimetres for every recording
in ../shared/data); colour images as uint8 RGB (H, W, 3).
"""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from pointfence.kernels.errors import InputError

from .filecaps import MAX_POINTS, MAX_SIDE, check_count, check_data_size, read_capped
from .lzf import lzf_decompress

_16BIT_MODES = {"I;16", "I;16L", "I;16B", "I;16N", "I"}


def read_depth_image(path) -> np.ndarray:
    """A 16-bit single-channel depth image (.png, .tif/.tiff, .pclzf) as uint16 (H, W)."""
    path = Path(path)
    if path.suffix.lower() == ".pclzf":
        return read_pclzf_depth(path)
    try:
        with Image.open(path) as im:
            mode = im.mode
            if mode not in _16BIT_MODES:
                raise InputError(
                    f"{path}: image mode {mode!r} ({'8-bit' if mode in ('L', 'P', '1') else 'colour or float'}); "
                    "expected a 16-bit single-channel depth image (PNG or TIFF, mode I;16)"
                )
            arr = np.array(im)
    except FileNotFoundError:
        raise InputError(f"{path}: no such file; expected a 16-bit depth image") from None
    except (UnidentifiedImageError, OSError, SyntaxError) as e:
        raise InputError(f"{path}: cannot decode ({e}); expected a readable 16-bit PNG or TIFF depth image") from None
    if arr.ndim != 2:
        raise InputError(f"{path}: array shape {arr.shape}; expected a single-channel (H, W) depth image")
    if arr.dtype != np.uint16:
        if arr.size and (arr.min() < 0 or arr.max() > 65535):
            raise InputError(f"{path}: values {arr.min()}..{arr.max()}; expected 16-bit depth codes 0..65535")
        arr = arr.astype(np.uint16)
    return arr


def read_color_image(path) -> np.ndarray:
    """An 8-bit colour image as uint8 RGB (H, W, 3)."""
    path = Path(path)
    try:
        with Image.open(path) as im:
            return np.array(im.convert("RGB"))
    except FileNotFoundError:
        raise InputError(f"{path}: no such file; expected a colour image") from None
    except (UnidentifiedImageError, OSError, SyntaxError) as e:
        raise InputError(f"{path}: cannot decode ({e}); expected a readable colour image") from None


def read_pclzf_depth(path) -> np.ndarray:
    """PCL's LZF depth image (pcl::io::LZFDepth16ImageWriter): "PCLZF", uint32 width, height,
    16-byte type ("depth16"), uint32 compressed and uncompressed sizes, then the LZF block of
    little-endian uint16 pixels, row-major. The sizes are checked against the file's size and
    the caps of ``filecaps`` before the image is allocated."""
    path = Path(path)
    raw = read_capped(path, "a .pclzf depth file")
    if len(raw) < 37 or raw[:5] != b"PCLZF":
        raise InputError(f"{path}: no PCLZF header; expected a file written by PCL's LZFDepth16ImageWriter")
    width, height = struct.unpack_from("<II", raw, 5)
    kind = raw[13:29].decode("ascii", "replace").strip("\0 ")
    csize, usize = struct.unpack_from("<II", raw, 29)
    if kind != "depth16" or usize != width * height * 2:
        raise InputError(f"{path}: PCLZF image type {kind!r}, {width}x{height}, {usize} bytes; expected 'depth16' with 2 bytes per pixel")
    check_count(path, "width", width, MAX_SIDE)
    check_count(path, "height", height, MAX_SIDE)
    check_count(path, "width*height", width * height, MAX_POINTS)
    check_data_size(path, "compressed size", csize, len(raw) - 37)
    data = lzf_decompress(raw[37:37 + csize], usize, str(path))  # refuses usize beyond what csize can give
    return np.frombuffer(data, "<u2").reshape(height, width).astype(np.uint16)
