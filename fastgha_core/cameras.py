"""Pinhole cameras in the OpenCV convention, and converters from dataset formats.

Conventions (DESIGN.md):
- world: head-centric canonical space in metres, +x subject's left, +y up, +z out of the face;
- camera: OpenCV, x right, y down, z forward;
- ``K [..., 3, 3]`` in pixels of the image the camera describes (``width`` x ``height``);
- ``w2c [..., 4, 4]`` world -> camera.

Pixel (u, v) = (0, 0) is the *top-left corner* of the top-left pixel, so the centre of
pixel (i, j) is at (j + 0.5, i + 0.5).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import torch
from torch import Tensor

__all__ = [
    "Cameras",
    "look_at_w2c",
    "plucker_rays",
    "farthest_viewpoint_sampling",
    "cameras_from_json",
    "cameras_to_json",
    "load_request_folder",
    "orbit_cameras",
]

_ORTHO_TOL = 1e-3


def _check_finite(name: str, t: Tensor) -> None:
    if not torch.isfinite(t).all():
        bad = (~torch.isfinite(t)).nonzero()[0].tolist()
        raise ValueError(f"{name} must be finite, got a non-finite value at index {bad}")


@dataclass(frozen=True)
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
        dtype, device = cams.K.dtype, cams.K.device
        v, u = torch.meshgrid(
            torch.arange(h, dtype=dtype, device=device) + 0.5,
            torch.arange(w, dtype=dtype, device=device) + 0.5,
            indexing="ij",
        )
        pix = torch.stack([u, v, torch.ones_like(u)], dim=-1)  # [h, w, 3]
        Kinv = torch.linalg.inv(cams.K)  # [..., 3, 3]
        d_cam = torch.einsum("...ij,hwj->...hwi", Kinv, pix)  # [..., h, w, 3]
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
    def stack(cams: Sequence["Cameras"]) -> "Cameras":
        if not cams:
            raise ValueError("need at least one camera to stack, got none")
        w, h = cams[0].width, cams[0].height
        for c in cams:
            if (c.width, c.height) != (w, h):
                raise ValueError(f"all cameras must share one image size, got {w}x{h} and {c.width}x{c.height}")
        return Cameras(
            torch.stack([c.K.reshape(3, 3) for c in cams]), torch.stack([c.w2c.reshape(4, 4) for c in cams]), w, h
        )


def look_at_w2c(
    eye: Tensor | Sequence[float],
    target: Tensor | Sequence[float] = (0.0, 0.0, 0.0),
    up: Tensor | Sequence[float] = (0.0, 1.0, 0.0),
) -> Tensor:
    """OpenCV world-to-camera matrices ``[..., 4, 4]`` for cameras at ``eye`` looking at ``target``."""
    eye = torch.as_tensor(eye, dtype=torch.float32)
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
    n = centers.shape[0]
    if not 1 <= k <= n:
        raise ValueError(f"k must be in [1, {n}] for {n} cameras, got {k}")
    dirs = centers / centers.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    if start is None:
        start = int(torch.randint(n, (1,), generator=generator))
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
    except (TypeError, ValueError) as e:
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
        raise ValueError(f"cameras must be a non-empty JSON array of camera objects, got {type(data).__name__}")
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
    if not folder.is_dir():
        raise ValueError(f"request folder {folder} does not exist or is not a folder")
    cam_file = folder / "cameras.json"
    if not cam_file.exists():
        raise ValueError(f"request folder {folder} has no cameras.json")
    images = sorted(
        p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.stem.endswith("_mask")
    )
    cams = cameras_from_json(cam_file.read_text())
    if len(images) != len(cams):
        raise ValueError(f"request folder {folder}: {len(images)} images but {len(cams)} cameras in cameras.json")
    return images, cams
