"""Pinhole cameras in the OpenCV convention, and converters from dataset formats.

Conventions (docs/conventions.md):
- world: head-centric canonical space in metres, +x subject's left, +y up, +z out of the face;
- camera: OpenCV, x right, y down, z forward;
- ``K [..., 3, 3]`` in pixels of the image the camera describes (``width`` x ``height``);
- ``w2c [..., 4, 4]`` world -> camera.

Pixel (u, v) = (0, 0) is the *top-left corner* of the top-left pixel, so the centre of
pixel (i, j) is at (j + 0.5, i + 0.5).

Dataset converters (bottom of the file) turn Ava-256 ``KRT`` / ``camera_calibration.json``,
NeRSemble ``camera_params.json``, VHAP/NeRF ``transforms.json`` and FLAME-fit head poses into
these cameras; ``docs/conventions.md`` writes the conventions down.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import torch
from torch import Tensor

__all__ = [
    "camera_rays",
    "Cameras",
    "look_at_w2c",
    "plucker_rays",
    "farthest_viewpoint_sampling",
    "cameras_from_json",
    "cameras_to_json",
    "load_request_folder",
    "orbit_cameras",
    "parse_ava256_krt",
    "read_ava256_krt",
    "read_ava256_calibration_json",
    "read_nersemble_camera_params",
    "read_transforms_json",
    "opengl_c2w_to_opencv_w2c",
    "head_pose_matrix",
    "fold_head_pose",
    "cameras_from_flame_pose",
]

logger = logging.getLogger(__name__)

_ORTHO_TOL = 1e-3


def _check_finite(name: str, t: Tensor) -> None:
    if not torch.isfinite(t).all():
        bad = (~torch.isfinite(t)).nonzero()[0].tolist()
        raise ValueError(f"{name} must be finite, got a non-finite value at index {bad}")


@dataclass(frozen=True, eq=False)
class Cameras:
    """A batch of pinhole cameras sharing one image size.

    Attributes:
        K: intrinsics in pixels, ``[..., 3, 3]``.
        w2c: world-to-camera rigid transform, ``[..., 4, 4]`` (OpenCV axes).
        width: image width in pixels.
        height: image height in pixels.
    """

    K: Tensor  # [..., 3, 3]
    w2c: Tensor  # [..., 4, 4]
    width: int
    height: int

    def __post_init__(self) -> None:
        K, w2c = self.K, self.w2c
        if not isinstance(K, Tensor) or not isinstance(w2c, Tensor):
            raise ValueError(f"K and w2c must be tensors, got {type(K).__name__} and {type(w2c).__name__}")
        if K.ndim < 2 or tuple(K.shape[-2:]) != (3, 3):
            raise ValueError(f"K must have shape [..., 3, 3], got {tuple(K.shape)}")
        if w2c.ndim < 2 or tuple(w2c.shape[-2:]) != (4, 4):
            raise ValueError(f"w2c must have shape [..., 4, 4], got {tuple(w2c.shape)}")
        if K.shape[:-2] != w2c.shape[:-2]:
            raise ValueError(
                f"K and w2c must share batch shape, got {tuple(K.shape[:-2])} and {tuple(w2c.shape[:-2])}"
            )
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"width and height must be positive, got {self.width}x{self.height}")
        _check_finite("K", K)
        _check_finite("w2c", w2c)
        last = K[..., 2, :]
        if K.numel() and (last - torch.tensor([0.0, 0.0, 1.0], dtype=K.dtype, device=K.device)).abs().amax() > 1e-6:
            raise ValueError(f"K last row must be [0, 0, 1] (a pinhole matrix), got {last.reshape(-1, 3)[0].tolist()}")
        fx, fy = K[..., 0, 0], K[..., 1, 1]
        if (fx <= 0).any() or (fy <= 0).any():
            raise ValueError(
                f"focal lengths must be positive, got fx={fx.flatten().tolist()[:4]} fy={fy.flatten().tolist()[:4]}"
            )
        R = w2c[..., :3, :3].double()
        eye = torch.eye(3, dtype=R.dtype, device=R.device)
        err = (R @ R.transpose(-1, -2) - eye).abs().amax() if R.numel() else torch.tensor(0.0)
        if err > _ORTHO_TOL:
            raise ValueError(f"w2c rotation must be orthonormal (R R^T = I), got max deviation {float(err):.3g}")
        if R.numel() and (torch.linalg.det(R) < 0).any():
            raise ValueError("w2c rotation must be a proper rotation (det = +1), got a reflection")
        bottom = w2c[..., 3, :]
        ref = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=w2c.dtype, device=w2c.device)
        if w2c.numel() and (bottom - ref).abs().amax() > 1e-6:
            raise ValueError(f"w2c last row must be [0, 0, 0, 1], got {bottom.reshape(-1, 4)[0].tolist()}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    # ---------------------------------------------------------------- basics
    @property
    def batch_shape(self) -> torch.Size:
        return self.K.shape[:-2]

    def __len__(self) -> int:
        return int(self.K.shape[0]) if self.K.ndim > 2 else 1

    def __getitem__(self, idx: Any) -> "Cameras":
        return Cameras(self.K[idx], self.w2c[idx], self.width, self.height)

    def flatten(self) -> "Cameras":
        """Cameras with batch shape ``[C]``."""
        return Cameras(self.K.reshape(-1, 3, 3), self.w2c.reshape(-1, 4, 4), self.width, self.height)

    def to(self, device: Any = None, dtype: torch.dtype | None = None) -> "Cameras":
        return Cameras(self.K.to(device=device, dtype=dtype), self.w2c.to(device=device, dtype=dtype), self.width, self.height)

    @property
    def device(self) -> torch.device:
        return self.K.device

    @property
    def R(self) -> Tensor:  # [..., 3, 3]
        return self.w2c[..., :3, :3]

    @property
    def t(self) -> Tensor:  # [..., 3]
        return self.w2c[..., :3, 3]

    @property
    def c2w(self) -> Tensor:  # [..., 4, 4]
        """Camera-to-world transform (rigid inverse of ``w2c``)."""
        R, t = self.R, self.t
        Rt = R.transpose(-1, -2)
        out = torch.zeros_like(self.w2c)
        out[..., :3, :3] = Rt
        out[..., :3, 3] = -(Rt @ t.unsqueeze(-1)).squeeze(-1)
        out[..., 3, 3] = 1.0
        return out

    @property
    def centers(self) -> Tensor:  # [..., 3]
        """Camera centres in world coordinates."""
        return self.c2w[..., :3, 3]

    # ---------------------------------------------------------------- geometry
    def world_to_camera(self, points: Tensor) -> Tensor:
        """``points [..., N, 3]`` (world) -> ``[..., N, 3]`` camera coordinates."""
        R, t = self.R, self.t
        return points @ R.transpose(-1, -2) + t.unsqueeze(-2)

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Project world points.

        Args:
            points: ``[..., N, 3]`` world points; the leading dims broadcast with the batch.
        Returns:
            uv: ``[..., N, 2]`` pixel coordinates (corner convention, see module doc).
            z: ``[..., N]`` camera-space depth (positive in front of the camera).
        """
        pc = self.world_to_camera(points)
        z = pc[..., 2]
        proj = pc @ self.K.transpose(-1, -2)
        zc = proj[..., 2:3]
        zc = torch.where(zc.abs() < 1e-12, torch.full_like(zc, 1e-12), zc)
        uv = proj[..., :2] / zc
        return uv, z

    def resize(self, width: int, height: int) -> "Cameras":
        """The same cameras for the image scaled to ``width`` x ``height``."""
        sx, sy = width / self.width, height / self.height
        K = self.K.clone()
        K[..., 0, :] = K[..., 0, :] * sx
        K[..., 1, :] = K[..., 1, :] * sy
        return Cameras(K, self.w2c, width, height)

    def crop(self, left: int, top: int, width: int, height: int) -> "Cameras":
        """The same cameras for the crop ``[top:top+height, left:left+width]`` of the image.

        ``left``/``top`` may be negative or the crop may extend past the image (padding).
        """
        K = self.K.clone()
        K[..., 0, 2] = K[..., 0, 2] - left
        K[..., 1, 2] = K[..., 1, 2] - top
        return Cameras(K, self.w2c, width, height)

    def pixel_rays(self, h: int | None = None, w: int | None = None) -> tuple[Tensor, Tensor]:
        """World-space rays through pixel centres of an ``h x w`` grid spanning the image.

        Returns:
            origins: ``[..., h, w, 3]``; directions: ``[..., h, w, 3]`` (unit length).
        """
        h = self.height if h is None else h
        w = self.width if w is None else w
        cams = self.resize(w, h) if (h, w) != (self.height, self.width) else self
        d_cam = camera_rays(cams.K, h, w)  # [..., h, w, 3]
        c2w = cams.c2w
        d_world = torch.einsum("...ij,...hwj->...hwi", c2w[..., :3, :3], d_cam)
        d_world = d_world / d_world.norm(dim=-1, keepdim=True)
        origins = c2w[..., None, None, :3, 3].expand_as(d_world)
        return origins, d_world

    # ---------------------------------------------------------------- constructors
    @staticmethod
    def look_at(
        eye: Tensor | Sequence[float],
        target: Tensor | Sequence[float] = (0.0, 0.0, 0.0),
        up: Tensor | Sequence[float] = (0.0, 1.0, 0.0),
        *,
        fov_deg: float = 20.0,
        width: int = 256,
        height: int = 256,
    ) -> "Cameras":
        """Cameras at ``eye [..., 3]`` looking at ``target`` with vertical field of view ``fov_deg``."""
        w2c = look_at_w2c(eye, target, up)
        f = 0.5 * height / math.tan(math.radians(fov_deg) / 2)
        K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=w2c.dtype)
        K = K.expand(*w2c.shape[:-2], 3, 3).clone()
        return Cameras(K, w2c, width, height)

    @staticmethod
    def facing_head(yaw_deg: float, pitch_deg: float = 0.0, *, distance: float = 1.0, fov_deg: float = 20.0, size: int = 256) -> "Cameras":
        """One square camera (batch ``[1]``) ``distance`` metres from the origin, looking at it, that
        sees a head at the origin facing +z turned by ``yaw_deg`` (+ = nose towards the image's right
        edge, the real photo sets' convention) and pitched by ``pitch_deg`` (+ = nose up: the camera
        below the head). The camera sits at azimuth ``-yaw_deg`` and elevation ``-pitch_deg``."""
        a, b = -math.radians(yaw_deg), math.radians(pitch_deg)
        eye = [distance * math.sin(a) * math.cos(b), -distance * math.sin(b), distance * math.cos(a) * math.cos(b)]
        return Cameras.look_at(eye, fov_deg=fov_deg, width=size, height=size).flatten()

    @staticmethod
    def stack(cams: Sequence["Cameras"]) -> "Cameras":
        if not cams:
            raise ValueError("need at least one camera to stack, got none")
        w, h = cams[0].width, cams[0].height
        for c in cams:
            if (c.width, c.height) != (w, h):
                raise ValueError(f"all cameras must share one image size, got {w}x{h} and {c.width}x{c.height}")
        # Each item may itself be a batch (any shape); the result has batch shape [sum of sizes].
        return Cameras(
            torch.cat([c.K.reshape(-1, 3, 3) for c in cams]), torch.cat([c.w2c.reshape(-1, 4, 4) for c in cams]), w, h
        )


