"""One frame: deform the canonical avatar, rasterize, quantise, JPEG-encode.

``FrameRenderer.render`` is blocking and thread-safe (inference only); the stream handler
runs it in the render thread pool, never on the event loop.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch
from torch import Tensor

from fastgha_core.cameras import Cameras
from fastgha_core.constants import BACKGROUND_RGB

from .imaging import encode_jpeg, frame_to_uint8

__all__ = ["FrameRenderer", "RenderedFrame", "fit_camera", "render_size_of"]


@dataclass
class RenderedFrame:
    jpeg: bytes
    width: int
    height: int
    deform_ms: float  # model.animate
    raster_ms: float  # rasterization + quantisation
    encode_ms: float  # JPEG

    @property
    def render_ms(self) -> float:
        return self.deform_ms + self.raster_ms


def render_size_of(config) -> tuple[int, int]:
    """``(width, height)`` of a model config's ``render_size`` (an int or a pair)."""
    s = getattr(config, "render_size", None) or getattr(config, "input_size", 256)
    if isinstance(s, (tuple, list)):
        return int(s[0]), int(s[1])
    return int(s), int(s)


def fit_camera(cam: Cameras, max_size: int) -> Cameras:
    """The camera scaled down (aspect kept, K adjusted) so that width and height are <= ``max_size``."""
    w, h = cam.width, cam.height
    if max(w, h) <= max_size:
        return cam
    s = max_size / max(w, h)
    return cam.resize(max(1, int(math.floor(w * s))), max(1, int(math.floor(h * s))))


class FrameRenderer:
    """Renders frames of avatars with one loaded model."""

    def __init__(
        self, model, device: str | torch.device, camera_distance: float = 1.0, fov_deg: float = 20.0, bf16: bool = False
    ) -> None:
        self.model = model
        self.device = torch.device(device)
        self.bf16 = bool(bf16)  # deformation MLP under bf16 autocast (see Settings.mlp_precision)
        self.width, self.height = render_size_of(model.config)
        self.default_camera = Cameras.look_at(
            (0.0, 0.0, float(camera_distance)), (0.0, 0.0, 0.0), fov_deg=fov_deg, width=self.width, height=self.height
        )  # frontal: +z is out of the face

    def render(self, avatar, expression: Tensor, camera: Cameras, jpeg_quality: int) -> RenderedFrame:
        """``expression [E]``, ``camera`` batch [1] -> one JPEG frame at the camera's size."""
        from fastgha_core.render import render

        t0 = time.perf_counter()
        with torch.inference_mode():
            g = self.model.animate(avatar, expression.to(self.device), bf16=self.bf16, camera=camera)  # camera: view blending (model/viewblend.py)
            if self.device.type == "cuda":
                torch.cuda.synchronize(self.device)
            t1 = time.perf_counter()
            out = render(g, camera.to(self.device), background=BACKGROUND_RGB)
            frame = frame_to_uint8(out.rgb[0])  # [H, W, 3] uint8 on the host
        t2 = time.perf_counter()
        jpeg = encode_jpeg(frame, jpeg_quality)
        t3 = time.perf_counter()
        return RenderedFrame(
            jpeg, frame.shape[1], frame.shape[0], 1e3 * (t1 - t0), 1e3 * (t2 - t1), 1e3 * (t3 - t2)
        )
