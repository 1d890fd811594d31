"""Decoding of uploaded photos and masks, and JPEG encoding of frames (Pillow).

Decoding goes through ``fastgha_core.images`` (the one decoder every ingest path uses): the pixel
limit is checked from the header *before* any pixel is decompressed (decompression bombs), only
JPEG and PNG are accepted, EXIF orientation is applied (the client's ``K`` describes the *upright*
image, as a photo viewer shows it), every pixel mode is normalised to correct 8-bit values or
refused, and every failure becomes a typed ``ApiError``:

| status | code | when |
|---|---|---|
| 400 | ``invalid_image`` | empty, not JPEG/PNG, truncated or corrupt |
| 400 | ``unsupported_image_mode`` | a pixel mode that has no faithful 8-bit reading (the message names it) |
| 413 | ``image_too_large`` | more stored pixels than ``max_pixels`` |
"""

from __future__ import annotations

import io

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from fastgha_core.images import DecodedImage, ImageDecodeError, decode_image_bytes, decode_mask_bytes

from .errors import ApiError

__all__ = ["decode_image", "decode_image_full", "decode_mask", "encode_jpeg", "frame_to_uint8"]

_FORMATS = ("JPEG", "PNG")
_STATUS = {"image_too_large": 413}


def _api_error(e: ImageDecodeError) -> ApiError:
    return ApiError(_STATUS.get(e.code, 400), e.code, e.message)


def decode_image_full(data: bytes, what: str, max_pixels: int, max_side: int | None = None) -> DecodedImage:
    """The :class:`~fastgha_core.images.DecodedImage` of a JPEG/PNG upload (uint8, upright, EXIF focal length)."""
    try:
        return decode_image_bytes(data, what, max_pixels=max_pixels, max_side=max_side, formats=_FORMATS)
    except ImageDecodeError as e:
        raise _api_error(e) from None


def decode_image(data: bytes, what: str, max_pixels: int, max_side: int | None = None) -> tuple[Tensor, Tensor | None]:
    """Decode a JPEG/PNG upload (upright: EXIF orientation applied).

    Returns:
        image: ``[3, H, W]`` float32 in [0, 1].
        alpha: ``[1, H, W]`` float32 in [0, 1] when the image has an alpha channel, else None.
    Raises:
        ApiError: 400 ``invalid_image`` / ``unsupported_image_mode``, 413 ``image_too_large``.
    """
    d = decode_image_full(data, what, max_pixels, max_side)
    image = torch.from_numpy(d.rgb).permute(2, 0, 1).float().div_(255.0)  # [3, H, W]
    alpha = None if d.alpha is None else torch.from_numpy(d.alpha).float().div_(255.0)[None]  # [1, H, W]
    return image, alpha


def decode_mask(data: bytes, what: str, max_pixels: int, max_side: int | None = None) -> Tensor:
    """Decode a foreground mask (white = foreground; an alpha channel wins) to ``[1, H, W]`` in [0, 1].

    16-bit grey masks are scaled, not clipped (a mask at half intensity reads 0.5). Errors as
    :func:`decode_image`.
    """
    try:
        m = decode_mask_bytes(data, what, max_pixels=max_pixels, max_side=max_side, formats=_FORMATS)
    except ImageDecodeError as e:
        raise _api_error(e) from None
    return torch.from_numpy(m).float().div_(255.0)[None]  # [1, H, W]


def frame_to_uint8(rgb: Tensor) -> np.ndarray:
    """``[3, H, W]`` float in [0, 1] (any device) -> ``[H, W, 3]`` uint8 C-contiguous numpy array.

    Quantises on the tensor's device, so a CUDA frame crosses to the host as uint8 (1/4 of the bytes).
    """
    if rgb.ndim != 3 or rgb.shape[0] != 3:
        raise ValueError(f"expected a [3, H, W] frame, got {list(rgb.shape)}")
    q = rgb.detach().mul(255.0).add_(0.5).clamp_(0.0, 255.0).to(torch.uint8)  # [3, H, W]
    return q.permute(1, 2, 0).contiguous().cpu().numpy()  # [H, W, 3]


def encode_jpeg(frame: np.ndarray, quality: int) -> bytes:
    """JPEG bytes of a ``[H, W, 3]`` uint8 C-contiguous array (Pillow, no intermediate copies)."""
    if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
        raise ValueError(f"expected a [H, W, 3] uint8 array, got {frame.dtype} {list(frame.shape)}")
    h, w = frame.shape[:2]
    im = Image.frombuffer("RGB", (w, h), np.ascontiguousarray(frame), "raw", "RGB", 0, 1)
    buf = io.BytesIO()
    im.save(buf, format="JPEG", quality=int(quality))
    return buf.getvalue()
