"""How a depth recording is quantised: the levels its camera could report (issue 23).

A depth image stores whole codes (``Camera.depth_scale`` m each, e.g. 1 mm), but the camera
behind it may resolve less than a code. A structured-light or stereo camera measures disparity,
so its depths come in steps of inverse depth: 1/z on the levels ``inv_offset + inv_step * k``
(k whole), a step of about ``inv_step * z^2`` m in depth, which grows with the square of the
depth. The 7-Scenes Kinect v1 recordings are such images: at 1.8 m their depths are about
9 mm apart (inv_step 0.0029 1/m: a 1/8-pixel disparity step of a 580 px x 7.5 cm camera),
stored in 1 mm codes.

``DepthSteps.fit`` finds the levels from the distinct depths of one image; ``quantize`` puts a
depth on the camera's level and code, as that camera would report it; ``step_at`` gives the
local step (m), the width within which the recorded depth says where the surface is. A camera
whose distinct depths are one code apart keeps the code as its step (``inv_step`` 0).

Used by the real-frame evaluation: in ``dynamic_real_frames`` the true surface is the recording
dequantised within half of its local step (a smooth surface, not the staircase of its levels),
and the moved scene is re-quantised onto the same levels, so that the camera's steps stay where
the camera puts them (fixed depths) while the surface moves through them; ``real_rig`` and
``dynamic_real_noise`` take the same levels for the rig's cameras and the modelled noise. In the
product, ``pointfence calib noise`` writes a disparity camera's ``inv_step`` as its
``[[camera]] depth_step_inv``, which ``Camera.near_reading`` uses.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: the true surface is the recording's depth smoothed over this many pixels (a Gaussian's sigma),
#: within half a step of each recorded depth (``dequantize``)
DEQUANTIZE_PX = 1.5
#: smoothing passes for a recording in disparity steps (``DepthSteps.disparity``): its treads are up to
#: about ten pixels wide on a slanted surface, ``DEQUANTIZE_PX`` * sqrt(passes) px of smoothing
DEQUANTIZE_PASSES = 16
#: a disparity camera is recognised from its distinct depths whose step is at least this many codes
#: (where the codes' own rounding, half a code, is at most a sixth of a step)
MIN_STEP_CODES = 3.0
#: ... and needs this many of them
MIN_LEVELS = 10
#: their mean distance to the nearest level (in steps) must stay below this: depths spread at
#: random over the steps give 0.25, depths on the levels rounded to whole codes about 0.04-0.08
MAX_MEAN_RESIDUAL = 0.12


def dequantize(depth_m: np.ndarray, code, sigma_px: float = DEQUANTIZE_PX, passes: int = 1) -> np.ndarray:
    """The smooth surface within the steps of a depth image (m, 0 = none; ``code``: its depth
    step, m, one value or one per pixel, ``DepthSteps.step_at``): the valid pixels' depths
    smoothed (a Gaussian of ``sigma_px`` over the valid neighbours), each kept within half a
    step of its recorded depth, so that the image is still this surface's quantisation;
    ``passes`` times (each smoothing the last one's surface: treads several pixels wide, as
    disparity steps make them, need more than one)."""
    from scipy import ndimage

    ok = depth_m > 0
    den = ndimage.gaussian_filter(ok.astype(np.float64), sigma_px, mode="nearest")
    half = 0.499 * np.asarray(code, np.float64)
    smooth = depth_m
    for _ in range(max(1, int(passes))):
        num = ndimage.gaussian_filter(np.where(ok, smooth, 0.0), sigma_px, mode="nearest")
        smooth = np.where(ok, np.clip(num / np.maximum(den, 1e-12), depth_m - half, depth_m + half), 0.0)
    return smooth


@dataclass(frozen=True)
class DepthSteps:
    """The depth levels of a camera: whole codes of ``unit`` m, and, where ``inv_step`` > 0,
    inverse depths on ``inv_offset + inv_step * k`` (1/m, k whole)."""

    unit: float
    inv_step: float = 0.0
    inv_offset: float = 0.0

    @property
    def disparity(self) -> bool:
        """Whether the depths come in disparity steps (coarser than the code somewhere)."""
        return self.inv_step > 0

    def step_at(self, z) -> np.ndarray:
        """The local depth step (m) at depths ``z`` (m): the code, or the disparity step where
        it is larger."""
        z = np.asarray(z, np.float64)
        return np.maximum(self.unit, self.inv_step * z * z)

    def surface(self, depth_m: np.ndarray) -> np.ndarray:
        """The smooth surface (m, 0 = none) within half a local step of each recorded depth of
        ``depth_m`` (m, 0 = none): ``dequantize`` with ``DEQUANTIZE_PASSES`` for a disparity
        camera, one pass for whole codes (as the evaluation has used since stop 33)."""
        return dequantize(depth_m, self.step_at(depth_m), passes=DEQUANTIZE_PASSES if self.disparity else 1)

    def quantize(self, z) -> np.ndarray:
        """Depths ``z`` (m, > 0) as the camera reports them, in whole codes (float64, not yet
        clipped to the image's range): the nearest disparity level, then the nearest code."""
        z = np.asarray(z, np.float64)
        if self.disparity:
            inv = 1.0 / np.maximum(z, 1e-9)
            k = np.rint((inv - self.inv_offset) / self.inv_step)
            lvl = self.inv_offset + self.inv_step * k
            # a level at or below 0 is beyond any range the camera has: keep the depth
            z = np.where(lvl > 0, 1.0 / np.where(lvl > 0, lvl, 1.0), z)
        return np.rint(z / self.unit)

    @classmethod
    def fit(cls, codes: np.ndarray, unit: float) -> "DepthSteps":
        """The levels of a depth image (``codes``: whole codes, 0 = none; ``unit`` m each) from
        its distinct depths: disparity levels where at least ``MIN_LEVELS`` distinct depths lie
        where the step would be ``MIN_STEP_CODES`` codes or more and sit on one comb of inverse
        depths (``MAX_MEAN_RESIDUAL``); else whole codes."""
        c = np.unique(np.asarray(codes)[np.asarray(codes) > 0]).astype(np.float64)
        plain = cls(float(unit))
        if c.size < MIN_LEVELS:
            return plain
        inv = 1.0 / (c * unit)
        gap = inv[:-1] - inv[1:]                         # between neighbouring distinct depths
        coarse = np.diff(c) >= 2                         # gaps the codes alone do not explain
        if np.count_nonzero(coarse) < MIN_LEVELS:
            return plain
        step = float(np.median(gap[coarse]))
        sel = step * (c * unit) ** 2 >= MIN_STEP_CODES * unit
        if np.count_nonzero(sel) < MIN_LEVELS:
            return plain
        x = inv[sel]
        # the comb's phase (the circular mean of 1/z modulo the step), then the comb itself by
        # least squares over the levels' numbers: 1/z = offset + step * k, as a disparity
        # camera's depth is 1 / (a d + b) of its whole disparity d
        offset = float(np.angle(np.mean(np.exp(2j * np.pi * x / step))) / (2 * np.pi) * step)
        for _ in range(4):
            k = np.rint((x - offset) / step)
            if np.ptp(k) < 2:
                return plain
            step, offset = (float(v) for v in np.polyfit(k, x, 1))
            if step <= 0:
                return plain
        r = (x - offset) / step
        if float(np.mean(np.abs(r - np.rint(r)))) > MAX_MEAN_RESIDUAL:
            return plain
        return cls(float(unit), step, offset)

    @classmethod
    def fit_frames(cls, depths, unit: float, max_code: int = 65535) -> "DepthSteps":
        """``fit`` over the valid readings (0 < code < ``max_code``) of one or more depth images
        (uint16 codes of ``unit`` m) of one camera."""
        return cls.fit(np.concatenate([np.unique(d[(d > 0) & (d < max_code)]) for d in depths]), unit)

    def describe(self) -> str:
        """One line for reports: the code and, for a disparity camera, its step at 1 and 2 m."""
        if not self.disparity:
            return f"{self.unit * 1e3:g} mm codes"
        a, b = self.step_at(1.0), self.step_at(2.0)
        return (f"disparity levels (1/z every {self.inv_step:.5f} 1/m: {float(a) * 1e3:.1f} mm at 1 m, "
                f"{float(b) * 1e3:.1f} mm at 2 m) in {self.unit * 1e3:g} mm codes")
