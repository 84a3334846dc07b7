"""Depth noise measured on real frames, and the fixed vs adaptive fixture radius study
(dissertation 6.3) on real geometry with that noise, in simulated time.

Noise model (``fit_noise``): the axial noise sigma_z(Z) = a + b Z^2 of the camera model
(``kernels/camera.py``, ``NoiseModel``), fitted from single frames by local plane fits. Every
``patch`` x ``patch`` block of valid pixels is fitted with a plane; a plane is exactly linear in
inverse depth over the pixel grid (1/Z = alpha u + beta v + gamma), so the fit is one linear
least-squares solve shared by all blocks. The block's residual RMS in Z (corrected for the 3
fitted parameters) estimates sigma_z at its median depth; blocks on edges or curved surfaces
read high, so each depth bin keeps the median of its blocks, and a + b Z^2 is fitted to the bins
(least squares weighted by block counts, a >= 0). Plane residuals rather than temporal
differences: the 7-Scenes and apc frames come from a moving, hand-held or arm-held camera
whose recorded poses are good to a few mm per frame (``real_rig``: the fused surface steps by
up to 5 mm between consecutive frames), so differences of aligned frames would measure the
pose error along with the noise; a single frame's plane residual sees only the sensor (its
random error and its depth quantisation, which is part of what a fixture must absorb).

Radius study (``radius_real_run``), on the recorded frames themselves (the kitchen's first 8,
each with its recorded pose: the sensor's real noise and the tracker's real pose error, the true
surface their denoised union), and with modelled noise: a real frame's surface, denoised (``truth_depth``: the
plane fit's value at each pixel, a box mean of inverse depth), is the true surface; every 30 Hz
frame is that surface plus fresh zero-mean noise drawn from the fitted model (times
``noise_scale``), rounded to the sensor's millimetres; no bias. A fixture proxy is pressed 3 cm
into it along the surface normal, as in ``dynamic_scenes.radius_run``. Fixed r_f against
adaptive r_f = r_base + k sigma at the same mean radius over the protected points (r_base
chosen so), so the comparison is of where the radius goes, not how much of it there is.
Penetration is measured against the true surface at every tick, by brute force.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from pointfence.kernels import DepthFrame, PipelineParams, RadiusModel, Workspace
from pointfence.kernels.camera import KINECT_NOISE_A, KINECT_NOISE_B, Camera, NoiseModel
from pointfence.kernels.errors import InputError
from pointfence.kernels.haptics import HapticParams, HapticScene, haptic_pipeline_params
from pointfence.service.depth_steps import DepthSteps
from pointfence.service.real_rig import SMOOTH, Surface, cloud, data_folder

RATE_HZ = 30.0
TICK_HZ = 1000.0


@dataclass(frozen=True)
class NoiseFit:
    """A fitted sigma_z = a + b Z^2 (a in m, b in 1/m) with the bins it was fitted to:
    ``bins`` rows (median depth m, sigma_z m, blocks), and the frames' depth levels (``steps``,
    ``depth_steps.DepthSteps``: a disparity camera's steps are part of sigma_z; None: unknown)."""

    a: float
    b: float
    bins: tuple
    steps: DepthSteps | None = None

    def model(self) -> NoiseModel:
        return NoiseModel(self.a, self.b)

    def summary(self) -> dict:
        out = {"a_mm": round(self.a * 1e3, 4), "b_per_m": round(self.b, 6),
               "sigma_z_mm_at": {f"{z:.2f}m": round(s * 1e3, 3) for z, s, _ in self.bins}}
        if self.steps is not None:
            out["depth_steps"] = self.steps.describe()
        return out