def camera_rays(K: Tensor, h: int, w: int) -> Tensor:
    """Camera-frame rays ``K^-1 (u + 0.5, v + 0.5, 1)`` through the pixel centres of an ``h x w``
    image with intrinsics ``K [..., 3, 3]``: ``[..., h, w, 3]``, not normalised (third component 1,
    so a camera z times the ray's length is the distance along it; OpenCV pinhole, +z forward)."""
    y, x = torch.meshgrid(torch.arange(h, dtype=K.dtype, device=K.device) + 0.5, torch.arange(w, dtype=K.dtype, device=K.device) + 0.5, indexing="ij")
    pix = torch.stack([x, y, torch.ones_like(x)], dim=-1)  # [h, w, 3]
    return torch.einsum("...ij,hwj->...hwi", torch.linalg.inv(K), pix)


def look_at_w2c(
    eye: Tensor | Sequence[float],
    target: Tensor | Sequence[float] = (0.0, 0.0, 0.0),
    up: Tensor | Sequence[float] = (0.0, 1.0, 0.0),
) -> Tensor:
    """OpenCV world-to-camera matrices ``[..., 4, 4]`` for cameras at ``eye`` looking at ``target``."""
    dtype = eye.dtype if isinstance(eye, Tensor) and eye.is_floating_point() else torch.float32
    eye = torch.as_tensor(eye, dtype=dtype)
    target = torch.as_tensor(target, dtype=eye.dtype).expand_as(eye)
    up = torch.as_tensor(up, dtype=eye.dtype).expand_as(eye)
    z = target - eye
    z = z / z.norm(dim=-1, keepdim=True)  # forward
    x = torch.linalg.cross(-up, z, dim=-1)  # right = down x forward (OpenCV: x = y x z)
    xn = x.norm(dim=-1, keepdim=True)
    if (xn < 1e-8).any():
        raise ValueError("look_at: the viewing direction is parallel to `up`; choose another up vector")
    x = x / xn
    y = torch.linalg.cross(z, x, dim=-1)  # down
    R = torch.stack([x, y, z], dim=-2)  # rows: camera axes in world  [..., 3, 3]
    t = -(R @ eye.unsqueeze(-1)).squeeze(-1)
    w2c = torch.zeros(*eye.shape[:-1], 4, 4, dtype=eye.dtype)
    w2c[..., :3, :3] = R
    w2c[..., :3, 3] = t
    w2c[..., 3, 3] = 1.0
    return w2c


