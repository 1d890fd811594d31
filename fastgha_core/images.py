"""One decoder for every photo and mask that enters FastGHA (server, ``reconstruct``, ``track``, datasets).

Every ingest path decodes through :func:`decode_image_bytes` / :func:`read_image` (photos) and
:func:`decode_mask_bytes` / :func:`read_mask` (foreground masks), so that all of them agree on:

- **EXIF orientation** (tag 0x0112, values 1-8) is applied: the returned pixels are the *upright*
  image a photo viewer shows, and camera intrinsics ``K`` always refer to that upright image
  (a phone's portrait shot is stored sideways with orientation 6).
- **Pixel modes** are normalised to correct 8-bit values, or refused with
  ``ImageDecodeError(code="unsupported_image_mode")`` naming the mode:

  ======================  =====================================================================
  Pillow mode             8-bit result
  ======================  =====================================================================
  ``RGB`` ``L``           as stored (``L`` replicated to 3 channels)
  ``1``                   0 / 255
  ``RGBA`` ``LA`` ``PA``  colour + alpha channel (alpha returned separately)
  ``P``                   palette colours; a ``tRNS`` transparency becomes the alpha channel
  ``CMYK`` ``YCbCr``      Pillow's conversion to RGB (no colour management)
  ``I;16`` ``I;16L``      ``round(v * 255 / 65535)`` (16-bit grey, e.g. 16-bit PNG)
  ``I;16B`` ``I;16N``
  ``I`` (32-bit int)      values in [0, 65535] are read as 16-bit grey (how Pillow opens 16-bit
                          files); anything outside that range is refused
  ``F`` (32-bit float)    values in [0, 1] are scaled by 255; anything else (or NaN/inf) is refused
  other (``LAB``, ...)    refused
  ======================  =====================================================================

- **Size limits**: the pixel count is checked from the header *before* any pixel is decompressed
  (decompression bombs): ``code="image_too_large"``. ``max_side`` downscales while decoding (JPEG
  DCT scaling via ``Image.draft``, then ``reduce``/antialiased resize), so a large photo never
  exists at full size in memory when a smaller one is wanted.

Errors are ``ImageDecodeError`` (a ``ValueError``) with ``code`` in ``"invalid_image"``,
``"image_too_large"``, ``"unsupported_image_mode"``; the message names the file by ``name``.
"""

from __future__ import annotations

import io
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image, UnidentifiedImageError

__all__ = [
    "DEFAULT_MAX_PIXELS",
    "DecodedImage",
    "ImageDecodeError",
    "decode_image_bytes",
    "decode_mask_bytes",
    "decode_pixels_bytes",
    "read_image",
    "read_mask",
    "apply_orientation",
    "too_large_error",
]

# 64 MP: larger than any phone photo (50 MP sensors), small enough to refuse decompression bombs.
DEFAULT_MAX_PIXELS = 64 * 1024 * 1024

_ORIENTATION_TAG = 0x0112
_EXIF_IFD = 0x8769
_FOCAL_LENGTH = 0x920A
_FOCAL_35MM = 0xA405
_FOCAL_PLANE_XRES = 0xA20E
_FOCAL_PLANE_YRES = 0xA20F
_FOCAL_PLANE_UNIT = 0xA210
_EXIF_WIDTH = 0xA002
_EXIF_HEIGHT = 0xA003
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}  # FocalPlaneResolutionUnit -> mm per unit
_FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)  # 43.27 mm

_SIXTEEN_BIT = ("I;16", "I;16L", "I;16B", "I;16N")


