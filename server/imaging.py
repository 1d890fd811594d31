"""Safe decoding of uploaded photos and masks, and JPEG encoding of frames (Pillow).

Decoding reads the header first and refuses images over the pixel limit *before* any pixel
is decompressed (decompression bombs), accepts only JPEG and PNG, and turns every Pillow
failure into an ``ApiError`` 400. Pixels are used as stored: EXIF orientation is ignored,
because the client's ``K`` describes the stored pixel grid.
"""

from __future__ import annotations

import io
import warnings

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from .errors import ApiError

__all__ = ["decode_image", "decode_mask", "encode_jpeg", "frame_to_uint8"]

_FORMATS = ("JPEG", "PNG")


def _open(data: bytes, what: str, max_pixels: int) -> Image.Image:
    if not data:
        raise ApiError(400, "invalid_image", f"{what} is empty")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            im = Image.open(io.BytesIO(data), formats=_FORMATS)
            w, h = im.size
            if w * h > max_pixels:
                raise ApiError(413, "image_too_large", f"{what} has {w}x{h} = {w * h} pixels; the limit is {max_pixels}")
            im.load()
    except ApiError:
        raise
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):
        raise ApiError(413, "image_too_large", f"{what} is too large to decode") from None
    except Exception as e:  # Pillow raises many types (OSError, SyntaxError, ValueError, ...)
        raise ApiError(400, "invalid_image", f"{what} is not a readable JPEG or PNG image ({type(e).__name__}: {e})") from None
    return im


def decode_image(data: bytes, what: str, max_pixels: int) -> tuple[Tensor, Tensor | None]:
    """Decode a JPEG/PNG upload.

    Returns:
        image: ``[3, H, W]`` float32 in [0, 1].
        alpha: ``[1, H, W]`` float32 in [0, 1] when the image has an alpha channel, else None.
    """
    im = _open(data, what, max_pixels)
    alpha = None
    if im.mode in ("RGBA", "LA") or (im.mode == "P" and "transparency" in im.info):
        im = im.convert("RGBA")
        arr = np.array(im)  # [H, W, 4] uint8 (writable)
        alpha = torch.from_numpy(arr[..., 3]).float().div_(255.0)[None]
        rgb = arr[..., :3]
    else:
        rgb = np.array(im.convert("RGB"))  # [H, W, 3] uint8 (writable)
    image = torch.from_numpy(rgb).permute(2, 0, 1).float().div_(255.0)  # [3, H, W]
    return image, alpha


def decode_mask(data: bytes, what: str, max_pixels: int) -> Tensor:
    """Decode a foreground mask (grey or RGB; white = foreground) to ``[1, H, W]`` in [0, 1]."""
    im = _open(data, what, max_pixels)
    if im.mode in ("RGBA", "LA"):
        arr = np.array(im.convert("RGBA"))[..., 3]
    else:
        arr = np.array(im.convert("L"))
    return torch.from_numpy(arr).float().div_(255.0)[None]  # [1, H, W]


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
