"""Differentiable Gaussian rasterizer: ``render(gaussians, cameras, ...) -> RenderOutput``.

Standard 3DGS EWA splatting (gsplat "classic" rules; exact definition in ``projection.py``
and ``compositing.py``). Outputs, per camera c and pixel p, with splats i in depth order and
``w_i = alpha_i T_i`` (``T_i`` the transmittance in front of splat i, ``T_final`` behind all
composited splats):

- ``alpha = 1 - T_final = sum_i w_i``;
- ``rgb = sum_i w_i color_i + T_final * background``;
- ``depth = (sum_i w_i z_i) / max(alpha, 1e-10)``: the expected camera-space z of the visible
  surface, i.e. gsplat's ``"ED"`` mode; it is exactly 0 where nothing was composited.

Backends: ``"cpu"`` (numba tile kernels), ``"reference"`` (dense torch), ``"torch_tiles"``
(pure-torch tiles), ``"gsplat"`` (CUDA); ``"auto"`` = gsplat for CUDA tensors, else cpu.
All are differentiable w.r.t. means, quats, scales, opacities and colors.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from ..cameras import Cameras
from ..gaussians import Gaussians
from .projection import project_gaussians

__all__ = ["RenderOutput", "render", "BACKENDS"]

BACKENDS = ("auto", "cpu", "reference", "torch_tiles", "gsplat")
DEPTH_ALPHA_EPS = 1e-10  # depth = sum(w z) / max(alpha, DEPTH_ALPHA_EPS)


@dataclass
class RenderOutput:
    """Rendered images for C cameras.

    Attributes:
        rgb: ``[C, 3, H, W]`` colour composited over the background.
        alpha: ``[C, 1, H, W]`` accumulated opacity ``1 - T_final``.
        depth: ``[C, 1, H, W]`` expected camera z (0 where alpha is 0), see the module doc.
    """

    rgb: Tensor  # [C, 3, H, W]
    alpha: Tensor  # [C, 1, H, W]
    depth: Tensor  # [C, 1, H, W]


def _background(background, C: int, dtype, device) -> Tensor | None:
    """``None`` or a ``[C, 3]`` tensor."""
    if background is None:
        return None
    bg = torch.as_tensor(background, dtype=dtype, device=device)
    if bg.shape == (3,):
        return bg.expand(C, 3)
    if bg.shape == (C, 3):
        return bg
    raise ValueError(f"background must be None, 3 values or a [C={C}, 3] tensor, got shape {list(bg.shape)}")


def _finish(acc: Tensor, alpha: Tensor, bg: Tensor | None) -> RenderOutput:
    """``acc [C, H, W, 4]`` (rgb + depth sums), ``alpha [C, H, W]`` -> RenderOutput."""
    rgb = acc[..., :3]
    if bg is not None:
        rgb = rgb + (1.0 - alpha)[..., None] * bg[:, None, None, :]
    depth = acc[..., 3] / alpha.clamp_min(DEPTH_ALPHA_EPS)
    return RenderOutput(rgb.permute(0, 3, 1, 2), alpha[:, None], depth[:, None])


def _pick_backend(backend: str, device: torch.device) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {list(BACKENDS)}, got {backend!r}")
    if backend == "auto":
        return "gsplat" if device.type == "cuda" else "cpu"
    if backend != "gsplat" and device.type != "cpu":
        raise ValueError(f"backend {backend!r} runs on CPU tensors, got tensors on {device}; use 'gsplat' on CUDA")
    return backend


def render(
    gaussians: Gaussians,
    cameras: Cameras,
    width: int | None = None,
    height: int | None = None,
    background: Tensor | Sequence[float] | None = None,
    backend: str = "auto",
) -> RenderOutput:
    """Render ``gaussians`` from every camera of ``cameras``.

    Args:
        gaussians: N Gaussians (activated values).
        cameras: a batch ``[C]`` (a single camera with batch shape ``[]`` or ``[1]`` gives C = 1).
        width, height: output size; default the cameras'. A different size renders the same
            view at that resolution (the intrinsics are scaled with ``Cameras.resize``).
        background: ``None`` (black, i.e. nothing added), 3 values or ``[C, 3]``; composited
            under the splats: ``rgb += T_final * background``.
        backend: ``"auto"``, ``"cpu"``, ``"reference"``, ``"torch_tiles"`` or ``"gsplat"``.
    Returns:
        RenderOutput with ``rgb [C, 3, H, W]``, ``alpha [C, 1, H, W]``, ``depth [C, 1, H, W]``.
    """
    if not isinstance(gaussians, Gaussians):
        raise ValueError(f"gaussians must be a Gaussians, got {type(gaussians).__name__}")
    if not isinstance(cameras, Cameras):
        raise ValueError(f"cameras must be a Cameras, got {type(cameras).__name__}")
    width = cameras.width if width is None else int(width)
    height = cameras.height if height is None else int(height)
    if width <= 0 or height <= 0:
        raise ValueError(f"width and height must be positive, got {width}x{height}")
    cams = cameras.flatten()
    if (width, height) != (cams.width, cams.height):
        cams = cams.resize(width, height)
    dtype, device = gaussians.dtype, gaussians.device
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"Gaussians must be float32 or float64, got {dtype}")
    cams = cams.to(device=device, dtype=dtype)
    C = cams.K.shape[0]
    bg = _background(background, C, dtype, device)
    name = _pick_backend(backend, device)

    if name == "gsplat":
        from .gsplat_backend import render_gsplat

        rgb, alpha, depth = render_gsplat(gaussians, cams.K, cams.w2c, width, height, bg)
        return RenderOutput(rgb, alpha, depth)

    g = gaussians
    needs_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (g.means, g.quats, g.scales, g.opacities, g.colors, cams.K, cams.w2c)
    )
    rects = None
    if name == "cpu" and not needs_grad:
        from .cpu_backend import project_cpu  # numba fast path, same maths

        proj, rects = project_cpu(g.means, g.quats, g.scales, cams.K, cams.w2c, width, height, g.opacities)
    else:
        proj = project_gaussians(g.means, g.quats, g.scales, cams.K, cams.w2c, width, height)
    values = torch.cat([g.colors.expand(C, -1, 3), proj.depths[..., None]], dim=-1)  # [C, N, 4]
    if name == "cpu":
        from .cpu_backend import rasterize_cpu

        acc, alpha = rasterize_cpu(proj, g.opacities, values, width, height, rects)
    elif name == "reference":
        from .reference import rasterize_reference

        acc, alpha = rasterize_reference(proj, g.opacities, values, width, height)
    else:
        from .torch_tiles import rasterize_torch_tiles

        acc, alpha = rasterize_torch_tiles(proj, g.opacities, values, width, height)
    return _finish(acc, alpha, bg)