class ImageDecodeError(ValueError):
    """A photo or mask that cannot be used. ``code``: ``invalid_image`` | ``image_too_large`` |
    ``unsupported_image_mode``; the message names the file."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code
        self.message = message


@dataclass
class DecodedImage:
    """A decoded, upright, 8-bit photo.

    Attributes:
        rgb: ``[H, W, 3]`` uint8, EXIF orientation applied (upright).
        alpha: ``[H, W]`` uint8 when the file has an alpha channel (or palette transparency), else None.
        name: the name the caller gave (file name or upload part name).
        mode: the file's Pillow mode before normalisation (``"RGB"``, ``"I;16"``, ...).
        exif_focal_35mm: 35 mm-equivalent focal length in mm (EXIF FocalLengthIn35mmFilm, or
            FocalLength times the crop factor derived from the focal-plane resolution), else None.
        orientation: the EXIF orientation that was applied (1 = none).
        scale: downscale factor applied while decoding (output long side / stored long side; 1.0 = none).
    """

    rgb: np.ndarray
    alpha: np.ndarray | None
    name: str
    mode: str
    exif_focal_35mm: float | None
    orientation: int
    scale: float

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])


# ---------------------------------------------------------------- orientation
def apply_orientation(arr: np.ndarray, orientation: int) -> np.ndarray:
    """Pixels ``[H, W, ...]`` as stored -> upright, for EXIF orientation 1..8 (others: unchanged).

    Same result as ``PIL.ImageOps.exif_transpose``: 2 mirror, 3 rotate 180, 4 flip, 5 transpose,
    6 rotate 90 clockwise, 7 transverse, 8 rotate 90 counter-clockwise. Returns a contiguous copy
    when anything moved.
    """
    if orientation == 2:
        out = arr[:, ::-1]
    elif orientation == 3:
        out = arr[::-1, ::-1]
    elif orientation == 4:
        out = arr[::-1]
    elif orientation == 5:
        out = arr.swapaxes(0, 1)
    elif orientation == 6:
        out = np.rot90(arr, k=-1)
    elif orientation == 7:
        out = arr[::-1, ::-1].swapaxes(0, 1)
    elif orientation == 8:
        out = np.rot90(arr, k=1)
    else:
        return arr
    return np.ascontiguousarray(out)


def _exif(im: Image.Image):
    try:
        return im.getexif()
    except Exception:  # a corrupt EXIF block must not make a readable photo unreadable
        return None


def _orientation(exif) -> int:
    if exif is None:
        return 1
    try:
        o = int(exif.get(_ORIENTATION_TAG, 1))
    except (TypeError, ValueError):
        return 1
    return o if 1 <= o <= 8 else 1


def _ratio(v) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return f if math.isfinite(f) and f > 0 else None


def _focal_35mm(exif, width: int, height: int) -> float | None:
    """35 mm-equivalent focal length (mm) from EXIF, when present or derivable."""
    if exif is None:
        return None
    try:
        ifd = exif.get_ifd(_EXIF_IFD)
    except Exception:
        return None
    f35 = _ratio(ifd.get(_FOCAL_35MM))
    if f35 is not None:
        return f35
    f = _ratio(ifd.get(_FOCAL_LENGTH))
    xres, yres = _ratio(ifd.get(_FOCAL_PLANE_XRES)), _ratio(ifd.get(_FOCAL_PLANE_YRES))
    unit = _UNIT_MM.get(int(ifd.get(_FOCAL_PLANE_UNIT, 2) or 2))
    if f is None or xres is None or unit is None:
        return None
    # the focal-plane resolution refers to the sensor read-out size (ExifImageWidth/Height when given)
    w = _ratio(ifd.get(_EXIF_WIDTH)) or float(width)
    h = _ratio(ifd.get(_EXIF_HEIGHT)) or float(height)
    sensor_w = w / xres * unit
    sensor_h = h / (yres or xres) * unit
    diag = math.hypot(sensor_w, sensor_h)
    if not 1.0 < diag < 100.0:  # nonsense resolution tags (some cameras write the print DPI)
        return None
    return f * _FULL_FRAME_DIAGONAL_MM / diag


# ---------------------------------------------------------------- opening
def too_large_error(name: str, e: Exception, max_pixels: int) -> ImageDecodeError:
    """``image_too_large`` with the image's size, from Pillow's decompression-bomb message ("Image
    size (N pixels) exceeds limit of M pixels, ..."), and this reader's own limit ``max_pixels``,
    which the caller set (Pillow's check, at 89 M pixels, comes first for larger images)."""
    import re

    m = re.search(r"\((\d+) pixels\)", str(e))
    size = f"has {m.group(1)} pixels" if m else "is too large to decode"
    return ImageDecodeError("image_too_large", f"{name} {size}; the limit is {max_pixels}")


def _open(data: bytes, name: str, max_pixels: int, formats: Sequence[str] | None) -> Image.Image:
    if not data:
        raise ImageDecodeError("invalid_image", f"{name} is empty")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            im = Image.open(io.BytesIO(data), formats=None if formats is None else list(formats))
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as e:
        raise too_large_error(name, e, max_pixels) from None
    except Exception as e:  # Pillow raises many types (UnidentifiedImageError, OSError, SyntaxError, ...)
        what = f"a readable {' or '.join(formats)} image" if formats else "an image file Pillow can read"
        # Pillow's UnidentifiedImageError only repeats that, with the repr of our BytesIO: leave it out
        why = "" if isinstance(e, UnidentifiedImageError) else f" ({type(e).__name__}: {e})"
        raise ImageDecodeError("invalid_image", f"{name} is not {what}{why}") from None
    w, h = im.size
    if w <= 0 or h <= 0:
        raise ImageDecodeError("invalid_image", f"{name} has an empty size {w}x{h}")
    if w * h > max_pixels:
        raise ImageDecodeError("image_too_large", f"{name} has {w}x{h} = {w * h} pixels; the limit is {max_pixels}")
    return im


def _load(im: Image.Image, name: str, max_side: int | None) -> None:
    """Decompress, asking the JPEG decoder for a DCT-scaled image when ``max_side`` allows."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            if max_side is not None and im.format == "JPEG" and max(im.size) > max_side:
                w, h = im.size
                s = max_side / max(w, h)
                # draft picks the smallest 1/1, 1/2, 1/4, 1/8 scale that is still >= the requested size
                im.draft(im.mode, (max(1, math.ceil(w * s)), max(1, math.ceil(h * s))))
            im.load()
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):  # _open checked the size already
        raise ImageDecodeError("image_too_large", f"{name} is too large to decode") from None
    except Exception as e:
        raise ImageDecodeError("invalid_image", f"{name} could not be decoded ({type(e).__name__}: {e})") from None


def _refuse_mode(name: str, mode: str, detail: str = "") -> ImageDecodeError:
    return ImageDecodeError(
        "unsupported_image_mode",
        f"{name} has pixel mode {mode!r}{detail}; send an 8-bit RGB/grey image (16-bit grey is also read)",
    )


def _grey16_to_u8(a: np.ndarray) -> np.ndarray:
    a = a.astype(np.uint32)
    return ((a * 255 + 32767) // 65535).astype(np.uint8)


def _normalise(im: Image.Image, name: str) -> tuple[Image.Image, Image.Image | None]:
    """Any Pillow mode -> (8-bit ``"RGB"`` or ``"L"`` image, 8-bit ``"L"`` alpha | None).

    Stays in Pillow so that a downscale can follow before the one copy into numpy.
    """
    mode = im.mode
    if mode in ("RGB", "L"):
        return im, None
    if mode == "1":
        return im.convert("L"), None
    if mode in ("RGBA", "RGBa", "PA") or (mode == "P" and "transparency" in im.info):
        rgba = im.convert("RGBA")
        return rgba.convert("RGB"), rgba.getchannel("A")
    if mode in ("LA", "La"):
        la = im.convert("LA")
        return la.getchannel("L"), la.getchannel("A")
    if mode in ("P", "CMYK", "YCbCr", "RGBX", "HSV"):
        try:
            return im.convert("RGB"), None
        except Exception as e:
            raise _refuse_mode(name, mode, f" (conversion to RGB failed: {e})") from None
    if mode in _SIXTEEN_BIT:
        a = np.asarray(im)
        if a.dtype.kind not in "ui":
            a = a.astype(np.uint16)
        return Image.fromarray(_grey16_to_u8(a), mode="L"), None
    if mode == "I":
        a = np.asarray(im)
        lo, hi = int(a.min()), int(a.max())
        if lo < 0 or hi > 65535:
            raise _refuse_mode(name, mode, f" (32-bit integers in [{lo}, {hi}]; only values in [0, 65535] are read, as 16-bit grey)")
        return Image.fromarray(_grey16_to_u8(a), mode="L"), None
    if mode == "F":
        a = np.asarray(im, dtype=np.float32)
        if not np.isfinite(a).all():
            raise _refuse_mode(name, mode, " (32-bit floats with NaN or infinite values)")
        lo, hi = float(a.min()), float(a.max())
        if lo < 0.0 or hi > 1.0:
            raise _refuse_mode(name, mode, f" (32-bit floats in [{lo:.4g}, {hi:.4g}]; only values in [0, 1] are read)")
        return Image.fromarray(np.round(a * 255.0).astype(np.uint8), mode="L"), None
    raise _refuse_mode(name, mode)


def _downscale(im: Image.Image, max_side: int | None) -> Image.Image:
    """Antialiased downscale of an 8-bit image so that its long side is at most ``max_side``."""
    w, h = im.size
    if max_side is None or max(w, h) <= max_side:
        return im
    s = max_side / max(w, h)
    # reducing_gap: an integer box reduction first (cheap, no full-size intermediate), then a short resize
    return im.resize((max(1, round(w * s)), max(1, round(h * s))), Image.Resampling.BILINEAR, reducing_gap=2.0)


_BAND_ROWS = 256


def _pixels(im: Image.Image) -> np.ndarray:
    """A writable uint8 array of an 8-bit ``RGB``/``L`` image, copied in bands of rows.

    ``np.asarray(image)`` goes through ``tobytes()``, which holds the encoded chunks *and* their
    join (twice the array) on top of Pillow's own 4-bytes-per-pixel copy; bands keep the transient
    small.
    """
    w, h = im.size
    if w * h <= 1 << 20:
        return np.array(im)
    out = np.empty((h, w, 3) if im.mode == "RGB" else (h, w), np.uint8)
    for y in range(0, h, _BAND_ROWS):
        out[y : y + _BAND_ROWS] = np.asarray(im.crop((0, y, w, min(h, y + _BAND_ROWS))))
    return out


def _finish(raw: np.ndarray, orientation: int) -> np.ndarray:
    """Upright, writable, C-contiguous uint8 (copies at most once; call after the Pillow images are closed)."""
    arr = apply_orientation(raw, orientation)
    if not (arr.flags.writeable and arr.flags.c_contiguous):
        arr = np.array(arr, dtype=np.uint8, order="C", copy=True)
    return arr


def _to_array(im: Image.Image, orientation: int) -> np.ndarray:
    return _finish(_pixels(im), orientation)


def _check_max_side(max_side: int | None) -> None:
    if max_side is not None and (not isinstance(max_side, int) or max_side < 1):
        raise ValueError(f"max_side must be a positive int or None, got {max_side!r}")


def decode_image_bytes(
    data: bytes,
    name: str,
    *,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    max_side: int | None = None,
    formats: Sequence[str] | None = None,
) -> DecodedImage:
    """Decode an encoded photo to an upright 8-bit :class:`DecodedImage` (module doc for the rules).

    Args:
        data: the encoded file.
        name: how messages name the file (file name or upload part name).
        max_pixels: largest stored ``width * height``; checked before decompression.
        max_side: when given, the long side of the result is at most this many pixels (downscaled
            while decoding; ``DecodedImage.scale`` says by how much).
        formats: Pillow format names to accept (e.g. ``("JPEG", "PNG")``); None = any Pillow reads.
    Raises:
        ImageDecodeError: ``invalid_image`` (empty, unreadable, truncated), ``image_too_large``,
            ``unsupported_image_mode``.
    """
    _check_max_side(max_side)
    im = _open(data, name, max_pixels, formats)
    with im:
        stored_long = max(im.size)
        mode = im.mode
        exif = _exif(im)
        orientation = _orientation(exif)
        focal = _focal_35mm(exif, *im.size)
        _load(im, name, max_side)
        colour, alpha = _normalise(im, name)
        colour = _downscale(colour, max_side)
        raw = _pixels(colour)
        raw_alpha = None if alpha is None else _pixels(_downscale(alpha, max_side))
        colour.close()
        del colour, alpha
    # the Pillow images are closed: their pixel memory is gone before the last copy
    if raw.ndim == 2:
        rgb = apply_orientation(np.repeat(raw[..., None], 3, axis=2), orientation)
        rgb = np.ascontiguousarray(rgb)
    else:
        rgb = _finish(raw, orientation)
    del raw
    a = None if raw_alpha is None else _finish(raw_alpha, orientation)
    scale = max(rgb.shape[:2]) / stored_long
    return DecodedImage(rgb, a, name, mode, focal, orientation, 1.0 if scale == 1 else float(scale))


def decode_mask_bytes(
    data: bytes,
    name: str,
    *,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    max_side: int | None = None,
    formats: Sequence[str] | None = None,
) -> np.ndarray:
    """Decode a foreground mask to ``[H, W]`` uint8 (255 = foreground), upright.

    Grey masks give their 8-bit grey values (16-bit grey is scaled by 255/65535, not clipped); a
    mask with an alpha channel (RGBA, LA, palette transparency) gives its alpha; RGB masks give their
    luma. Same modes, limits and errors as :func:`decode_image_bytes`.
    """
    _check_max_side(max_side)
    im = _open(data, name, max_pixels, formats)
    with im:
        orientation = _orientation(_exif(im))
        _load(im, name, max_side)
        colour, alpha = _normalise(im, name)
        m = alpha if alpha is not None else colour.convert("L") if colour.mode != "L" else colour
        return _to_array(_downscale(m, max_side), orientation)


def decode_pixels_bytes(
    data: bytes, name: str, *, max_pixels: int = DEFAULT_MAX_PIXELS, formats: Sequence[str] | None = None
) -> np.ndarray:
    """Decode keeping the channel count: ``[H, W, C]`` uint8 with C = 1 (grey), 3 (colour) or 4 (+ alpha).

    For dataset files whose grey values are labels (segmentation class ids) rather than photos:
    grey stays one channel with its values; otherwise the same modes, orientation and errors as
    :func:`decode_image_bytes`.
    """
    im = _open(data, name, max_pixels, formats)
    with im:
        orientation = _orientation(_exif(im))
        _load(im, name, None)
        colour, alpha = _normalise(im, name)
        arr = _to_array(colour, orientation)
    arr = arr[..., None] if arr.ndim == 2 else arr
    if alpha is not None:
        arr = np.concatenate([arr, _to_array(alpha, orientation)[..., None]], axis=2)
    return arr


def _read(path: str | Path) -> tuple[bytes, str]:
    p = Path(path)
    try:
        return p.read_bytes(), str(p)
    except FileNotFoundError:
        raise ImageDecodeError("invalid_image", f"{p} does not exist") from None
    except OSError as e:
        raise ImageDecodeError("invalid_image", f"{p} cannot be read ({type(e).__name__}: {e})") from None


def read_image(
    path: str | Path, *, max_pixels: int = DEFAULT_MAX_PIXELS, max_side: int | None = None, formats: Sequence[str] | None = None
) -> DecodedImage:
    """:func:`decode_image_bytes` on the file at ``path`` (named by its path in messages)."""
    data, name = _read(path)
    return decode_image_bytes(data, name, max_pixels=max_pixels, max_side=max_side, formats=formats)


def read_mask(
    path: str | Path, *, max_pixels: int = DEFAULT_MAX_PIXELS, max_side: int | None = None, formats: Sequence[str] | None = None
) -> np.ndarray:
    """:func:`decode_mask_bytes` on the file at ``path``: ``[H, W]`` uint8."""
    data, name = _read(path)
    return decode_mask_bytes(data, name, max_pixels=max_pixels, max_side=max_side, formats=formats)