def plucker_rays(cameras: Cameras, h: int, w: int) -> Tensor:
    """Plücker ray maps ``[..., 6, h, w]`` = (unit direction, origin x direction) per pixel centre."""
    o, d = cameras.pixel_rays(h, w)  # [..., h, w, 3]
    m = torch.linalg.cross(o, d, dim=-1)
    return torch.cat([d, m], dim=-1).movedim(-1, -3)


def orbit_cameras(
    n: int,
    *,
    radius: float = 1.0,
    yaw_deg: float = 35.0,
    pitch_deg: float = 10.0,
    fov_deg: float = 20.0,
    width: int = 256,
    height: int = 256,
    target: Sequence[float] = (0.0, 0.0, 0.0),
) -> Cameras:
    """``n`` cameras swinging left-right (±yaw) with a gentle pitch wave, looking at ``target``."""
    s = torch.linspace(0, 2 * math.pi, n + 1, dtype=torch.float64)[:-1]
    yaw = torch.deg2rad(torch.tensor(yaw_deg, dtype=torch.float64)) * torch.sin(s)
    pitch = torch.deg2rad(torch.tensor(pitch_deg, dtype=torch.float64)) * torch.sin(2 * s) * 0.5
    eye = torch.stack(
        [radius * torch.cos(pitch) * torch.sin(yaw), radius * torch.sin(pitch), radius * torch.cos(pitch) * torch.cos(yaw)],
        dim=-1,
    ) + torch.tensor(target, dtype=torch.float64)
    cams = Cameras.look_at(eye.float(), torch.tensor(target, dtype=torch.float32), fov_deg=fov_deg, width=width, height=height)
    return cams


