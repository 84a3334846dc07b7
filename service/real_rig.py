"""A real two-camera rig from a recorded sequence with camera poses (dissertation 6.4 on real
frames): two viewpoints of one static scene, the protected point both see, a tool's depth
rendered into the real depth images, and the fused surface that safety is measured against.

Frames: world = the recording's pose frame (7-Scenes: camera-to-world 4x4, m); camera
coordinates x right, y down, z forward. Depth images are uint16 millimetres (0: no reading).

The rig is two windows of consecutive frames of one hand-held recording: camera A is the
first ``window`` frames, camera B the last ``window`` (the two viewpoints furthest apart the
recording allows), each frame with its own recorded pose. ``window = 1`` freezes each camera on
one real frame (a rigid rig over a static scene); a longer window plays the frames back and
forth at 30 Hz, so each new frame brings the sensor's real noise and the tracker's real pose
error, the way a live camera does.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from pointfence.kernels import DepthFrame
from pointfence.kernels.camera import Camera
from pointfence.kernels.errors import InputError
from pointfence.kernels.selffilter import Capsule

#: where the shared real recordings live (beside the repository)
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
KITCHEN = "7scenes_kitchen_50f"

#: the radius (m) over which the true surface is denoised for the second measure
SMOOTH = 0.015


def data_folder(name: str, data=None) -> Path:
    """``data / name`` (default: ``../shared/data``), or InputError saying where it was looked for."""
    root = Path(data) if data is not None else DATA
    path = root / name
    if not path.is_dir():
        raise InputError(f"real recording {name!r} not found at {path}; pass data=FOLDER holding {name}/ "
                         "(the project's recordings are in ../shared/data)")
    return path


@dataclass
class RigCamera:
    """One camera of the rig: its ``Camera`` (pose of the window's first frame) and its
    window of real frames: ``depths`` (uint16 mm, (H, W)) with their ``poses`` (4x4 camera ->
    world)."""

    camera: Camera
    depths: list
    poses: list

    def index(self, seq: int) -> int:
        """Which frame of the window frame ``seq`` shows: back and forth (0 1 2 1 0 1 ...), so
        the pose never jumps."""
        n = len(self.depths)
        if n == 1:
            return 0
        k = seq % (2 * n - 2)
        return k if k < n else 2 * n - 2 - k

    def frame(self, seq: int, t: float, depth=None) -> DepthFrame:
        """Frame ``seq`` at time ``t`` (s); ``depth`` replaces the recorded image (a rendered tool)."""
        i = self.index(seq)
        d = self.depths[i] if depth is None else depth
        return DepthFrame(self.camera.name, d, t, seq, T_world_cam=self.poses[i])

    def steps(self):
        """The camera's depth levels (``depth_steps.DepthSteps``) fitted from its window's frames."""
        from .depth_steps import DepthSteps

        return DepthSteps.fit_frames(self.depths, self.camera.depth_scale, self.camera.max_code)

    def points(self, i: int, box=None, dequantized: bool = False) -> np.ndarray:
        """World points (N, 3) of window frame ``i``, float64, optionally inside ``box`` = (lo, hi);
        ``dequantized``: each pixel's depth moved onto the smooth surface within half of the
        camera's depth step (``DepthSteps.surface``: a Kinect v1's disparity steps are 18 mm at
        2.5 m), instead of the staircase the camera reports."""
        d = self.depths[i]
        z = None
        if dequantized:
            from .depth_steps import DepthSteps

            cam = self.camera
            ok = (d > 0) & (d < cam.max_code)
            z = DepthSteps.fit_frames([d], cam.depth_scale, cam.max_code).surface(
                np.where(ok, d.astype(np.float64) * cam.depth_scale, 0.0))
        return cloud(self.camera, d, self.poses[i], box, z=z)


def cloud(cam: Camera, depth: np.ndarray, T_world_cam: np.ndarray, box=None, z=None) -> np.ndarray:
    """Back-projection of a uint16 depth image through ``cam``'s pinhole (no distortion), world
    frame, m; only readings inside the camera's z range (and ``box`` = (lo, hi), world m).
    ``z``: the pixels' depths (m, float) to use instead of the image's codes (its valid pixels)."""
    z = depth.astype(np.float64) * cam.depth_scale if z is None else np.asarray(z, np.float64)
    v, u = np.nonzero((depth > 0) & (depth < cam.max_code) & (z >= cam.z_min) & (z <= cam.z_max))
    zz = z[v, u]
    p = np.stack([(u - cam.cx) / cam.fx * zz, (v - cam.cy) / cam.fy * zz, zz], axis=1)
    w = p @ np.asarray(T_world_cam)[:3, :3].T + np.asarray(T_world_cam)[:3, 3]
    if box is not None:
        lo, hi = np.asarray(box[0]), np.asarray(box[1])
        w = w[np.all((w >= lo) & (w <= hi), axis=1)]
    return w


def _rigid(T) -> np.ndarray:
    """The recorded pose with its rotation re-orthonormalised (poses are stored to 8 digits)."""
    T = np.array(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = U @ Vt
    return T


def load_rig(name: str = KITCHEN, *, data=None, window: int = 1) -> tuple:
    """(camera A, camera B) of the recording ``name``: A over its first ``window`` frames, B over
    its last ``window`` (the widest baseline of a hand-held sweep). Raises InputError when the
    recording has no poses or fewer than 2 * window frames."""
    from pointfence.service.sources.recorded import RecordedSource

    src = RecordedSource(data_folder(name, data), loop=False)
    n = len(src)
    if not isinstance(window, int) or window < 1 or 2 * window > n:
        raise InputError(f"rig window = {window!r} frames; expected 1..{n // 2} for {n} frames of {name}")
    out = []
    for label, idx in (("A", range(window)), ("B", range(n - window, n))):
        depths, poses = [], []
        for i in idx:
            d, _, T = src.load(i)
            if T is None:
                raise InputError(f"{name}: frame {i} has no pose; a real rig needs camera poses (pose.txt)")
            depths.append(np.ascontiguousarray(d))
            poses.append(_rigid(T))
        out.append(RigCamera(replace(src.camera, name=f"cam{label}", T_world_cam=poses[0]), depths, poses))
    return tuple(out)


@dataclass(frozen=True)
class Site:
    """The protected point of the rig and its surroundings (world frame, m).

    ``point``: a surface point both cameras see; ``normal``: the fused surface's unit normal
    there, towards camera A; ``view``: unit direction from the point to camera A; ``offset_mm``:
    the mean signed distance of B's points to A's local plane (the rig's registration error
    there); ``parallax_deg``: angle between the two cameras' rays to the point; ``rms_mm``: the
    RMS residual of the fused local plane fit (noise and curvature)."""

    point: np.ndarray
    normal: np.ndarray
    view: np.ndarray
    offset_mm: float
    parallax_deg: float
    rms_mm: float

    def box(self, half: float) -> tuple:
        """The axis-aligned box of half-width ``half`` (m) around the point."""
        return self.point - half, self.point + half


def plane_fit(p: np.ndarray):
    """(centroid, unit normal, RMS residual m) of the least-squares plane through points (N, 3)."""
    m = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - m, full_matrices=False)
    n = vt[2]
    return m, n, float(np.sqrt(np.mean(((p - m) @ n) ** 2)))


def pick_site(a: RigCamera, b: RigCamera, *, radius: float = 0.04, stride: int = 8, max_offset_mm: float = 2.0) -> Site:
    """The protected point: among points of A's first frame (every ``stride``-th pixel) that B's
    last frame also sees (its depth there agrees within 1 cm), with at least 30 points of each
    camera within ``radius``, a fused local plane with RMS under 4 mm and A and B agreeing there
    within ``max_offset_mm``: the one with the largest parallax between the two cameras (where a
    second camera helps most). Deterministic: the same frames give the same site."""
    ca, cb = a.camera, b.camera
    TA, TB = a.poses[0], b.poses[-1]
    pa_all = a.points(0)
    pb_all = b.points(len(b.depths) - 1)
    pa = cloud(ca, _strided(a.depths[0], stride), TA)
    # B's depth at the projection of each candidate
    pc = (pa - TB[:3, 3]) @ TB[:3, :3]
    front = pc[:, 2] > cb.z_min
    u = np.full(len(pa), -1)
    v = np.full(len(pa), -1)
    u[front] = np.round(pc[front, 0] / pc[front, 2] * cb.fx + cb.cx).astype(int)
    v[front] = np.round(pc[front, 1] / pc[front, 2] * cb.fy + cb.cy).astype(int)
    inside = front & (u >= 0) & (u < cb.width) & (v >= 0) & (v < cb.height)
    zb = np.zeros(len(pa))
    zb[inside] = b.depths[-1][v[inside], u[inside]] * cb.depth_scale
    seen = inside & (zb > 0) & (np.abs(zb - pc[:, 2]) < 0.01)
    from scipy.spatial import cKDTree

    eye_a, eye_b = TA[:3, 3], TB[:3, 3]
    ta, tb = cKDTree(pa_all), cKDTree(pb_all)
    best = None
    for q in pa[seen]:
        na = pa_all[ta.query_ball_point(q, radius)]
        nb = pb_all[tb.query_ball_point(q, radius)]
        if len(na) < 30 or len(nb) < 30:
            continue
        m, n, _ = plane_fit(na)
        n = n if n @ (eye_a - q) > 0 else -n
        off = float(np.mean((nb - m) @ n)) * 1e3
        _, nf, rms = plane_fit(np.vstack([na, nb]))
        if abs(off) > max_offset_mm or rms > 0.004:
            continue
        ra, rb = eye_a - q, eye_b - q
        par = float(np.degrees(np.arccos(np.clip(ra @ rb / np.linalg.norm(ra) / np.linalg.norm(rb), -1, 1))))
        if best is None or par > best.parallax_deg:
            view = ra / np.linalg.norm(ra)
            nf = nf if nf @ view > 0 else -nf
            best = Site(q.copy(), nf, view, round(off, 3), round(par, 3), round(rms * 1e3, 3))
    if best is None:
        raise InputError("no point both cameras of the rig see on a flat, consistently registered patch; "
                         "choose frames whose views overlap more (a smaller rig window)")
    return best


def _strided(depth: np.ndarray, stride: int) -> np.ndarray:
    """``depth`` with only every ``stride``-th pixel (rows and columns) kept, the rest 0."""
    out = np.zeros_like(depth)
    out[::stride, ::stride] = depth[::stride, ::stride]
    return out


def render_tool(cam: Camera, depth: np.ndarray, T_world_cam: np.ndarray, capsules, *, window=None) -> np.ndarray:
    """The real depth image with the tool in front: every pixel whose ray meets a capsule before
    the recorded surface (or where there is no reading) reads the tool's depth (mm, rounded).
    The ray of pixel (u, v) is the pinhole's; the first hit along it is found analytically (the
    capsule's cylinder and its two end balls). Only pixels whose ray can reach the tool are
    tested (the capsules' bounding boxes, projected)."""
    out = depth.copy()
    R, t = np.asarray(T_world_cam)[:3, :3], np.asarray(T_world_cam)[:3, 3]
    for c in capsules:
        a = R.T @ (np.asarray(c.a) - t)
        b = R.T @ (np.asarray(c.b) - t)
        rs, cs = _pixel_window(cam, a, b, c.radius)
        if rs is None:
            continue
        v, u = np.mgrid[rs, cs]
        d = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones(u.shape)], axis=-1)  # z = 1 rays
        s = _ray_capsule(d.reshape(-1, 3), a, b, c.radius).reshape(u.shape)  # depth z of the first hit
        z_mm = np.where(np.isfinite(s), np.round(s / cam.depth_scale), 0).astype(np.int64)
        cur = out[rs, cs].astype(np.int64)
        hit = (z_mm > 0) & ((cur == 0) | (cur >= cam.max_code) | (z_mm < cur))
        cur[hit] = z_mm[hit]
        out[rs, cs] = np.clip(cur, 0, 65535).astype(np.uint16)
    return out


