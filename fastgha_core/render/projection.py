"""EWA projection of 3D Gaussians to screen space, and their 16x16-tile footprints.

This is the one definition of the splatting rules shared by the ``cpu``, ``reference`` and
``torch_tiles`` backends (the ``gsplat`` backend follows the same rules inside gsplat):

- camera-space mean ``p = R m + t``, covariance ``Σc = R (Rq S S Rq^T) R^T``;
- perspective Jacobian at ``p`` with ``x/z``, ``y/z`` clamped to 1.3x the field of view
  (gsplat's ``persp_proj``), ``Σ2d = J Σc J^T + eps2d I`` with ``eps2d = 0.3``;
- cull: ``z < NEAR_PLANE``, ``det(Σ2d) <= 0``, radius 0, or a footprint fully off-screen;
- radius = ``ceil(3 sqrt(λmax(Σ2d)))`` (3-sigma footprint, λmax with gsplat's 0.01 floor);
- a Gaussian is listed in every tile of ``[floor(mx/16 - r/16), ceil(mx/16 + r/16))`` (and the
  same in y), clamped to the image's tiles.

Pixel centres are at ``(j + 0.5, i + 0.5)`` (the K convention of ``fastgha_core.cameras``).
Everything here is differentiable with torch autograd except the integer radii and tile rects.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = [
    "TILE_SIZE",
    "NEAR_PLANE",
    "EPS2D",
    "ALPHA_MAX",
    "ALPHA_MIN",
    "T_MIN",
    "Projected",
    "quat_to_rotmat",
    "project_gaussians",
    "tile_rects",
]

TILE_SIZE = 16  # pixels per tile side
NEAR_PLANE = 0.01  # metres; Gaussians with camera z below this are culled
EPS2D = 0.3  # screen-space low-pass added to the 2D covariance (pixels^2)
ALPHA_MAX = 0.99  # per-splat alpha clamp (original 3DGS; gsplat's kernel uses 0.999)
ALPHA_MIN = 1.0 / 255.0  # splats with alpha below this at a pixel are skipped there
T_MIN = 1e-4  # a splat that would bring transmittance to <= T_MIN is not composited; the pixel stops


@dataclass
class Projected:
    """Screen-space Gaussians for C cameras.

    Attributes:
        means2d: ``[C, N, 2]`` pixel coordinates of the projected means.
        conics: ``[C, N, 3]`` inverse 2D covariance (a, b, c) = [[a, b], [b, c]].
        depths: ``[C, N]`` camera-space z.
        radii: ``[C, N]`` int32 3-sigma radius in pixels, 0 for culled Gaussians.
    """

    means2d: Tensor  # [C, N, 2]
    conics: Tensor  # [C, N, 3]
    depths: Tensor  # [C, N]
    radii: Tensor  # [C, N] int32


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices ``[..., 3, 3]`` from quaternions ``[..., 4]`` wxyz (normalised here)."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


def project_gaussians(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    K: Tensor,  # [C, 3, 3]
    w2c: Tensor,  # [C, 4, 4]
    width: int,
    height: int,
) -> Projected:
    """Project N Gaussians into C cameras (see the module docstring for the exact rules)."""
    R, t = w2c[:, :3, :3], w2c[:, :3, 3]  # [C, 3, 3], [C, 3]
    p = torch.einsum("cij,nj->cni", R, means) + t[:, None, :]  # [C, N, 3]
    Rq = quat_to_rotmat(quats)  # [N, 3, 3]
    M = Rq * scales[:, None, :]  # [N, 3, 3]  (columns scaled)
    cov3 = M @ M.transpose(-1, -2)  # [N, 3, 3]
    covc = torch.einsum("cij,njk,clk->cnil", R, cov3, R)  # [C, N, 3, 3]

    x, y, z = p.unbind(-1)  # [C, N]
    valid_z = z >= NEAR_PLANE
    zs = torch.where(valid_z, z, torch.ones_like(z))  # safe z for the culled ones
    fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]  # [C, 1]
    cx, cy = K[:, 0, 2, None], K[:, 1, 2, None]
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
    rz = 1.0 / zs
    tx = zs * torch.minimum(lim_x_pos, torch.maximum(-lim_x_neg, x * rz))
    ty = zs * torch.minimum(lim_y_pos, torch.maximum(-lim_y_neg, y * rz))
    zero = torch.zeros_like(zs)
    J = torch.stack(
        [fx * rz, zero, -fx * tx * rz * rz, zero, fy * rz, -fy * ty * rz * rz], dim=-1
    ).reshape(*zs.shape, 2, 3)  # [C, N, 2, 3]
    cov2 = J @ covc @ J.transpose(-1, -2)  # [C, N, 2, 2]
    a = cov2[..., 0, 0] + EPS2D
    b = 0.5 * (cov2[..., 0, 1] + cov2[..., 1, 0])
    c = cov2[..., 1, 1] + EPS2D
    det = a * c - b * b
    valid = valid_z & (det > 0)
    dets = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / dets, -b / dets, a / dets], dim=-1)  # [C, N, 3]
    means2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], dim=-1)  # [C, N, 2]

    with torch.no_grad():
        half = 0.5 * (a + c)
        lam = half + torch.sqrt(torch.clamp(half * half - det, min=0.01))
        radius = torch.ceil(3.0 * torch.sqrt(lam))
        mx, my = means2d[..., 0], means2d[..., 1]
        onscreen = (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
        valid = valid & onscreen & (radius > 0) & torch.isfinite(radius)
        radii = torch.where(valid, radius, torch.zeros_like(radius)).to(torch.int32)
    return Projected(means2d, conics, z, radii)


def tile_rects(means2d: Tensor, radii: Tensor, width: int, height: int) -> Tensor:
    """Tile rectangles ``[C, N, 4]`` int64 (x0, y0, x1, y1), end-exclusive, empty for culled ones."""
    tw = (width + TILE_SIZE - 1) // TILE_SIZE
    th = (height + TILE_SIZE - 1) // TILE_SIZE
    with torch.no_grad():
        r = radii.to(means2d.dtype) / TILE_SIZE
        gx, gy = means2d[..., 0] / TILE_SIZE, means2d[..., 1] / TILE_SIZE
        x0 = torch.floor(gx - r).clamp(0, tw)
        x1 = torch.ceil(gx + r).clamp(0, tw)
        y0 = torch.floor(gy - r).clamp(0, th)
        y1 = torch.ceil(gy + r).clamp(0, th)
        rect = torch.stack([x0, y0, x1, y1], dim=-1).to(torch.int64)
        rect[radii <= 0] = 0
    return rect