def farthest_viewpoint_sampling(centers: Tensor, k: int, start: int | None = None, generator: torch.Generator | None = None) -> list[int]:
    """Pick ``k`` of the cameras with centres ``[N, 3]`` by farthest-point sampling on viewing directions.

    Starts from ``start`` (a random camera when None) and repeatedly adds the camera whose
    direction from the origin (the head) is farthest from all chosen ones.
    """
    centers = torch.as_tensor(centers)
    if centers.ndim != 2 or centers.shape[1] != 3:
        raise ValueError(f"centers must have shape [N, 3], got {list(centers.shape)}")
    n = centers.shape[0]
    if not 1 <= k <= n:
        raise ValueError(f"k must be in [1, {n}] for {n} cameras, got {k}")
    centers = centers.double()
    dirs = centers / centers.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    if start is None:
        start = int(torch.randint(n, (1,), generator=generator))
    elif not 0 <= int(start) < n:
        raise ValueError(f"start must be a camera index in [0, {n - 1}], got {start}")
    start = int(start)
    chosen = [start]
    dist = (dirs - dirs[start]).norm(dim=-1)
    for _ in range(k - 1):
        dist[chosen] = -1.0
        nxt = int(torch.argmax(dist))
        chosen.append(nxt)
        dist = torch.minimum(dist, (dirs - dirs[nxt]).norm(dim=-1))
    return chosen


# ---------------------------------------------------------------- our JSON schema
def _camera_from_obj(obj: Any, index: int) -> tuple[Tensor, Tensor, int, int]:
    if not isinstance(obj, dict):
        raise ValueError(f"camera {index}: expected an object with K, w2c, width, height, got {type(obj).__name__}")
    missing = [k for k in ("K", "w2c", "width", "height") if k not in obj]
    if missing:
        raise ValueError(f"camera {index}: missing field(s) {missing}; expected K, w2c, width, height")
    try:
        K = torch.tensor(obj["K"], dtype=torch.float32)
        w2c = torch.tensor(obj["w2c"], dtype=torch.float32)
    except (TypeError, ValueError, OverflowError) as e:
        raise ValueError(f"camera {index}: K and w2c must be numeric matrices ({e})") from None
    if tuple(K.shape) != (3, 3):
        raise ValueError(f"camera {index}: K must be 3x3, got shape {tuple(K.shape)}")
    if tuple(w2c.shape) == (3, 4):
        w2c = torch.cat([w2c, torch.tensor([[0.0, 0.0, 0.0, 1.0]])], dim=0)
    if tuple(w2c.shape) != (4, 4):
        raise ValueError(f"camera {index}: w2c must be 4x4 (or 3x4), got shape {tuple(w2c.shape)}")
    w, h = obj["width"], obj["height"]
    if not (isinstance(w, int) and isinstance(h, int)) or isinstance(w, bool) or isinstance(h, bool):
        raise ValueError(f"camera {index}: width and height must be integers, got {w!r} and {h!r}")
    return K, w2c, w, h