def _pixel_window(cam: Camera, a, b, r):
    """(row slice, column slice) bounding the image of the capsule a-b of radius r (camera
    frame), or (None, None) when it is wholly behind the camera; the whole image when it
    reaches behind it."""
    corners = np.array([p + r * np.array(s) for p in (a, b) for s in
                        ((1, 1, 1), (1, 1, -1), (1, -1, 1), (1, -1, -1), (-1, 1, 1), (-1, 1, -1), (-1, -1, 1),
                         (-1, -1, -1))])
    if np.all(corners[:, 2] <= cam.z_min):
        return None, None
    if np.any(corners[:, 2] <= 1e-6):
        return slice(0, cam.height), slice(0, cam.width)
    u = corners[:, 0] / corners[:, 2] * cam.fx + cam.cx
    v = corners[:, 1] / corners[:, 2] * cam.fy + cam.cy
    c0, c1 = max(int(np.floor(u.min())), 0), min(int(np.ceil(u.max())) + 1, cam.width)
    r0, r1 = max(int(np.floor(v.min())), 0), min(int(np.ceil(v.max())) + 1, cam.height)
    if c0 >= c1 or r0 >= r1:
        return None, None
    return slice(r0, r1), slice(c0, c1)


def _ray_capsule(d: np.ndarray, a, b, r) -> np.ndarray:
    """For rays s * d from the origin (d with z = 1, so s is the depth), the smallest s > 0 at
    which the ray is within ``r`` of segment a-b; inf where it never is."""
    best = np.full(len(d), np.inf)
    # the two end balls: |s d - c|^2 = r^2
    for c in (a, b):
        A = np.einsum("ij,ij->i", d, d)
        B = -2.0 * d @ c
        C = c @ c - r * r
        disc = B * B - 4 * A * C
        ok = disc >= 0
        s = np.where(ok, (-B - np.sqrt(np.where(ok, disc, 0.0))) / (2 * A), np.inf)
        best = np.minimum(best, np.where(s > 0, s, np.inf))
    # the cylinder between them: |(s d - a) x w|^2 = r^2, with 0 <= (s d - a) . w <= L
    ab = b - a
    L = float(np.linalg.norm(ab))
    if L > 0:
        w = ab / L
        dp = d - np.outer(d @ w, w)
        ap = -a - (-a @ w) * w
        A = np.einsum("ij,ij->i", dp, dp)
        B = 2.0 * dp @ ap
        C = ap @ ap - r * r
        disc = B * B - 4 * A * C
        ok = (disc >= 0) & (A > 1e-15)
        s = np.where(ok, (-B - np.sqrt(np.where(ok, disc, 0.0))) / (2 * np.where(A > 1e-15, A, 1.0)), np.inf)
        s = np.where(ok, s, 0.0)
        along = s * (d @ w) - a @ w
        ok &= (s > 0) & (along >= 0) & (along <= L)
        best = np.minimum(best, np.where(ok, s, np.inf))
    return best


