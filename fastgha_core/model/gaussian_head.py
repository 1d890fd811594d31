"""Gaussian head: raw decoder maps -> activated, unprojected, fused ``Gaussians``.

This is the one place where raw channels are sliced (``GaussianLayout``). Per pixel of each view's
map ``[12+F, H, W]``:

- depth 1: distance along the pixel's ray, ``t = |c| + depth_range * tanh(raw)`` where ``|c|`` is the
  camera's distance to the world origin (the head centre), with ``depth_parity_sigma > 0`` less its
  row-alternating part (``remove_row_parity`` over the input's foreground). Zero raw output puts the point on the
  sphere around the camera through the origin, and the parameterisation works for any camera
  distance. The Gaussian centre is ``origin + t * direction`` (``Cameras.pixel_rays``). A given
  ``ray_depth [B, V, H, W]`` replaces ``t`` (the tracked head surface, ``model/surface.py``).
- rgb 3: sigmoid; with ``rgb_residual`` the raw value is a residual on the logit of the map
  pixel's own input colour, ``sigmoid(raw + logit(clamp(image, 0.01, 0.99)))``.
- quat 4: wxyz in the *camera* frame, ``normalize(raw + (1, 0, 0, 0))`` (identity at zero), rotated to
  world by the camera-to-world rotation.
- scale 3: bounded exp in units of the pixel footprint at that depth,
  ``footprint * exp(log(min) + (log(max) - log(min)) * sigmoid(raw))`` with
  ``footprint = t / f`` (metres per map pixel, ``f`` the mean focal length of the map's camera).
- opacity 1: sigmoid; with ``foreground_opacity`` multiplied by the input pixel's foreground
  weight ``clamp((1 - min_c |image_c - bg_c| ...)``, see ``foreground_weight``: inputs are matted on
  ``BACKGROUND_RGB``, so a pixel of exactly the background colour is background and makes a
  transparent Gaussian (pruned by ``reconstruct``).
- feature F: raw (the deformation MLP's input).

All views of a sample are concatenated into one set of ``V*H*W`` Gaussians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..cameras import Cameras
from ..config import GaussianHeadConfig
from ..constants import BACKGROUND_RGB
from ..gaussians import Gaussians

__all__ = [
    "GaussianLayout",
    "GaussianHead",
    "edge_source_index",
    "edge_weight",
    "foreground_weight",
    "matrix_to_quaternion",
    "quaternion_multiply",
    "remove_row_parity",
    "row_parity",
]

FOREGROUND_SOFTNESS = 0.03  # colour distance from the background at which a pixel counts as fully foreground


def foreground_weight(images: Tensor) -> Tensor:
    """Foreground weight ``[..., H, W]`` in [0, 1] of images ``[..., 3, H, W]`` matted on ``BACKGROUND_RGB``.

    ``clamp(max_c |image_c - bg_c| / FOREGROUND_SOFTNESS, 0, 1)``: 0 on the background colour, 1 once
    any channel differs by 0.03 or more, a ramp on anti-aliased matte edges.
    """
    bg = images.new_tensor(BACKGROUND_RGB).view(3, 1, 1)
    return ((images - bg).abs().amax(dim=-3) / FOREGROUND_SOFTNESS).clamp(0.0, 1.0)


def edge_weight(images: Tensor, margin_px: float) -> Tensor:
    """Opacity factor ``[..., H, W]`` in [0, 1] that fades out the pixels next to the matte's outline.

    ``images [..., 3, H, W]`` are matted on ``BACKGROUND_RGB``; a pixel is background where
    ``foreground_weight < 0.5``. With ``d`` the Euclidean distance, in pixels of ``images``, from a
    pixel's centre to the nearest background pixel's centre, the factor is
    ``clamp(d - margin_px, 0, 1)``: 0 within ``margin_px`` of the background, 1 a pixel further in.
    An image without background pixels gets 1 everywhere; ``margin_px <= 0`` gives 1 everywhere.

    Why: a pixel on a photo's matte outline mixes the wall behind the person with the face (the
    matte keeps it, its colour is part wall). On a profile view such pixels lie on the face's front
    outline (nose ridge, chin), so their Gaussians land on the midline and a frontal render shows a
    wall-coloured streak down the nose (measured on the real photo sets: the streak Gaussians are
    those within 3 px of their view's background at 128 px input).
    Raises ``ValueError`` when ``images`` is not ``[..., 3, H, W]``.
    """
    h, w = _check_images(images, "edge_weight")
    out = torch.ones((int(np.prod(images.shape[:-3], dtype=np.int64)), h, w), dtype=torch.float32)
    if margin_px > 0:
        for i, d in enumerate(_background_distances(images)):
            if d is not None:
                out[i] = (torch.from_numpy(d).float() - float(margin_px)).clamp(0.0, 1.0)
    return out.reshape(images.shape[:-3] + (h, w)).to(images.device, images.dtype)


def edge_source_index(images: Tensor, margin_px: float) -> Tensor:
    """For each pixel, the flat index ``y * W + x`` ``[..., H, W]`` (long) of the pixel whose colour it takes.

    A foreground pixel within ``margin_px`` of the background (``edge_weight < 1``, background being
    ``foreground_weight < 0.5``) takes the nearest pixel at least ``margin_px + 1`` from the background
    (the matte's interior, Euclidean distance); every other pixel, and every pixel of an image with
    no such interior, keeps its own index. The colour de-mixing counterpart of ``edge_weight``:
    outline pixels keep their coverage but lose the wall colour mixed into them.
    Raises ``ValueError`` when ``images`` is not ``[..., 3, H, W]``.
    """
    h, w = _check_images(images, "edge_source_index")
    own = torch.arange(h * w).view(h, w)
    out = own.repeat(int(np.prod(images.shape[:-3], dtype=np.int64)), 1, 1)
    if margin_px > 0:
        from scipy import ndimage

        for i, d in enumerate(_background_distances(images)):
            if d is None:
                continue
            interior = d >= margin_px + 1
            if not interior.any():
                continue
            _, (iy, ix) = ndimage.distance_transform_edt(~interior, return_indices=True)
            band = torch.from_numpy((d > 0) & ~interior)
            out[i][band] = torch.from_numpy(iy * w + ix).long()[band]
    return out.reshape(images.shape[:-3] + (h, w)).to(images.device)


def _check_images(images: Tensor, name: str) -> tuple[int, int]:
    if images.ndim < 3 or images.shape[-3] != 3:
        raise ValueError(f"{name}: images must have shape [..., 3, H, W], got {list(images.shape)}")
    return int(images.shape[-2]), int(images.shape[-1])


def _background_distances(images: Tensor) -> list[np.ndarray | None]:
    """Per image of ``images [..., 3, H, W]`` (flattened), the Euclidean distance ``[H, W]`` in pixels
    from each pixel's centre to the nearest background pixel's (``foreground_weight < 0.5``; 0 on the
    background), or None for an image without background."""
    from scipy import ndimage

    h, w = images.shape[-2:]
    bg = (foreground_weight(images.detach().float()) < 0.5).reshape(-1, h, w).cpu().numpy()
    return [ndimage.distance_transform_edt(~b) if b.any() else None for b in bg]


def _gaussian_blur_masked(x: Tensor, weight: Tensor, sigma: float) -> Tensor:
    """Normalised convolution: ``blur(x * weight) / blur(weight)`` over the last two dims ``[..., H, W]``
    with a separable Gaussian of ``sigma`` pixels (radius ``ceil(3 sigma)``, zero padding); 0 where
    no weight is within reach."""
    r = max(1, int(math.ceil(3.0 * sigma)))
    k = torch.arange(-r, r + 1, device=x.device, dtype=x.dtype)
    k = torch.exp(-(k**2) / (2.0 * sigma**2))
    k = k / k.sum()
    h, w = x.shape[-2:]
    num = torch.stack([x * weight, weight.expand_as(x)]).reshape(-1, 1, h, w)
    num = F.conv2d(F.pad(num, (0, 0, r, r)), k.view(1, 1, -1, 1))
    num = F.conv2d(F.pad(num, (r, r, 0, 0)), k.view(1, 1, 1, -1))
    num = num.reshape(2, *x.shape)
    return num[0] / num[1].clamp_min(1e-6) * (num[1] > 1e-6).to(x.dtype)


def row_parity(depth: Tensor, mask: Tensor | None = None, sigma: float = 2.0) -> Tensor:
    """Local amplitude ``c [..., H, W]`` of the row-alternating (Nyquist in y) part of ``depth [..., H, W]``.

    Model: ``depth[y, x] = s[y, x] + c[y, x] * (-1)**y`` with ``s`` and ``c`` smooth. Each pixel's
    estimate is half its vertical second difference, demodulated:
    ``(-1)**y * (depth[y] - (depth[y-1] + depth[y+1]) / 2) / 2`` (exact for a constant ``c`` on a
    linear ``s``), averaged by a normalised Gaussian blur of ``sigma`` pixels (both axes) over the
    pixels whose row and both vertical neighbours lie in ``mask`` (bool or [0, 1] ``[..., H, W]``;
    everything when None); the first and last rows count as outside. Units are those of ``depth``.
    Why: the shipped decoder's depth maps alternate row by row (docs/model-card-log.md, "The
    row-alternating depth"). Raises ``ValueError`` for fewer than 2 dims, a mask of another shape or ``sigma <= 0``.
    """
    if depth.ndim < 2:
        raise ValueError(f"row_parity: depth must have shape [..., H, W], got {list(depth.shape)}")
    if mask is not None and tuple(mask.shape) != tuple(depth.shape):
        raise ValueError(f"row_parity: mask must have the depth's shape {list(depth.shape)}, got {list(mask.shape)}")
    if not sigma > 0:
        raise ValueError(f"row_parity: sigma must be > 0 pixels, got {sigma}")
    h = depth.shape[-2]
    m = torch.ones_like(depth) if mask is None else (mask > 0.5).to(depth.dtype)
    valid = torch.zeros_like(m)
    if h >= 3:
        valid[..., 1:-1, :] = m[..., 1:-1, :] * m[..., :-2, :] * m[..., 2:, :]
    second = torch.zeros_like(depth)
    second[..., 1:-1, :] = depth[..., 1:-1, :] - 0.5 * (depth[..., :-2, :] + depth[..., 2:, :])
    sign = 1.0 - 2.0 * (torch.arange(h, device=depth.device) % 2).to(depth.dtype)  # (-1)**y
    c = 0.5 * sign[:, None] * second
    return _gaussian_blur_masked(c, valid, float(sigma))


def remove_row_parity(depth: Tensor, mask: Tensor | None = None, sigma: float = 2.0) -> Tensor:
    """``depth - (-1)**y * row_parity(depth, mask, sigma)``: the row alternation taken out, ``[..., H, W]``.

    A notch at the vertical Nyquist frequency: a pure ``c * (-1)**y`` pattern on a linear ramp goes
    exactly, a map that is linear in ``y`` stays exactly, and a vertical frequency ``w`` (radians per
    row) keeps ``1 - sin(w/2)**2 * exp(-sigma**2 (pi - w)**2 / 2)`` of its amplitude (away from the
    mask's edges): rows of period 4 keep 99.6% at ``sigma`` 2, unlike a 3-tap vertical blur that keeps
    50%. Differentiable. Arguments as ``row_parity``.
    """
    h = depth.shape[-2] if depth.ndim >= 2 else 0
    c = row_parity(depth, mask, sigma)
    sign = 1.0 - 2.0 * (torch.arange(h, device=depth.device) % 2).to(depth.dtype)
    return depth - sign[:, None] * c


@dataclass(frozen=True)
class GaussianLayout:
    """Channel slices of the raw Gaussian maps: depth 1 + rgb 3 + quat 4 + scale 3 + opacity 1 + feature F."""

    feature_dim: int = 32

    depth = slice(0, 1)
    rgb = slice(1, 4)
    quat = slice(4, 8)
    scale = slice(8, 11)
    opacity = slice(11, 12)

    @property
    def feature(self) -> slice:
        return slice(12, 12 + self.feature_dim)

    @property
    def channels(self) -> int:
        return 12 + self.feature_dim


def quaternion_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product of wxyz quaternions ``[..., 4]`` (rotation ``a`` after ``b``)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def matrix_to_quaternion(R: Tensor) -> Tensor:
    """Rotation matrices ``[..., 3, 3]`` -> unit wxyz quaternions ``[..., 4]`` (w >= 0)."""
    m = R
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    # Four candidate solutions; pick the numerically best per matrix (largest denominator).
    cands = torch.stack(
        [
            torch.stack([1 + tr, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
            torch.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
            torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], m[..., 1, 2] + m[..., 2, 1]], -1),
            torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]], -1),
        ],
        dim=-2,
    )  # [..., 4, 4]
    diag = torch.stack([1 + tr, 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], 1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]], -1)
    best = diag.argmax(-1)  # [...]
    q = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


class GaussianHead:
    """Stateless: ``GaussianHead(cfg)(maps [B, V, 12+F, H, W], cameras [B, V], images) -> list[Gaussians]``."""

    def __init__(self, cfg: GaussianHeadConfig):
        self.cfg = cfg
        self.layout = GaussianLayout(cfg.feature_dim)

    def __call__(self, maps: Tensor, cameras: Cameras, images: Tensor | None = None, ray_depth: Tensor | None = None) -> list[Gaussians]:
        """Raw maps ``[B, V, 12+F, H, W]`` (any float dtype) -> float32 Gaussians, computed without autocast.

        ``images [B, V, 3, H, W]`` (the inputs, at the maps' size) are required when ``cfg.rgb_residual``.
        ``ray_depth [B, V, H, W]`` (metres along each pixel's ray), when given, replaces the predicted depth;
        a callable ``ray_depth(t_pred [B, V, H, W]) -> [B, V, H, W]`` replaces it by a function of it.
        """
        with torch.autocast(device_type=maps.device.type, enabled=False):
            return self._activate(maps.float(), cameras, images, ray_depth)

    def _activate(self, maps: Tensor, cameras: Cameras, images: Tensor | None = None, ray_depth: Tensor | None = None) -> list[Gaussians]:
        lay = self.layout
        if maps.ndim != 5 or maps.shape[2] != lay.channels:
            raise ValueError(f"GaussianHead: maps must have shape [B, V, {lay.channels}, H, W], got {list(maps.shape)}")
        b, v, _, h, w = maps.shape
        if tuple(cameras.batch_shape) != (b, v):
            raise ValueError(f"GaussianHead: cameras must have batch shape [{b}, {v}], got {list(cameras.batch_shape)}")
        cams = cameras.to(dtype=maps.dtype)
        x = maps.permute(0, 1, 3, 4, 2)  # [B, V, H, W, C]
        origins, dirs = cams.pixel_rays(h, w)  # [B, V, H, W, 3] each
        dist = cams.centers.norm(dim=-1)[..., None, None, None]  # [B, V, 1, 1, 1]
        if ray_depth is None or callable(ray_depth):
            t = dist + self.cfg.depth_range * torch.tanh(x[..., lay.depth])  # [B, V, H, W, 1]
            if self.cfg.depth_parity_sigma > 0:  # the decoder's row alternation taken out (docs/model-card-log.md)
                fg = None if images is None or tuple(images.shape) != (b, v, 3, h, w) else foreground_weight(images.float())
                t = remove_row_parity(t[..., 0], fg, self.cfg.depth_parity_sigma)[..., None]
            if ray_depth is not None:  # a function of the predicted depth (model/surface.py: blend)
                t = ray_depth(t[..., 0]).to(maps)[..., None]
        else:
            if tuple(ray_depth.shape) != (b, v, h, w):
                raise ValueError(f"GaussianHead: ray_depth must have shape [{b}, {v}, {h}, {w}], got {list(ray_depth.shape)}")
            t = ray_depth.to(maps)[..., None]
        means = origins + t * dirs  # [B, V, H, W, 3]

        focal = cams.resize(w, h).K[..., [0, 1], [0, 1]].mean(-1)[..., None, None, None]  # [B, V, 1, 1, 1]
        lo, hi = math.log(self.cfg.min_scale_px), math.log(self.cfg.max_scale_px)
        scales = (t / focal) * torch.exp(lo + (hi - lo) * torch.sigmoid(x[..., lay.scale]))  # [B, V, H, W, 3]

        q_cam = x[..., lay.quat] + x.new_tensor([1.0, 0.0, 0.0, 0.0])
        q_cam = F.normalize(q_cam, dim=-1, eps=1e-8)  # [B, V, H, W, 4]
        q_c2w = matrix_to_quaternion(cams.c2w[..., :3, :3])[..., None, None, :]  # [B, V, 1, 1, 4]
        quats = F.normalize(quaternion_multiply(q_c2w.expand_as(q_cam), q_cam), dim=-1)

        raw_rgb = x[..., lay.rgb]  # [B, V, H, W, 3]
        if self.cfg.rgb_residual:
            if images is None or tuple(images.shape) != (b, v, 3, h, w):
                got = None if images is None else list(images.shape)
                raise ValueError(f"GaussianHead: rgb_residual needs the input images [{b}, {v}, 3, {h}, {w}], got {got}")
            raw_rgb = raw_rgb + torch.logit(images.float().clamp(0.01, 0.99)).permute(0, 1, 3, 4, 2)
        colors = torch.sigmoid(raw_rgb)
        opac = torch.sigmoid(x[..., lay.opacity])[..., 0]  # [B, V, H, W]
        if self.cfg.foreground_opacity:
            if images is None or tuple(images.shape) != (b, v, 3, h, w):
                got = None if images is None else list(images.shape)
                raise ValueError(f"GaussianHead: foreground_opacity needs the input images [{b}, {v}, 3, {h}, {w}], got {got}")
            opac = opac * foreground_weight(images.float())
        feats = x[..., lay.feature]
        out = []
        for i in range(b):
            out.append(
                Gaussians(
                    means=means[i].reshape(-1, 3),  # [V*H*W, 3]
                    quats=quats[i].reshape(-1, 4),
                    scales=scales[i].reshape(-1, 3),
                    opacities=opac[i].reshape(-1),
                    colors=colors[i].reshape(-1, 3),
                    features=feats[i].reshape(-1, lay.feature_dim),
                )
            )
        return out