def _json_kind(value: Any) -> str:
    """JSON's name for a parsed value's type (``str`` -> ``string``), for error messages."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, (int, float)):
        return "number"
    return {"str": "string", "dict": "object", "list": "array"}.get(type(value).__name__, type(value).__name__)


def cameras_from_json(data: Any) -> list[Cameras]:
    """Parse our camera schema: one object or an array of ``{"K", "w2c", "width", "height"}``.

    Returns one single-camera ``Cameras`` per object (sizes may differ between images).
    """
    if isinstance(data, (str, bytes)):
        try:
            data = json.loads(data)
        except json.JSONDecodeError as e:
            raise ValueError(f"cameras JSON does not parse: {e}") from None
    if isinstance(data, dict):
        data = [data]
    if not isinstance(data, list) or not data:
        got = "an empty array" if isinstance(data, list) else f"a JSON {_json_kind(data)}"
        raise ValueError(f"cameras must be a non-empty JSON array of camera objects, got {got}")
    out = []
    for i, obj in enumerate(data):
        K, w2c, w, h = _camera_from_obj(obj, i)
        try:
            out.append(Cameras(K[None], w2c[None], w, h))
        except ValueError as e:
            raise ValueError(f"camera {i}: {e}") from None
    return out


def cameras_to_json(cameras: Cameras) -> list[dict]:
    """Our camera schema for every camera in the batch (flattened)."""
    c = cameras.flatten()
    return [
        {"K": c.K[i].tolist(), "w2c": c.w2c[i].tolist(), "width": c.width, "height": c.height}
        for i in range(c.K.shape[0])
    ]


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def load_request_folder(folder: str | Path) -> tuple[list[Path], list[Cameras]]:
    """A request folder: images sorted by file name plus ``cameras.json`` in the same order.

    Mask files named ``*_mask.png`` (or in a ``masks/`` subfolder) are not images.
    """
    folder = Path(folder)
    if folder.is_file():
        raise ValueError(f"request folder {folder} is a file; expected a folder of photos (+ cameras.json): put the photo in one")
    if not folder.is_dir():
        raise ValueError(f"request folder {folder} does not exist")
    cam_file = folder / "cameras.json"
    if not cam_file.exists():
        # track into ANOTHER folder: `track` refuses an --out that holds the photos (reconstruct would take both as views);
        # under out/ of the working directory (as the README's commands), since the photos' own folder may be read-only
        found = sorted({p.suffix for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.stem.endswith("_mask")})
        photos = " ".join(f"{folder}/*{x}" for x in found) or "PHOTO..."
        tracked = f"out/{folder.resolve().name or 'photos'}-tracked"
        raise ValueError(
            f"request folder {folder} has no cameras.json; for photos without cameras, run "
            f"`fastgha track --images {photos} --out {tracked}` first (it writes the crops, masks, cameras.json and "
            f"head.json into that new folder), then use --input {tracked}"
        )
    images = sorted(
        p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.stem.endswith("_mask")
    )
    cams = cameras_from_json(cam_file.read_text())
    if len(images) != len(cams):
        shown = ", ".join(p.name for p in images[:8]) + (", ..." if len(images) > 8 else "")
        raise ValueError(
            f"request folder {folder}: {len(images)} images ({shown}) but {len(cams)} cameras in cameras.json, "
            "one per image in file-name order; remove the images that are not views, or add their cameras"
        )
    return images, cams


# ---------------------------------------------------------------- dataset converters
# Every converter returns OpenCV cameras in metres (module doc). Lens distortion is not modelled:
# images are assumed undistorted; a warning is logged when a file carries non-zero coefficients.

# Ava-256 full-resolution images are 2668 wide x 4096 tall (the released images are downsampled;
# call ``.resize(w, h)`` on the result to match them).
AVA256_WIDTH, AVA256_HEIGHT = 2668, 4096

# OpenCV calibrations put pixel centres at integer coordinates, ours at +0.5 (module doc): the
# dataset readers whose K comes from an OpenCV-style calibration add this to (cx, cy).
OPENCV_TO_CORNER = 0.5

# OpenGL camera axes (x right, y up, z backward) -> OpenCV (x right, y down, z forward).
_GL_TO_CV = (1.0, -1.0, -1.0)


def _read_json_source(src: Any, what: str) -> Any:
    """A parsed JSON object, or the file at a path (str / Path)."""
    if isinstance(src, (dict, list)):
        return src
    if isinstance(src, (str, Path)):
        path = Path(src)
        if not path.is_file():
            raise FileNotFoundError(f"{what}: no such file {path}")
        try:
            return json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"{what}: {path} is not valid JSON ({e})") from None
    raise ValueError(f"{what}: expected a path or a parsed JSON object, got {type(src).__name__}")


def _matrix(value: Any, what: str, shapes: tuple[tuple[int, int], ...]) -> Tensor:
    try:
        m = torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError) as e:
        raise ValueError(f"{what} must be a numeric matrix ({e})") from None
    if tuple(m.shape) not in shapes:
        raise ValueError(f"{what} must have shape {' or '.join(str(list(s)) for s in shapes)}, got {list(m.shape)}")
    return m


def _intrinsics_either_layout(k: Tensor, what: str) -> Tensor:
    """``K`` stored row-major (last row ``[0, 0, 1]``) or transposed (last column ``[0, 0, 1]``)."""
    last = torch.tensor([0.0, 0.0, 1.0], dtype=k.dtype)
    if torch.allclose(k[2], last, atol=1e-9):
        return k
    if torch.allclose(k[:, 2], last, atol=1e-9):
        return k.T.contiguous()
    raise ValueError(f"{what}: expected a pinhole K with [0, 0, 1] as last row (or, transposed, last column), got {k.tolist()}")


def _shift_principal_point(K: Tensor, shift: float) -> Tensor:
    K = K.clone()
    K[0, 2] += shift
    K[1, 2] += shift
    return K


def _homogeneous(m: Tensor) -> Tensor:  # [3, 4] | [4, 4] -> [4, 4]
    if m.shape[0] == 4:
        return m
    return torch.cat([m, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=m.dtype)], dim=0)


def _single(K: Tensor, w2c: Tensor, width: int, height: int, what: str) -> Cameras:
    try:
        return Cameras(K.float()[None], w2c.float()[None], width, height)
    except ValueError as e:
        raise ValueError(f"{what}: {e}") from None


def _warn_distortion(dist: Any, what: str) -> None:
    try:
        d = torch.as_tensor(dist, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        return
    if d.numel() and d.abs().max() > 0:
        logger.warning("%s: lens distortion %s is ignored; undistort the images first", what, d.tolist())


def parse_ava256_krt(
    text: str,
    *,
    width: int = AVA256_WIDTH,
    height: int = AVA256_HEIGHT,
    translation_scale: float = 1e-3,
    principal_point_shift: float = OPENCV_TO_CORNER,
) -> dict[str, Cameras]:
    """Cameras from the text of an Ava-256 / Multiface ``KRT`` file.

    Per camera, 9 lines: the camera name; ``K`` as 3 lines of 3 numbers (row-major or
    transposed, detected from where ``[0, 0, 1]`` sits); the distortion coefficients;
    the world-to-camera extrinsic ``[R | t]`` as 3 lines of 4 numbers with ``t`` in
    millimetres; one blank line. ``translation_scale`` converts the translation to metres;
    ``principal_point_shift`` (+0.5) moves the OpenCV principal point to our pixel-corner origin.

    Returns ``{name: Cameras}`` with batch shape ``[1]`` each, in file order; ``K`` is in pixels of
    the ``width`` x ``height`` image (Ava-256 full resolution by default).
    """
    lines = [ln.strip() for ln in text.splitlines()]
    out: dict[str, Cameras] = {}
    i = 0
    while i < len(lines):
        if not lines[i]:
            i += 1
            continue
        name = lines[i]
        block = lines[i + 1 : i + 8]
        what = f"KRT camera {name!r}"
        if len(block) < 7:
            raise ValueError(f"{what}: expected 7 lines after the name (K 3, distortion 1, extrinsic 3), got {len(block)}")
        try:
            rows = [[float(x) for x in ln.split()] for ln in block]
        except ValueError as e:
            raise ValueError(f"{what}: non-numeric value ({e})") from None
        K = _intrinsics_either_layout(_matrix(rows[0:3], f"{what} K", ((3, 3),)), what)
        K = _shift_principal_point(K, principal_point_shift)
        _warn_distortion(rows[3], what)
        ext = _matrix(rows[4:7], f"{what} extrinsic", ((3, 4),))
        ext[:, 3] *= translation_scale
        out[name] = _single(K, _homogeneous(ext), width, height, what)
        i += 8
    if not out:
        raise ValueError("KRT file holds no cameras")
    return out


def read_ava256_krt(path: str | Path, **kwargs: Any) -> dict[str, Cameras]:
    """:func:`parse_ava256_krt` on the file at ``path``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"KRT: no such file {path}")
    return parse_ava256_krt(path.read_text(), **kwargs)


