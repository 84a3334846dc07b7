"""A depth frame as every depth source yields it."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from .errors import InputError


@dataclass
class DepthFrame:
    """One depth image from one camera.

    Attributes:
        camera: name of the camera that produced it (matches ``Camera.name``).
        depth: uint16 image, shape (height, width), in the camera's depth units.
        timestamp: capture time, seconds (monotonic clock of the source).
        seq: frame counter of the source, starting at 0.
        color: optional uint8 RGB image registered to the depth image, shape (height, width, 3).
        mask: optional uint8 image, nonzero where the pixel belongs to a protected structure.
        T_world_cam: optional per-frame pose (recorded sequences with poses; moving cameras).
    """

    camera: str
    depth: np.ndarray
    timestamp: float
    seq: int = 0
    color: Optional[np.ndarray] = None
    mask: Optional[np.ndarray] = None
    T_world_cam: Optional[np.ndarray] = None

    def check(self, width: int, height: int) -> None:
        """Raise InputError unless this frame fits a ``width`` x ``height`` camera."""
        d = self.depth
        if not isinstance(d, np.ndarray) or d.dtype != np.uint16:
            got = getattr(d, "dtype", type(d).__name__)
            raise InputError(f"frame from {self.camera!r}: depth dtype {got}; expected uint16 (convert with .astype(np.uint16) after scaling)")
        if d.shape != (height, width):
            raise InputError(f"frame from {self.camera!r}: depth shape {d.shape}; expected ({height}, {width}) for this camera")
        if self.color is not None:
            c = self.color
            if not isinstance(c, np.ndarray) or c.dtype != np.uint8 or c.shape != (height, width, 3):
                raise InputError(
                    f"frame from {self.camera!r}: color {getattr(c, 'dtype', None)} {getattr(c, 'shape', None)}; "
                    f"expected uint8 ({height}, {width}, 3) registered to the depth image"
                )
        if self.mask is not None:
            m = self.mask
            if not isinstance(m, np.ndarray) or m.shape != (height, width):
                raise InputError(f"frame from {self.camera!r}: mask shape {getattr(m, 'shape', None)}; expected ({height}, {width})")