def block_sigmas(depth: np.ndarray, cam: Camera, patch: int = 8, min_valid: float = 0.5) -> tuple:
    """(median depth m, residual RMS of the block's plane fit m) of every ``patch`` x ``patch``
    block of a uint16 depth image with at least ``min_valid`` of its pixels valid (sensors with a
    grid of holes, like the apc frames', still give blocks) whose valid depths span under 10 %
    of their median (no depth edge). Each block's plane is a weighted least-squares fit of
    inverse depth over the pixel grid (exact for a plane)."""
    h, w = depth.shape
    H, W = h // patch * patch, w // patch * patch
    n = patch * patch

    def blocks(a):
        return a[:H, :W].reshape(H // patch, patch, W // patch, patch).transpose(0, 2, 1, 3).reshape(-1, n)

    z = blocks(depth).astype(np.float64) * cam.depth_scale
    raw = blocks(depth)
    ok = (raw > 0) & (raw < cam.max_code) & (z >= cam.z_min) & (z <= cam.z_max)
    cnt = ok.sum(axis=1)
    keep = cnt >= max(int(np.ceil(min_valid * n)), 6)
    z, ok, cnt = z[keep], ok[keep], cnt[keep]
    if not len(z):
        return np.zeros(0), np.zeros(0)
    big = np.where(ok, z, -np.inf).max(axis=1)
    small = np.where(ok, z, np.inf).min(axis=1)
    med = np.array([np.median(r[m]) for r, m in zip(z, ok)])
    flat = (big - small) < 0.1 * med
    z, ok, cnt, med = z[flat], ok[flat], cnt[flat], med[flat]
    v, u = np.mgrid[0:patch, 0:patch]
    X = np.stack([u.ravel() - (patch - 1) / 2, v.ravel() - (patch - 1) / 2, np.ones(n)], axis=1)
    wgt = ok.astype(np.float64)
    inv = np.where(ok, 1.0 / np.where(ok, z, 1.0), 0.0)     # linear in (u, v) on a plane
    A = np.einsum("bn,ni,nj->bij", wgt, X, X)
    rhs = np.einsum("bn,ni,bn->bi", wgt, X, inv)
    coef = np.linalg.solve(A, rhs[..., None])[..., 0]
    fit = 1.0 / (coef @ X.T)
    rms = np.sqrt(np.sum(wgt * (z - fit) ** 2, axis=1) / (cnt - 3))
    return med, rms


def fit_noise(frames, *, patch: int = 8, bin_width: float = 0.1, min_blocks: int = 30) -> NoiseFit:
    """Fit sigma_z = a + b Z^2 to ``frames``, an iterable of (uint16 depth, Camera), as the
    module docstring describes. Raises InputError when fewer than two depth bins have
    ``min_blocks`` flat blocks."""
    zs, ss, depths = [], [], []
    cam = None
    for depth, cam in frames:
        z, s = block_sigmas(depth, cam, patch)
        zs.append(z)
        ss.append(s)
        depths.append(depth)
    z, s = np.concatenate(zs), np.concatenate(ss)
    rows = []
    if len(z):
        edges = np.arange(np.floor(z.min() / bin_width) * bin_width, z.max() + bin_width, bin_width)
        for lo in edges:
            m = (z >= lo) & (z < lo + bin_width)
            if m.sum() >= min_blocks:
                rows.append((float(np.median(z[m])), float(np.median(s[m])), int(m.sum())))
    if len(rows) < 2:
        raise InputError(f"noise fit: {len(rows)} depth bin(s) with >= {min_blocks} flat {patch}x{patch} blocks; "
                         "expected at least 2 (give more frames, or frames with flat surfaces at several depths)")
    zb, sb, cnt = (np.array(c) for c in zip(*rows))
    wts = np.sqrt(cnt)
    A = np.stack([np.ones_like(zb), zb * zb], axis=1) * wts[:, None]
    a, b = np.linalg.lstsq(A, sb * wts, rcond=None)[0]
    if a < 0:  # a >= 0: the camera model refuses a negative floor
        a, b = 0.0, float(np.sum(wts * wts * sb * zb * zb) / np.sum(wts * wts * zb ** 4))
    if b < 0:
        a, b = float(np.sum(wts * wts * sb) / np.sum(wts * wts)), 0.0
    steps = DepthSteps.fit_frames(depths, cam.depth_scale, cam.max_code)
    return NoiseFit(float(a), float(b), tuple(rows), steps)


def recording_frames(name: str, *, data=None, every: int = 5):
    """(depth, Camera) of every ``every``-th frame of the recording ``name`` in ../shared/data."""
    from pointfence.service.sources.recorded import RecordedSource

    src = RecordedSource(data_folder(name, data), loop=False)
    return [(src.load(i)[0], src.camera) for i in range(0, len(src), every)]


# --- the radius study on real geometry --------------------------------------------------------------

def truth_depth(depth: np.ndarray, cam: Camera, window: int = 9) -> np.ndarray:
    """The denoised surface of a real depth image, float64 m (0: no estimate): at each pixel the
    value of the least-squares plane through the ``window`` x ``window`` block centred on it
    (for a full, symmetric block that is the block's mean inverse depth); pixels whose block
    is not fully valid get 0."""
    from scipy.ndimage import uniform_filter

    z = depth.astype(np.float64) * cam.depth_scale
    ok = (depth > 0) & (depth < cam.max_code) & (z >= cam.z_min) & (z <= cam.z_max)
    inv = np.where(ok, 1.0 / np.where(ok, z, 1.0), 0.0)
    full = uniform_filter(ok.astype(np.float64), window, mode="constant") > 1 - 1e-9
    mean_inv = uniform_filter(inv, window, mode="constant")
    return np.where(full, 1.0 / np.where(full, mean_inv, 1.0), 0.0)


@dataclass(frozen=True)
class RealSite:
    """A real surface patch for the radius study: the camera (with its recorded pose), the true
    depth (``truth_depth``), the protected point and the outward normal there (world m)."""

    name: str
    camera: Camera
    depth: np.ndarray
    point: np.ndarray
    normal: np.ndarray

    @property
    def distance(self) -> float:
        return float(np.linalg.norm(self.point - self.camera.T_world_cam[:3, 3]))


def real_site(name: str, depth: np.ndarray, cam: Camera, pixel) -> RealSite:
    """The site at image ``pixel`` (u, v) of a real frame: its denoised surface, the point there
    and the local plane's normal, turned towards the camera."""
    from pointfence.service.real_rig import plane_fit

    t = truth_depth(depth, cam)
    u, v = int(pixel[0]), int(pixel[1])
    if t[v, u] <= 0:
        raise InputError(f"site {name}: pixel ({u}, {v}) has no valid 9x9 neighbourhood; choose a pixel on a surface")
    T = cam.T_world_cam
    p_cam = np.array([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0]) * t[v, u]
    p = T[:3, :3] @ p_cam + T[:3, 3]
    r = 12
    sub = np.zeros_like(depth)
    sub[v - r:v + r + 1, u - r:u + r + 1] = np.round(t[v - r:v + r + 1, u - r:u + r + 1] / cam.depth_scale).astype(np.uint16)
    _, n, _ = plane_fit(cloud(cam, sub, T))
    eye = T[:3, 3]
    n = n if n @ (eye - p) > 0 else -n
    return RealSite(name, cam, t, p, n)


def _noisy_frame(truth: np.ndarray, cam: Camera, noise: NoiseModel, rng, steps: DepthSteps | None = None) -> np.ndarray:
    """The true depth (m, 0: none) plus zero-mean Gaussian noise of ``noise``, rounded to the
    camera's depth units (uint16). With a disparity camera's ``steps``: the noise beyond its
    quantisation (sigma_z^2 less step^2 / 12, the variance of rounding to a step), then the
    depth put on its levels (``DepthSteps.quantize``), as such a camera reports it."""
    ok = truth > 0
    sigma = noise.sigma_z(truth)
    if steps is not None and steps.disparity:
        sigma = np.sqrt(np.maximum(sigma ** 2 - steps.step_at(truth) ** 2 / 12.0, 0.0))
    z = truth + rng.standard_normal(truth.shape) * sigma
    if steps is not None:
        d = np.where(ok & (z > 0), steps.quantize(np.where(z > 0, z, 1.0)), 0)
    else:
        d = np.where(ok & (z > 0), np.round(z / cam.depth_scale), 0)
    return np.clip(d, 0, cam.max_code - 1).astype(np.uint16)


def radius_real_run(sites, noise: NoiseModel, adaptive: bool, *, r_f: float = 0.02, k_sigma: float = 2.0,
                    half: float = 0.06, duration: float = 0.5, backend: str = "opencl", device: str | None = None,
                    seed: int = 0, sequence=None, steps: DepthSteps | None = None) -> list:
    """Fixture proxies pressed 3 cm into real ``sites`` of one frame (same camera), one proxy per
    site along its normal (each HIP comes down from r_f + 5 cm outside at 0.8 m/s, then
    presses), with fresh frames of the true depth plus ``noise`` at 30 Hz. Every point of the
    workspace (the sites' bounding box grown by 2 ``half``) is protected. Fixed r_f, or adaptive
    r_base + k_sigma sigma with r_base set so that the mean radius over the protected points of
    the first frame is r_f. Returns one row per site: the penetration of the r_f region around
    the true surface within ``half`` of the site (safety, mm), the proxy's closest approach to
    that surface (mm), the median gap outside it in the
    second half of the run (submittance, mm), sigma_z there and the mean and spread of all the
    frame's radii (mm). ``steps``: the camera's depth levels the modelled frames are put on
    (``_noisy_frame``; None: whole codes).

    ``sequence`` (a ``real_rig.RigCamera`` whose first frame the sites were picked on): the
    frames are instead the recording's own consecutive frames with their own poses, played back
    and forth (real noise, real pose error), and the true surface is the union of all of them
    denoised over ``SMOOTH`` (their mean surface); ``noise`` then only sets the adaptive radius."""
    cam = replace(sites[0].camera, noise=noise)
    P = np.array([s.point for s in sites])
    N = np.array([s.normal for s in sites])
    ws = Workspace(tuple(P.min(axis=0) - 2 * half), tuple(P.max(axis=0) + 2 * half))
    params = HapticParams(mode="fixture")
    rng = np.random.default_rng([seed, 1])
    truth_img = sites[0].depth

    def frame_at(seq):
        if sequence is not None:
            i = sequence.index(seq)
            return DepthFrame(cam.name, sequence.depths[i], seq / RATE_HZ, seq, T_world_cam=sequence.poses[i])
        return DepthFrame(cam.name, _noisy_frame(truth_img, cam, noise, rng, steps), seq / RATE_HZ, seq)

    first = frame_at(0)
    r_max = r_f + 0.04
    if adaptive:  # r_base for the same mean radius: the mean k sigma over the first frame's points
        probe = RadiusModel(r_base=0.0, adaptive=True, k_sigma=k_sigma, r_max=r_max)
        hs = HapticScene([cam], P, params, haptic_pipeline_params(params, PipelineParams(workspace=ws, radius=probe)),
                         backend=backend, device=device)
        hs.ingest([first])
        mean_extra = float(np.mean(hs.pipeline.host_snapshot().points[:, 3]))
        if mean_extra >= r_f:
            raise InputError(f"k_sigma sigma averages {mean_extra * 1e3:.1f} mm over the protected points, not below "
                             f"r_f = {r_f * 1e3:.0f} mm: no adaptive radius has that mean; lower k_sigma")
        radius = RadiusModel(r_base=r_f - mean_extra, adaptive=True, k_sigma=k_sigma, r_max=r_max)
    else:
        radius = RadiusModel(r_base=r_f, r_max=r_max)
    pp = haptic_pipeline_params(params, PipelineParams(workspace=ws, radius=radius))
    start = P + (r_f + 0.05) * N
    hs = HapticScene([cam], start, params, pp, backend=backend, device=device)
    if sequence is None:
        exact = np.round(truth_img / cam.depth_scale).astype(np.uint16)
        truths = [Surface(cloud(cam, exact, cam.T_world_cam, (p - half, p + half)), n) for p, n in zip(P, N)]
    else:
        truths = [Surface(np.vstack([sequence.points(i, (p - half, p + half)) for i in range(len(sequence.depths))]),
                          n, smooth=SMOOTH) for p, n in zip(P, N)]
    pen = np.full(len(sites), -np.inf)
    closest = np.full(len(sites), np.inf)
    gaps = [[] for _ in sites]
    radii = None
    seq = -1
    n_ticks = int(duration * TICK_HZ)
    for k in range(n_ticks):
        s = int(k / TICK_HZ * RATE_HZ)
        if s != seq:
            seq = s
            frame = first if seq == 0 else frame_at(seq)
            hs.ingest([frame])
            if radii is None:
                radii = hs.pipeline.host_snapshot().points[:, 3].astype(np.float64)
        depth_in = min(0.8 * k / TICK_HZ, r_f + 0.05 + 0.03)  # the HIPs: down from outside, then 3 cm in
        hs.step(start - depth_in * N)
        for i, t in enumerate(truths):
            d = t.signed_distance(hs.proxies[i])
            pen[i] = max(pen[i], r_f - d)
            closest[i] = min(closest[i], d)
            if k >= n_ticks // 2:
                gaps[i].append(d - r_f)
    return [{"site": st.name, "distance_m": round(st.distance, 3), "adaptive": adaptive, "k_sigma": k_sigma,
             "sigma_z_mm": round(float(noise.sigma_z(st.distance)) * 1e3, 3),
             "radius_mean_mm": round(float(radii.mean()) * 1e3, 3), "radius_sd_mm": round(float(radii.std()) * 1e3, 3),
             "safety_penetration_mm": round(max(float(pen[i]), 0.0) * 1e3, 3),
             "closest_approach_mm": round(float(closest[i]) * 1e3, 3),
             "submittance_gap_mm": round(float(np.median(gaps[i])) * 1e3, 3)} for i, st in enumerate(sites)]


def kinect_model() -> NoiseModel:
    """The Kinect model the code uses by default (``kernels/camera.py``)."""
    return NoiseModel(KINECT_NOISE_A, KINECT_NOISE_B)


def pick_site_pixels(depth: np.ndarray, cam: Camera, targets, *, half: int = 20, stride: int = 10) -> list:
    """For each target depth (m), the pixel (u, v) of ``depth`` whose (2 half + 1)^2 block is
    fully valid with the flattest plane fit (residual RMS below 1.5 sigma of the Kinect model
    there) and a median depth within 15 % of the target; None for a target no block meets."""
    t = truth_depth(depth, cam)
    z = depth.astype(np.float64) * cam.depth_scale
    ok = (depth > 0) & (depth < cam.max_code)
    best = [None] * len(targets)
    score = [np.inf] * len(targets)
    for v in range(half + 5, depth.shape[0] - half - 5, stride):
        for u in range(half + 5, depth.shape[1] - half - 5, stride):
            blk = z[v - half:v + half + 1, u - half:u + half + 1]
            if not ok[v - half:v + half + 1, u - half:u + half + 1].all() or t[v, u] <= 0:
                continue
            med = float(np.median(blk))
            if blk.max() - blk.min() > 0.1 * med:
                continue
            _, s = block_sigmas(depth[v - half:v + half + 1, u - half:u + half + 1], cam, 2 * half + 1)
            if not len(s):
                continue
            for i, zt in enumerate(targets):
                if abs(med - zt) < 0.15 * zt and s[0] < score[i]:
                    score[i], best[i] = float(s[0]), (u, v)
    return best


def real_sites(data=None) -> list:
    """The study's real sites: flat patches of the 7-Scenes kitchen's first frame at about 1.2,
    2.0 and 2.8 m (Kinect v1), one scene whose noise varies with depth (where an adaptive
    radius can differ from a fixed one at the same mean)."""
    from pointfence.service.sources.recorded import RecordedSource

    out = []
    for name, targets in (("7scenes_kitchen_50f", (1.2, 2.0, 2.8)),):
        src = RecordedSource(data_folder(name, data), loop=False)
        depth, _, pose = src.load(0)
        cam = src.camera if pose is None else replace(src.camera, T_world_cam=pose)
        for zt, px in zip(targets, pick_site_pixels(depth, cam, targets)):
            if px is not None:
                out.append(real_site(f"{name.split('_')[0]}@{zt:g}m", depth, cam, px))
    return out


def radius_real_study(fit: NoiseFit, *, noise_scales=(1.0, 2.0), data=None, window: int = 8, **options) -> list:
    """Rows of ``radius_real_run`` over the kitchen's sites (``real_sites``), fixed and adaptive:
    with the recording's own first ``window`` frames (``noise_scale`` "recorded"; 0: skipped),
    and with the noise ``fit`` (fitted on the kitchen's own frames) times each scale, on the
    frames' own depth levels (``fit.steps``)."""
    from pointfence.service.real_rig import load_rig

    sites = real_sites(data)
    rows = []
    if window:
        seq = load_rig(window=window, data=data)[0]
        for adaptive in (False, True):
            for r in radius_real_run(sites, fit.model(), adaptive, sequence=seq, **options):
                r["noise_scale"] = "recorded"
                rows.append(r)
    for m in noise_scales:
        model = NoiseModel(fit.a * m, fit.b * m)
        for adaptive in (False, True):
            for r in radius_real_run(sites, model, adaptive, steps=fit.steps, **options):
                r["noise_scale"] = m
                rows.append(r)
    return rows


def summarize(rows: list) -> dict:
    """Per noise scale, fixed against adaptive at the same mean radius: the worst penetration of
    the nominal r_f region over the sites, the worst (smallest) closest approach to the true
    surface over the sites (mm; the larger, the safer; below 0: the proxy touched it), and the
    worst margin in the site's own noise, min over the sites of closest approach / sigma_z
    (how many standard deviations of the depth error separate the proxy from the surface where
    that is fewest: the chance of touching it; the nominal region's penetration charges an
    adaptive radius for the radius it moves away from a quiet site by design)."""
    out = {}
    for m in dict.fromkeys(r["noise_scale"] for r in rows):
        d = {}
        for adaptive, key in ((False, "fixed"), (True, "adaptive")):
            rs = [r for r in rows if r["noise_scale"] == m and r["adaptive"] == adaptive]
            d[key] = {"worst_penetration_mm": max(r["safety_penetration_mm"] for r in rs),
                      "worst_closest_approach_mm": min(r["closest_approach_mm"] for r in rs),
                      "worst_margin_sigmas": round(min(r["closest_approach_mm"] / r["sigma_z_mm"] for r in rs), 2),
                      "mean_gap_mm": round(float(np.mean([r["submittance_gap_mm"] for r in rs])), 3)}
        out["recorded_frames" if m == "recorded" else f"noise_x{m:g}"] = d
    return out
