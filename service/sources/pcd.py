"""Organised PCD files (Point Cloud Library) as depth images.

Reads PCD v0.7 files with DATA ascii, binary or binary_compressed (LZF, fields stored one
after another), fields x y z in metres in the sensor frame (z forward) and optionally rgb or
rgba (packed 0xAARRGGBB). An organised cloud (HEIGHT > 1) maps point (row, col) to pixel
(v, u); the depth image is z rounded to ``depth_scale`` units, 0 where z is NaN or <= 0.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from pointfence.kernels.errors import InputError

from .filecaps import MAX_COUNT, MAX_POINTS, MAX_SIDE, check_count, check_data_size, read_capped
from .lzf import lzf_decompress

_TYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("U", 1): "u1", ("U", 2): "<u2", ("U", 4): "<u4",
          ("I", 1): "i1", ("I", 2): "<i2", ("I", 4): "<i4", ("U", 8): "<u8", ("I", 8): "<i8"}


@dataclass
class PcdCloud:
    """An organised cloud: xyz (H, W, 3) float32 metres (NaN = no data), rgb (H, W, 3) uint8 or
    None, viewpoint: the header's VIEWPOINT (tx ty tz qw qx qy qz) as written. It is kept for
    reference only: writers disagree on it (PCL's grabber files say "0 0 0 0 1 0 0"), so the
    points are taken to be in the camera frame, as an organised cloud's pixels are."""

    xyz: np.ndarray
    rgb: Optional[np.ndarray]
    viewpoint: tuple


def _header(raw: bytes, path: Path) -> tuple[dict, int]:
    head, pos = {}, 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise InputError(f"{path}: PCD header has no DATA line; expected a PCD v0.7 file")
        line = raw[pos:end].decode("ascii", "replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        head[key.upper()] = vals
        if key.upper() == "DATA":
            return head, pos


def _int(head: dict, key: str, path: Path, i: int = 0) -> int:
    """Header field ``key`` (its ``i``-th value) as an integer; InputError naming it otherwise."""
    vals = head.get(key)
    if not vals or len(vals) <= i:
        raise InputError(f"{path}: PCD header has no {key} value; expected FIELDS, SIZE, TYPE, WIDTH, HEIGHT, DATA")
    try:
        return int(vals[i])
    except ValueError:
        raise InputError(f"{path}: header field {key} = {vals[i]!r}; expected an integer") from None


def _layout(head: dict, path: Path) -> tuple[list, list, list, int, int]:
    """(names, dtypes, counts, width, height) of the header, every size checked against the caps."""
    names = head.get("FIELDS")
    if not names:
        raise InputError(f"{path}: PCD header has no FIELDS; expected FIELDS, SIZE, TYPE, WIDTH, HEIGHT, DATA")
    n = len(names)
    types = head.get("TYPE", [])
    for key, vals in (("SIZE", head.get("SIZE", [])), ("TYPE", types), ("COUNT", head.get("COUNT", names))):
        if len(vals) != n:
            raise InputError(f"{path}: header field {key} has {len(vals)} values for {n} FIELDS {names}; expected one each")
    sizes = [_int(head, "SIZE", path, i) for i in range(n)]
    counts = [_int(head, "COUNT", path, i) for i in range(n)] if "COUNT" in head else [1] * n
    for c in counts:
        check_count(path, "COUNT", c, MAX_COUNT)
    try:
        dtypes = [np.dtype(_TYPES[(t.upper(), s)]) for t, s in zip(types, sizes)]
    except KeyError as e:
        raise InputError(f"{path}: header field TYPE/SIZE {e.args[0]}; expected F 4|8, U or I 1|2|4|8") from None
    width = check_count(path, "WIDTH", _int(head, "WIDTH", path), MAX_SIDE)
    height = _int(head, "HEIGHT", path)
    if height <= 1:
        raise InputError(f"{path}: unorganised cloud (HEIGHT = {height}); expected an organised cloud (HEIGHT > 1) to make a depth image")
    check_count(path, "HEIGHT", height, MAX_SIDE)
    check_count(path, "WIDTH*HEIGHT", width * height, MAX_POINTS)
    if "POINTS" in head and _int(head, "POINTS", path) != width * height:
        raise InputError(f"{path}: header field POINTS = {head['POINTS'][0]} but WIDTH*HEIGHT = {width * height}; "
                         "expected them equal (a corrupt header)")
    return names, dtypes, counts, width, height


def read_pcd(path) -> PcdCloud:
    """Read an organised PCD file; InputError naming the file when it is not one.

    Every size in the header is checked against the caps of ``filecaps`` and against the bytes
    the file holds before any array is allocated."""
    path = Path(path)
    raw = read_capped(path, "a readable .pcd file")
    head, pos = _header(raw, path)
    names, dtypes, counts, width, height = _layout(head, path)
    if not {"x", "y", "z"} <= set(names):
        raise InputError(f"{path}: fields {names}; expected x, y, z")
    npts, mode = width * height, head["DATA"][0].lower() if head["DATA"] else ""
    record = sum(dt.itemsize * c for dt, c in zip(dtypes, counts))
    have = len(raw) - pos
    fields = {}
    if mode == "binary_compressed":
        check_data_size(path, "DATA binary_compressed (sizes)", 8, have)
        csize, usize = (int(v) for v in np.frombuffer(raw, "<u4", 2, pos))
        check_data_size(path, "DATA binary_compressed (compressed size)", csize, have - 8)
        if usize != npts * record:
            raise InputError(f"{path}: uncompressed size {usize} bytes; WIDTH*HEIGHT*record = {npts}*{record} = "
                             f"{npts * record} bytes (a corrupt header)")
        data = lzf_decompress(raw[pos + 8:pos + 8 + csize], usize, f"{path}")
        off = 0
        for name, dt, c in zip(names, dtypes, counts):  # field-major: all x, then all y, ...
            fields[name] = np.frombuffer(data, dt, npts * c, off).reshape(npts, c)[:, 0]
            off += npts * c * dt.itemsize
    elif mode == "binary":
        check_data_size(path, f"WIDTH*HEIGHT = {npts} points of {record} bytes", npts * record, have)
        rec = np.dtype([(f"{n}_{k}", dt) for n, dt, c in zip(names, dtypes, counts) for k in range(c)])
        arr = np.frombuffer(raw, rec, npts, pos)
        fields = {n: arr[f"{n}_0"] for n in names}
    elif mode == "ascii":
        lines = raw[pos:].decode("ascii", "replace").splitlines()
        n_lines = sum(1 for ln in lines if ln.strip())
        if n_lines != npts:
            raise InputError(f"{path}: {n_lines} data lines; WIDTH*HEIGHT = {npts} (truncated or corrupt file)")
        try:
            table = np.loadtxt(lines, dtype=np.float64, ndmin=2)
        except ValueError as e:
            raise InputError(f"{path}: ascii data unreadable ({e}); expected {sum(counts)} numbers a line") from None
        if table.shape != (npts, sum(counts)):
            raise InputError(f"{path}: ascii data {table.shape[0]}x{table.shape[1]}; expected {npts} lines of "
                             f"{sum(counts)} numbers")
        col = 0
        for name, dt, c in zip(names, dtypes, counts):
            fields[name] = table[:, col].astype(dt)
            col += c
    else:
        raise InputError(f"{path}: DATA {mode}; expected ascii, binary or binary_compressed")
    xyz = np.stack([fields[k].astype(np.float32) for k in "xyz"], axis=-1).reshape(height, width, 3)
    rgb = None
    key = "rgba" if "rgba" in fields else "rgb" if "rgb" in fields else None
    if key is not None and fields[key].dtype.itemsize == 4:
        packed = np.ascontiguousarray(fields[key]).view(np.uint32).reshape(height, width)
        rgb = np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], axis=-1).astype(np.uint8)
    try:
        vp = tuple(float(v) for v in head.get("VIEWPOINT", [0, 0, 0, 1, 0, 0, 0]))
    except ValueError:
        raise InputError(f"{path}: header field VIEWPOINT = {head['VIEWPOINT']}; expected 7 numbers") from None
    return PcdCloud(xyz, rgb, vp)


