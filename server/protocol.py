"""The WebSocket stream protocol: parsing client messages and packing frame messages.

Pure functions, no I/O; the full description with examples is ``docs/protocol.md``.

Client -> server
    * JSON text frame request ``{"seq": int, "expression": [E floats] | {name: weight}, "camera": {...}}``
      (``"type": "frame"`` optional; ``camera`` optional and sticky);
    * JSON text control messages ``{"type": "options", "jpeg_quality": 1..100, "max_size": int}`` and
      ``{"type": "ping", ...}``;
    * compact binary frame request (all little-endian)::

        b"FGHQ" | uint32 seq | uint16 E | E x float32 expression | uint8 has_camera
        [ | 9 x float32 K (row-major) | 16 x float32 w2c (row-major) | uint16 width | uint16 height ]

Server -> client
    * binary frame: ``b"FGHA" | uint32 L | L bytes UTF-8 JSON header | JPEG bytes``;
    * JSON text: ``ready``, ``pong``, ``options`` (the values now in force) and
      ``{"type": "error", "code": ..., "message": ...}``.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from fastgha_core.cameras import Cameras, cameras_from_json

__all__ = [
    "ProtocolError",
    "FrameRequest",
    "OptionsMessage",
    "PingMessage",
    "parse_text_message",
    "parse_binary_message",
    "pack_binary_request",
    "pack_frame",
    "unpack_frame",
    "error_message",
    "FRAME_MAGIC",
    "REQUEST_MAGIC",
    "MAX_SEQ",
    "MAX_ABS_EXPRESSION",
    "MAX_CAMERA_SIZE",
    "MAX_CAMERA_TRANSLATION",
    "FOCAL_RANGE",
    "MAX_PRINCIPAL_OFFSET",
    "F32_MAX",
    "check_camera",
    "check_reconstruction",
    "parse_cameras_json",
    "parse_head_json",
]

FRAME_MAGIC = b"FGHA"
REQUEST_MAGIC = b"FGHQ"
MAX_SEQ = 2**32 - 1
MAX_ABS_EXPRESSION = 100.0  # expression values are coefficients/weights of order 1; larger is a client bug
F32_MAX = float(np.finfo(np.float32).max)  # every JSON number must fit float32 (3.4028235e38)
_F32_MAX_DIGITS = len(str(int(F32_MAX)))  # 39: longer integer literals overflow without being converted
# Bounds of a camera the renderer can use (docs/protocol.md, "Camera objects"); the binary form carries uint16 sizes.
MAX_CAMERA_SIZE = 65535  # pixels, width and height
MAX_CAMERA_TRANSLATION = 1000.0  # metres: |w2c translation| (a head is ~0.25 m; 1 km is far beyond any use)
FOCAL_RANGE = (1e-2, 1e6)  # pixels, fx and fy
MAX_PRINCIPAL_OFFSET = 1e6  # pixels, |cx|, |cy| and |skew|
_HEAD = struct.Struct("<4sIH")  # magic, seq, E
_CAM = struct.Struct("<9f16fHH")  # K, w2c, width, height


class ProtocolError(ValueError):
    """A bad client message; answered with ``{"type": "error", "code", "message"}``, the socket stays open."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


@dataclass(frozen=True)
class FrameRequest:
    """One frame to render: ``expression [E]`` float32 and an optional new (sticky) camera."""

    seq: int
    expression: Tensor  # [E]
    camera: Cameras | None  # batch [1] when given


@dataclass(frozen=True)
class OptionsMessage:
    jpeg_quality: int | None
    max_size: int | None


@dataclass(frozen=True)
class PingMessage:
    payload: dict


def error_message(code: str, message: str) -> str:
    return json.dumps({"type": "error", "code": code, "message": message})


# ---------------------------------------------------------------- JSON parsing
def _reject_constant(name: str) -> float:
    raise ProtocolError("non_finite_number", f"JSON numbers must be finite, got {name}")