def read_ava256_calibration_json(
    src: Any,
    *,
    width: int | None = None,
    height: int | None = None,
    translation_scale: float = 1e-3,
    principal_point_shift: float = OPENCV_TO_CORNER,
) -> dict[str, Cameras]:
    """Cameras from an Ava-256 ``camera_calibration.json`` (Meta's KRT JSON format).

    ``{"KRT": [{"cameraId", "K", "T", "width"?, "height"?, "distortion"?, ...}, ...]}`` where
    ``K`` is stored transposed (column-major; a row-major K is detected and accepted) and ``T`` is
    the world-to-camera extrinsic stored transposed, ``[4][4]`` or ``[4][3]`` (i.e. a 3x4
    ``[R | t]``), translation in millimetres. ``width``/``height`` fill in when a camera has none.
    ``principal_point_shift`` (+0.5) moves the OpenCV principal point to our pixel-corner origin.

    Args:
        src: a path or the parsed JSON object.
    Returns:
        ``{cameraId: Cameras}`` with batch shape ``[1]`` each, in file order.
    """
    data = _read_json_source(src, "camera_calibration.json")
    entries = data.get("KRT") if isinstance(data, dict) else data
    if not isinstance(entries, list) or not entries:
        raise ValueError("camera_calibration.json: expected {'KRT': [camera, ...]} with at least one camera")
    out: dict[str, Cameras] = {}
    for i, cam in enumerate(entries):
        if not isinstance(cam, dict):
            raise ValueError(f"camera_calibration.json: camera {i} must be an object, got {type(cam).__name__}")
        name = str(cam.get("cameraId", cam.get("name", i)))
        what = f"camera_calibration.json camera {name!r}"
        for key in ("K", "T"):
            if key not in cam:
                raise ValueError(f"{what}: missing field {key!r}; expected K, T (and width, height)")
        K = _intrinsics_either_layout(_matrix(cam["K"], f"{what} K", ((3, 3),)), what)
        K = _shift_principal_point(K, principal_point_shift)
        ext = _matrix(cam["T"], f"{what} T (stored transposed)", ((4, 4), (4, 3))).T.contiguous()
        ext = _homogeneous(ext)
        ext[:3, 3] *= translation_scale
        w, h = cam.get("width", width), cam.get("height", height)
        if w is None or h is None:
            raise ValueError(f"{what}: no width/height in the file; pass width= and height=")
        _warn_distortion(cam.get("distortion", []), what)
        out[name] = _single(K, ext, int(w), int(h), what)
    return out


def read_nersemble_camera_params(
    src: Any, *, width: int, height: int, principal_point_shift: float = OPENCV_TO_CORNER
) -> dict[str, Cameras]:
    """Cameras from NeRSemble ``calibration/camera_params.json``.

    ``{"world_2_cam": {serial: 4x4}, "intrinsics": 3x3}``: OpenCV world-to-camera matrices in
    metres per camera serial and one shared ``K`` (a ``{serial: 3x3}`` map is accepted too) in
    pixels of the ``width`` x ``height`` images it was calibrated for (not stored in the file;
    full-resolution NeRSemble images are 2200 x 3208). ``principal_point_shift`` (+0.5) moves the
    OpenCV principal point to our pixel-corner origin.

    Returns ``{serial: Cameras}`` with batch shape ``[1]`` each.
    """
    data = _read_json_source(src, "camera_params.json")
    if not isinstance(data, dict) or "world_2_cam" not in data or "intrinsics" not in data:
        got = sorted(data) if isinstance(data, dict) else type(data).__name__
        raise ValueError(f"camera_params.json: expected keys 'world_2_cam' and 'intrinsics', got {got}")
    w2cs, intr = data["world_2_cam"], data["intrinsics"]
    if not isinstance(w2cs, dict) or not w2cs:
        raise ValueError("camera_params.json: 'world_2_cam' must map camera serials to 4x4 matrices")
    out: dict[str, Cameras] = {}
    for serial, m in w2cs.items():
        what = f"camera_params.json camera {serial!r}"
        k_src = intr[serial] if isinstance(intr, dict) else intr
        K = _shift_principal_point(_matrix(k_src, f"{what} intrinsics", ((3, 3),)), principal_point_shift)
        w2c = _homogeneous(_matrix(m, f"{what} world_2_cam", ((4, 4), (3, 4))))
        out[str(serial)] = _single(K, w2c, width, height, what)
    return out


