"""Square head crops at the model's input resolution, with K adjusted and padding.

The crop is centred on the projection of the head origin (the ICT head centre, about eye level)
and spans ``extent_m`` metres at the head's depth: ``side = f * extent_m / t_z`` pixels. The
default 0.3527 m is the field of a 20-degree camera at 1 m (``Cameras.look_at``'s default fov),
the framing of the synthetic training data, so a tracked photo looks like a training view.
Where the crop leaves the photo it is padded with ``BACKGROUND_RGB`` (and mask 0). K follows
with ``Cameras.crop`` then ``Cameras.resize``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from PIL import Image

from ..cameras import Cameras
from ..constants import BACKGROUND_RGB

__all__ = ["CropBox", "head_crop_box", "crop_array", "crop_cameras", "DEFAULT_EXTENT_M"]

DEFAULT_EXTENT_M = 2.0 * math.tan(math.radians(10.0))  # 0.3527 m: 20 degrees at 1 m


@dataclass(frozen=True)
class CropBox:
    """A square crop in pixels of the source image (may extend past its borders)."""

    left: int
    top: int
    side: int


def head_crop_box(K: np.ndarray, t: np.ndarray, extent_m: float = DEFAULT_EXTENT_M) -> CropBox:
    """The crop for a head at translation ``t [3]`` (camera coordinates) seen through ``K [3, 3]``."""
    K, t = np.asarray(K, dtype=np.float64), np.asarray(t, dtype=np.float64)
    if t[2] <= 0:
        raise ValueError(f"the head must be in front of the camera (t_z > 0), got t_z = {t[2]:.3f} m")
    u = K[0, 0] * t[0] / t[2] + K[0, 2]
    v = K[1, 1] * t[1] / t[2] + K[1, 2]
    side = max(int(round(0.5 * (K[0, 0] + K[1, 1]) * extent_m / t[2])), 8)
    return CropBox(int(round(u - side / 2)), int(round(v - side / 2)), side)


def crop_array(img: np.ndarray, box: CropBox, size: int, fill) -> np.ndarray:
    """Crop ``img [H, W, C]`` (uint8 or float32) to ``box``, pad with ``fill [C]``, resize to ``size``.

    Resampling is PIL's antialiased bilinear (float images go through mode "F" per channel).
    """
    h, w = img.shape[:2]
    c = img.shape[2]
    canvas = np.empty((box.side, box.side, c), dtype=img.dtype)
    canvas[:] = np.asarray(fill, dtype=img.dtype).reshape(1, 1, c)
    x0, y0 = max(box.left, 0), max(box.top, 0)
    x1, y1 = min(box.left + box.side, w), min(box.top + box.side, h)
    if x1 > x0 and y1 > y0:
        canvas[y0 - box.top : y1 - box.top, x0 - box.left : x1 - box.left] = img[y0:y1, x0:x1]
    if box.side == size:
        return canvas
    if canvas.dtype == np.uint8 and c == 3:
        return np.asarray(Image.fromarray(canvas).resize((size, size), Image.BILINEAR, reducing_gap=None))
    chans = [np.asarray(Image.fromarray(canvas[..., k].astype(np.float32), mode="F").resize((size, size), Image.BILINEAR)) for k in range(c)]
    return np.stack(chans, axis=-1).astype(img.dtype)


def crop_cameras(cam: Cameras, box: CropBox, size: int) -> Cameras:
    """``cam`` (of the source image) for the crop ``box`` resized to ``size x size``."""
    return cam.crop(box.left, box.top, box.side, box.side).resize(size, size)


def background_uint8() -> np.ndarray:
    return np.round(np.asarray(BACKGROUND_RGB) * 255.0).astype(np.uint8)