def _finite_float(text: str) -> float:
    v = float(text)
    if not math.isfinite(v) or abs(v) > F32_MAX:
        raise ProtocolError("non_finite_number", f"JSON numbers must be finite float32 values, got {text[:32]} (overflows float32)")
    return v


def _bounded_int(text: str) -> int:
    # checked on the text first: int() of more than 4300 digits raises ValueError, and an int beyond
    # float64 raises OverflowError wherever it is converted later
    if len(text.lstrip("-")) > _F32_MAX_DIGITS or abs(v := int(text)) > F32_MAX:
        short = text[:32] + ("..." if len(text) > 32 else "")
        raise ProtocolError("non_finite_number", f"JSON numbers must be finite float32 values, got an integer of {len(text.lstrip('-'))} digits ({short})")
    return v


def loads_strict(text: str | bytes) -> Any:
    """``json.loads`` that refuses NaN, Infinity and any number (integer or not) beyond float32.

    Raises ``ProtocolError`` with code ``non_finite_number`` (such numbers) or ``invalid_json``.
    """
    try:
        return json.loads(text, parse_constant=_reject_constant, parse_float=_finite_float, parse_int=_bounded_int)
    except ProtocolError:
        raise
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as e:
        raise ProtocolError("invalid_json", f"message is not valid JSON: {e}") from None
    except ValueError as e:  # anything else json.loads may raise on hostile input
        raise ProtocolError("invalid_json", f"message is not valid JSON ({type(e).__name__})") from None