def opengl_c2w_to_opencv_w2c(c2w_gl: Tensor) -> Tensor:
    """``c2w [..., 4, 4]`` with OpenGL camera axes (x right, y up, z back) -> OpenCV ``w2c [..., 4, 4]``."""
    flip = torch.tensor([*_GL_TO_CV, 1.0], dtype=c2w_gl.dtype, device=c2w_gl.device)
    c2w = c2w_gl * flip  # scales the columns: camera axes y, z flipped  [..., 4, 4]
    R = c2w[..., :3, :3].transpose(-1, -2)
    w2c = torch.zeros_like(c2w)
    w2c[..., :3, :3] = R
    w2c[..., :3, 3] = -(R @ c2w[..., :3, 3:4]).squeeze(-1)
    w2c[..., 3, 3] = 1.0
    return w2c


def _is_vhap_export(data: Any) -> bool:
    """VHAP's ``export_as_nerf_dataset.py`` marks its files with per-frame timestep/camera indices."""
    frames = data.get("frames") if isinstance(data, dict) else None
    if isinstance(data, dict) and "camera_indices" in data and "timestep_indices" in data:
        return True
    return bool(frames) and isinstance(frames[0], dict) and {"timestep_index", "camera_index"} <= set(frames[0])


def read_transforms_json(src: Any, *, principal_point_origin: str = "auto") -> list[Cameras]:
    """Cameras from a VHAP / NeRF-style ``transforms.json``, one per entry of ``frames``.

    ``transform_matrix`` is camera-to-world with OpenGL camera axes. Intrinsics ``fl_x fl_y cx cy
    w h`` are read from the frame, falling back to the top level; ``camera_angle_x`` (horizontal
    FoV, radians, principal point at the image centre) is accepted when ``fl_x`` is absent and
    ``fl_y`` defaults to ``fl_x``.

    Where ``cy`` is measured from (``principal_point_origin``):

    - ``"top"``: nerfstudio / instant-ngp files, ``cy`` from the top row, pixel centres at +0.5
      (our convention): kept as they are.
    - ``"bottom"``: VHAP exports. VHAP converts its OpenCV cameras to OpenGL before writing
      (``vhap/util/camera.py: convert_camera_convention("opencv->opengl")`` flips the camera's y
      and z axes *and* sets ``K[1, 2] = H - K[1, 2]``), so its ``cy`` is measured from the bottom
      row: we read ``cy = h - cy_file``. ``cx`` is unchanged by that conversion. (VHAP passes the
      source calibration's OpenCV principal point through without a half-pixel shift, so a VHAP
      export of an OpenCV-calibrated rig keeps that source's +-0.5 px ambiguity.)
    - ``"auto"`` (default): ``"bottom"`` when the file is a VHAP export (frames carry
      ``timestep_index`` and ``camera_index``, or the top level ``timestep_indices`` and
      ``camera_indices``), else ``"top"``.

    Returns a list of ``Cameras`` (batch shape ``[1]``) in frame order.
    Raises ``ValueError`` for a malformed file or an unknown ``principal_point_origin``.
    """
    if principal_point_origin not in ("auto", "top", "bottom"):
        raise ValueError(f"principal_point_origin must be 'auto', 'top' or 'bottom', got {principal_point_origin!r}")
    data = _read_json_source(src, "transforms.json")
    frames = data.get("frames") if isinstance(data, dict) else None
    if not isinstance(frames, list) or not frames:
        raise ValueError("transforms.json: expected an object with a non-empty 'frames' array")
    from_bottom = principal_point_origin == "bottom" or (principal_point_origin == "auto" and _is_vhap_export(data))
    out = []
    for i, fr in enumerate(frames):
        what = f"transforms.json frame {i}"
        if not isinstance(fr, dict) or "transform_matrix" not in fr:
            raise ValueError(f"{what}: expected an object with 'transform_matrix'")

        def get(key: str, default: Any = None) -> Any:
            return fr.get(key, data.get(key, default))

        w, h = get("w"), get("h")
        if w is None or h is None:
            raise ValueError(f"{what}: no image size; expected 'w' and 'h' in the frame or at the top level")
        fx = get("fl_x")
        if fx is None:
            angle = get("camera_angle_x")
            if angle is None:
                raise ValueError(f"{what}: no focal length; expected 'fl_x' or 'camera_angle_x'")
            fx = 0.5 * float(w) / math.tan(0.5 * float(angle))
        fy = get("fl_y", fx)
        cx, cy = get("cx", 0.5 * float(w)), get("cy", 0.5 * float(h))
        try:
            cy = float(h) - float(cy) if from_bottom else float(cy)
            K = torch.tensor([[float(fx), 0.0, float(cx)], [0.0, float(fy), cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{what}: intrinsics must be numbers ({e})") from None
        c2w = _homogeneous(_matrix(fr["transform_matrix"], f"{what} transform_matrix", ((4, 4), (3, 4))))
        out.append(_single(K, opengl_c2w_to_opencv_w2c(c2w), int(round(float(w))), int(round(float(h))), what))
    return out


def head_pose_matrix(rotation: Tensor, translation: Tensor, pivot: Tensor | None = None) -> Tensor:
    """Rigid head-to-parent transforms ``[..., 4, 4]`` from an axis-angle pose.

    ``x_parent = R(rotation) (x_head - pivot) + pivot + translation``. FLAME rotates its global
    pose about the root joint, so pass the shape's root joint as ``pivot`` for an exact fold;
    ``pivot=None`` rotates about the head origin.

    Args:
        rotation: ``[..., 3]`` axis-angle (radians).
        translation: ``[..., 3]`` in metres.
        pivot: ``[..., 3]`` or None.
    """
    from .rotations import axis_angle_to_matrix

    rotation = torch.as_tensor(rotation, dtype=torch.float64)
    translation = torch.as_tensor(translation, dtype=torch.float64)
    if rotation.shape[-1:] != (3,) or translation.shape[-1:] != (3,):
        raise ValueError(
            f"head pose rotation and translation must have shape [..., 3], got {list(rotation.shape)} and {list(translation.shape)}"
        )
    _check_finite("head pose rotation", rotation)
    _check_finite("head pose translation", translation)
    R = axis_angle_to_matrix(rotation)  # [..., 3, 3]
    t = translation
    if pivot is not None:
        p = torch.as_tensor(pivot, dtype=torch.float64)
        t = t + p - (R @ p.unsqueeze(-1)).squeeze(-1)
    batch = torch.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = torch.zeros(*batch, 4, 4, dtype=torch.float64)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def fold_head_pose(cameras: Cameras, head_to_world: Tensor) -> Cameras:
    """Head-centric cameras: ``w2c' = w2c @ head_to_world`` so that the head pose lives in the cameras.

    ``head_to_world [..., 4, 4]`` (or ``[..., 3, 4]``) is the rigid transform placing the canonical
    head in the cameras' world (e.g. an Ava-256 per-frame head pose, converted to metres, or
    :func:`head_pose_matrix` of a FLAME fit); it broadcasts against the camera batch.
    """
    T = torch.as_tensor(head_to_world, dtype=torch.float64)
    if T.shape[-2:] == (3, 4):
        T = torch.cat([T, torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype).expand(*T.shape[:-2], 1, 4)], dim=-2)
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"head_to_world must have shape [..., 4, 4] or [..., 3, 4], got {list(T.shape)}")
    w2c = cameras.w2c.double() @ T
    K = cameras.K.expand(*w2c.shape[:-2], 3, 3)
    try:
        return Cameras(K.clone(), w2c.to(cameras.w2c.dtype), cameras.width, cameras.height)
    except ValueError as e:
        raise ValueError(f"fold_head_pose: head_to_world must be a rigid transform ({e})") from None


def cameras_from_flame_pose(
    rotation: Tensor,
    translation: Tensor,
    K: Tensor,
    width: int,
    height: int,
    *,
    pivot: Tensor | None = None,
    camera_convention: str = "opengl",
) -> Cameras:
    """Head-centric OpenCV cameras from a FLAME fit's head pose expressed in the camera frame.

    Monocular FLAME trackers output the head's rotation (axis-angle) and translation in the
    camera's frame: ``x_cam = R (x_head - pivot) + pivot + t``. With ``camera_convention="opengl"``
    that camera frame has x right, y up, z backward (the head sits at negative z); "opencv" means
    x right, y down, z forward. Folding the pose into the camera gives
    ``w2c = diag(1, -1, -1, 1) @ [R | t']`` (OpenGL) or ``[R | t']`` (OpenCV).

    Args:
        rotation, translation: ``[..., 3]`` head pose (radians, metres).
        K: ``[..., 3, 3]`` or ``[3, 3]`` intrinsics in pixels of the ``width`` x ``height`` image.
        pivot: ``[..., 3]`` rotation centre (FLAME's root joint) or None for the head origin.
    """
    if camera_convention not in ("opengl", "opencv"):
        raise ValueError(f"camera_convention must be 'opengl' or 'opencv', got {camera_convention!r}")
    T = head_pose_matrix(rotation, translation, pivot)  # [..., 4, 4]
    if camera_convention == "opengl":
        flip = torch.tensor([*_GL_TO_CV, 1.0], dtype=T.dtype)
        T = flip[:, None] * T  # scales the rows: camera y, z flipped
    K = torch.as_tensor(K, dtype=torch.float32)
    if K.shape[-2:] != (3, 3):
        raise ValueError(f"K must have shape [..., 3, 3], got {list(K.shape)}")
    batch = torch.broadcast_shapes(K.shape[:-2], T.shape[:-2])
    return Cameras(K.expand(*batch, 3, 3).clone(), T.float().expand(*batch, 4, 4).clone(), width, height)