def depth_from_cloud(cloud: PcdCloud, depth_scale: float = 0.001) -> np.ndarray:
    """uint16 depth image (H, W) in ``depth_scale`` m units from an organised cloud; 0 = no data."""
    z = cloud.xyz[..., 2].astype(np.float64)
    ok = np.isfinite(z) & (z > 0)
    code = np.round(np.where(ok, z, 0.0) / depth_scale)
    return np.where(ok & (code <= 65535), code, 0).astype(np.uint16)


def fit_intrinsics(cloud: PcdCloud) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) by least squares on u = fx x/z + cx, v = fy y/z + cy over valid points."""
    h, w, _ = cloud.xyz.shape
    x, y, z = (cloud.xyz[..., k].astype(np.float64) for k in range(3))
    ok = np.isfinite(z) & (z > 0) & np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 10:
        raise InputError("organised cloud has fewer than 10 valid points; cannot fit intrinsics: give fx, fy, cx, cy")
    v, u = np.nonzero(ok)
    (fx, cx), *_ = np.linalg.lstsq(np.stack([x[ok] / z[ok], np.ones(ok.sum())], 1), u.astype(np.float64), rcond=None)
    (fy, cy), *_ = np.linalg.lstsq(np.stack([y[ok] / z[ok], np.ones(ok.sum())], 1), v.astype(np.float64), rcond=None)
    # Rounded to 1e-4 px: the fit is exact to float32 precision on clean organised clouds.
    return tuple(round(float(k), 4) for k in (fx, fy, cx, cy))