def tool_capsules(tip, axis, parts) -> list:
    """World capsules of a straight tool: ``parts`` = ((s0, s1, radius), ...) spans along the unit
    ``axis`` (from the tip up the tool, m) measured from ``tip``."""
    tip, axis = np.asarray(tip, np.float64), np.asarray(axis, np.float64)
    return [Capsule(tuple(tip + s0 * axis), tuple(tip + s1 * axis), float(r)) for s0, s1, r in parts]


def nearest_distance(points: np.ndarray, x) -> float:
    """Brute force: the distance (m) from ``x`` (3,) to the nearest of ``points`` (N, 3)."""
    d = points - np.asarray(x, np.float64)
    return float(np.sqrt(np.min(np.einsum("ij,ij->i", d, d)))) if len(points) else np.inf


class Surface:
    """The true surface for safety measures: a fused cloud (N, 3) around a protected site, world m,
    and the site's outward unit normal.

    ``smooth`` > 0 (m): the denoised surface instead, every point moved onto the least-squares
    plane of the cloud within ``smooth`` of it (the mean surface the noisy readings scatter
    around). ``signed_distance(x)``: the distance to the nearest point (brute force over all of them),
    negative when ``x`` lies behind the surface there: behind the mean of its ``k`` nearest
    points along the outward normal (a sign that depth noise cannot flip away from the surface,
    where a single point's own normal can)."""

    def __init__(self, points: np.ndarray, outward, k: int = 8, smooth: float = 0.0):
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        if len(self.points) < k:
            raise InputError(f"true surface has {len(self.points)} points; expected at least {k}")
        if smooth > 0:
            self.points = denoise(self.points, smooth)
        self.outward = np.asarray(outward, np.float64) / np.linalg.norm(outward)
        self.k = int(k)
        from scipy.spatial import cKDTree

        self._tree = cKDTree(self.points)

    def signed_distance(self, x):
        """Signed distance (m) of a point (3,) (a float) or of points (M, 3) (an array)."""
        x = np.asarray(x, np.float64)
        one = x.ndim == 1
        xs = np.atleast_2d(x)
        dist, near = self._tree.query(xs, self.k)
        behind = (self.points[near].mean(axis=1) - xs) @ self.outward > 0
        d = np.where(behind, -dist[:, 0], dist[:, 0])
        return float(d[0]) if one else d


def denoise(points: np.ndarray, radius: float, k: int = 64) -> np.ndarray:
    """Every point projected onto the least-squares plane of its ``k`` nearest points within
    ``radius`` (m) (fewer than 6 of them: left as it is), float64 world m."""
    from scipy.spatial import cKDTree

    k = min(k, len(points))
    dist, idx = cKDTree(points).query(points, k)
    w = (dist <= radius)[..., None]                      # neighbours beyond radius weigh nothing
    cnt = w.sum(axis=1)
    nb = points[idx]
    m = (nb * w).sum(axis=1) / np.maximum(cnt, 1)
    c = (nb - m[:, None]) * w
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    n = vt[:, 2, :]
    h = np.einsum("ij,ij->i", points - m, n)
    return np.where(cnt >= 6, points - h[:, None] * n, points)