def _parse_seq(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ProtocolError("invalid_seq", f"seq must be an integer, got {type(value).__name__}")
    if not 0 <= value <= MAX_SEQ:
        raise ProtocolError("invalid_seq", f"seq must be in [0, {MAX_SEQ}], got {value}")
    return value


def _check_expression_values(expr: Tensor) -> Tensor:
    if not torch.isfinite(expr).all():
        raise ProtocolError("non_finite_number", "expression values must be finite")
    if expr.numel() and float(expr.abs().max()) > MAX_ABS_EXPRESSION:
        raise ProtocolError(
            "invalid_expression", f"expression values must lie in [-{MAX_ABS_EXPRESSION:g}, {MAX_ABS_EXPRESSION:g}], got {float(expr.abs().max()):.4g}"
        )
    return expr


def parse_expression(value: Any, space: Any) -> Tensor:
    """A vector of ``space.dim`` numbers or a name->weight map -> ``[E]`` float32."""
    if isinstance(value, list):
        if len(value) != space.dim:
            raise ProtocolError(
                "invalid_expression_length",
                f"expression for space {space.name!r} needs {space.dim} values, got {len(value)}",
            )
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            raise ProtocolError("invalid_expression", f"expression vector must contain only numbers (space {space.name!r})")
    elif not isinstance(value, dict):
        raise ProtocolError(
            "invalid_expression",
            f"expression must be a list of {space.dim} numbers or a name->weight object, got {type(value).__name__}",
        )
    try:
        expr = space.parse(value)
    except ProtocolError:
        raise
    except (ValueError, TypeError, KeyError) as e:
        code = "unknown_expression_name" if isinstance(value, dict) and "unknown name" in str(e) else "invalid_expression"
        raise ProtocolError(code, str(e)) from None
    expr = torch.as_tensor(expr, dtype=torch.float32).reshape(-1)
    if expr.shape[0] != space.dim:
        raise ProtocolError("invalid_expression_length", f"expression must have {space.dim} values, got {expr.shape[0]}")
    return _check_expression_values(expr)


def check_camera(cam: Cameras) -> Cameras:
    """``cam`` when the renderer can use it; ``ValueError`` saying which bound it breaks.

    Bounds: width and height in [1, MAX_CAMERA_SIZE]; K upper triangular with last row [0, 0, 1],
    fx and fy in FOCAL_RANGE, |cx|, |cy|, |skew| <= MAX_PRINCIPAL_OFFSET; |w2c translation| <=
    MAX_CAMERA_TRANSLATION metres. (``Cameras`` itself checks finiteness and a rigid w2c.)
    """
    w, h = int(cam.width), int(cam.height)
    if not (1 <= w <= MAX_CAMERA_SIZE and 1 <= h <= MAX_CAMERA_SIZE):
        raise ValueError(f"width and height must be in [1, {MAX_CAMERA_SIZE}], got {w}x{h}")
    K = cam.K.reshape(-1, 3, 3).double()
    t = cam.w2c.reshape(-1, 4, 4)[:, :3, 3].double()
    if (K[:, 1, 0] != 0).any() or (K[:, 2, :] != torch.tensor([0.0, 0.0, 1.0], dtype=K.dtype)).any():
        raise ValueError(f"K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K[0].tolist()}")
    lo, hi = FOCAL_RANGE
    f = torch.stack([K[:, 0, 0], K[:, 1, 1]])
    if (f < lo).any() or (f > hi).any():
        raise ValueError(f"focal lengths must be in [{lo:g}, {hi:g}] pixels, got fx={float(K[0, 0, 0]):.4g} fy={float(K[0, 1, 1]):.4g}")
    off = torch.stack([K[:, 0, 1], K[:, 0, 2], K[:, 1, 2]]).abs()
    if (off > MAX_PRINCIPAL_OFFSET).any():
        raise ValueError(f"|cx|, |cy| and the skew must be at most {MAX_PRINCIPAL_OFFSET:g} pixels, got {float(off.max()):.4g}")
    dist = t.norm(dim=-1)
    if (dist > MAX_CAMERA_TRANSLATION).any():
        raise ValueError(f"the w2c translation must be at most {MAX_CAMERA_TRANSLATION:g} m long, got {float(dist.max()):.4g} m")
    return cam


def check_reconstruction(num_gaussians: int, minimum: int) -> None:
    """Refuse a reconstruction with fewer than ``minimum`` Gaussians: it holds no head (cameras far
    from it, say) and every frame of it would fail. ``ProtocolError`` code ``no_head_reconstructed``."""
    if num_gaussians < minimum:
        raise ProtocolError(
            "no_head_reconstructed",
            f"the reconstruction holds {num_gaussians} Gaussians (at least {minimum} make a head): "
            "check that the cameras look at the head from about a metre and that the masks are not empty",
        )


def parse_camera(value: Any) -> Cameras:
    try:
        cams = cameras_from_json(value if isinstance(value, (dict, list)) else [value])
        if len(cams) != 1:
            raise ValueError(f"camera must be one camera object, got {len(cams)}")
        return check_camera(cams[0])
    except (ValueError, TypeError, OverflowError) as e:
        raise ProtocolError("invalid_camera", str(e)) from None


def _loads_part(text: str | bytes, part: str, expected: str):
    """One JSON part of a multipart upload, read by ``loads_strict``; its errors name the ``part``
    and say what was ``expected`` (the upload carries other parts too)."""
    try:
        return loads_strict(text)
    except ProtocolError as e:
        if e.code != "invalid_json":
            raise ProtocolError(e.code, f"{part}: {e.message}") from None
        detail = e.message.removeprefix("message is not valid JSON").lstrip(": ")
        if detail.startswith("(") and detail.endswith(")"):
            detail = detail[1:-1]
        raise ProtocolError("invalid_json", f"{part} is not valid JSON ({detail}); expected {expected}") from None


def parse_cameras_json(text: str | bytes) -> list[Cameras]:
    """The ``cameras`` field of ``POST /v1/avatars``: a JSON array of camera objects, each within
    ``check_camera``'s bounds. Raises ``ProtocolError`` with code ``invalid_json`` /
    ``non_finite_number`` (see ``loads_strict``) or ``invalid_cameras``; the messages name the
    ``cameras`` field, since the upload carries other parts too."""
    data = _loads_part(text, "cameras", "a JSON array of camera objects")
    try:
        if isinstance(data, str):  # cameras_from_json would parse a string as JSON text again
            raise ValueError("cameras must be a non-empty JSON array of camera objects, got a JSON string")
        cams = cameras_from_json(data)
        for i, c in enumerate(cams):
            try:
                check_camera(c)
            except ValueError as e:
                raise ValueError(f"camera {i}: {e}") from None
        return cams
    except (ValueError, TypeError, OverflowError) as e:
        raise ProtocolError("invalid_cameras", str(e)) from None


def parse_head_json(text: str | bytes, num_images: int):
    """The ``head`` part of ``POST /v1/avatars``: ``fastgha track``'s head.json with each photo's
    expression, ``{"model": "ict_facekit", "identity": [1..100 numbers], "expressions": [[53] per image]}``
    and optionally each image's ``"frames"`` entry, ``[left, top, right, bottom]`` in the images' order
    (``docs/protocol.md``) -> ``fastgha_core.model.surface.HeadSurface``, read by
    ``fastgha_core.headfile.head_surface_from_json`` as ``fastgha reconstruct`` reads head.json.

    Raises ``ProtocolError`` with code ``invalid_json`` / ``non_finite_number`` (``loads_strict``),
    ``head_count_mismatch`` (expressions for another number of photos) or ``invalid_head``; the
    messages name the ``head`` part and say what was expected."""
    from fastgha_core.headfile import head_surface_from_json

    data = _loads_part(text, "head", "head.json of `fastgha track` with an 'expressions' list")
    try:
        head = head_surface_from_json(data, None, source="head")
    except ValueError as e:
        raise ProtocolError("invalid_head", str(e)) from None
    if len(head) != num_images:
        raise ProtocolError(
            "head_count_mismatch", f"head: expressions for {len(head)} photo(s) but {num_images} images came; send one list of 53 weights per image, in their order"
        )
    return head


def _parse_options(obj: dict) -> OptionsMessage:
    q = obj.get("jpeg_quality")
    s = obj.get("max_size")
    if q is not None and (isinstance(q, bool) or not isinstance(q, int) or not 1 <= q <= 100):
        raise ProtocolError("invalid_options", f"jpeg_quality must be an integer in [1, 100], got {q!r}")
    if s is not None and (isinstance(s, bool) or not isinstance(s, int) or not 16 <= s <= 65535):
        raise ProtocolError("invalid_options", f"max_size must be an integer in [16, 65535], got {s!r}")
    unknown = sorted(set(obj) - {"type", "jpeg_quality", "max_size"})
    if unknown:
        raise ProtocolError("invalid_options", f"unknown option(s) {unknown}; expected jpeg_quality, max_size")
    return OptionsMessage(q, s)


def parse_text_message(text: str, space: Any) -> FrameRequest | OptionsMessage | PingMessage:
    """Parse one client text message (see module doc); raises ``ProtocolError``, and only that:
    an unexpected exception of a parser becomes ``invalid_message`` so the stream stays open."""
    try:
        return _parse_text_message(text, space)
    except ProtocolError:
        raise
    except Exception as e:
        raise ProtocolError("invalid_message", f"the message could not be parsed ({type(e).__name__})") from None


def _parse_text_message(text: str, space: Any) -> FrameRequest | OptionsMessage | PingMessage:
    obj = loads_strict(text)
    if not isinstance(obj, dict):
        raise ProtocolError("invalid_message", f"message must be a JSON object, got {type(obj).__name__}")
    kind = obj.get("type", "frame")
    if kind == "ping":
        return PingMessage(obj)
    if kind == "options":
        return _parse_options(obj)
    if kind != "frame":
        raise ProtocolError("unknown_message_type", f"type must be 'frame', 'options' or 'ping', got {kind!r}")
    if "seq" not in obj:
        raise ProtocolError("invalid_seq", "frame request needs an integer seq")
    seq = _parse_seq(obj["seq"])
    if "expression" not in obj:
        raise ProtocolError("invalid_expression", "frame request needs an expression")
    expr = parse_expression(obj["expression"], space)
    cam = parse_camera(obj["camera"]) if obj.get("camera") is not None else None
    return FrameRequest(seq, expr, cam)


# ---------------------------------------------------------------- binary requests
def parse_binary_message(data: bytes, space: Any) -> FrameRequest:
    """Parse the compact binary frame request (see module doc); raises ``ProtocolError``."""
    if len(data) < _HEAD.size or data[:4] != REQUEST_MAGIC:
        raise ProtocolError("invalid_binary", f"binary requests start with {REQUEST_MAGIC!r} + uint32 seq + uint16 E")
    _, seq, e = _HEAD.unpack_from(data, 0)
    if e != space.dim:
        raise ProtocolError(
            "invalid_expression_length", f"expression for space {space.name!r} needs {space.dim} values, got {e}"
        )
    off = _HEAD.size
    need = off + 4 * e + 1
    if len(data) < need:
        raise ProtocolError("invalid_binary", f"binary request truncated: {len(data)} bytes, need at least {need}")
    expr = torch.from_numpy(np.frombuffer(data, dtype="<f4", count=e, offset=off).astype(np.float32))
    expr = _check_expression_values(expr)
    off += 4 * e
    has_cam = data[off]
    off += 1
    cam = None
    if has_cam == 1:
        if len(data) != off + _CAM.size:
            raise ProtocolError("invalid_binary", f"binary request with camera must be {off + _CAM.size} bytes, got {len(data)}")
        vals = _CAM.unpack_from(data, off)
        nums = vals[:25]
        if not all(math.isfinite(v) for v in nums):
            raise ProtocolError("non_finite_number", "camera K and w2c must be finite")
        K = torch.tensor(nums[:9], dtype=torch.float32).reshape(3, 3)
        w2c = torch.tensor(nums[9:25], dtype=torch.float32).reshape(4, 4)
        try:
            cam = check_camera(Cameras(K[None], w2c[None], vals[25], vals[26]))
        except ValueError as ex:
            raise ProtocolError("invalid_camera", str(ex)) from None
    elif has_cam == 0:
        if len(data) != off:
            raise ProtocolError("invalid_binary", f"binary request without camera must be {off} bytes, got {len(data)}")
    else:
        raise ProtocolError("invalid_binary", f"has_camera must be 0 or 1, got {has_cam}")
    return FrameRequest(seq, expr, cam)


def pack_binary_request(seq: int, expression: Any, camera: Cameras | None = None) -> bytes:
    """The compact binary form of a frame request (client side; used by tests and the Python client)."""
    expr = np.asarray(expression, dtype="<f4").reshape(-1)
    out = [_HEAD.pack(REQUEST_MAGIC, seq, expr.shape[0]), expr.tobytes()]
    if camera is None:
        out.append(b"\x00")
    else:
        K = camera.K.reshape(3, 3).tolist()
        w2c = camera.w2c.reshape(4, 4).tolist()
        out += [b"\x01", _CAM.pack(*sum(K, []), *sum(w2c, []), camera.width, camera.height)]
    return b"".join(out)


# ---------------------------------------------------------------- frame messages
def pack_frame(header: dict, jpeg: bytes) -> bytes:
    """``b"FGHA" | uint32 LE len(header) | UTF-8 JSON header | JPEG``."""
    h = json.dumps(header, separators=(",", ":")).encode("utf-8")
    return b"".join((FRAME_MAGIC, struct.pack("<I", len(h)), h, jpeg))


def unpack_frame(data: bytes) -> tuple[dict, bytes]:
    """Inverse of ``pack_frame``: ``(header, jpeg_bytes)``; ``ValueError`` on a malformed message."""
    if len(data) < 8 or data[:4] != FRAME_MAGIC:
        raise ValueError(f"frame messages start with {FRAME_MAGIC!r}, got {bytes(data[:4])!r}")
    (n,) = struct.unpack_from("<I", data, 4)
    if 8 + n > len(data):
        raise ValueError(f"frame header length {n} exceeds the message ({len(data)} bytes)")
    return json.loads(bytes(data[8 : 8 + n]).decode("utf-8")), bytes(data[8 + n :])
