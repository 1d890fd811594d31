"""CUDA backend: ``gsplat.rasterization`` through its documented API (extra ``cuda``).

gsplat is imported lazily, only when this backend runs. Activated scales and opacities,
``viewmats`` = w2c, ``Ks`` = K, ``render_mode="RGB+ED"`` (expected depth, normalised by
alpha as in our ``depth``), ``rasterize_mode="classic"``, ``eps2d=0.3``, ``near_plane=0.01``.

Known differences from our CPU kernels (inside gsplat 1.5, not configurable): the per-splat
alpha clamp is 0.999 (ours 0.99) and the tile footprint is the opacity-aware per-axis box
(ours the 3-sigma circle); images agree except where a splat is nearly opaque or where its
faint fringe beyond 3 sigma falls outside its 3-sigma tiles.
"""

from __future__ import annotations

from torch import Tensor

from ..gaussians import Gaussians
from .projection import EPS2D, NEAR_PLANE, TILE_SIZE

__all__ = ["render_gsplat"]


def render_gsplat(
    gaussians: Gaussians,
    K: Tensor,  # [C, 3, 3]
    w2c: Tensor,  # [C, 4, 4]
    width: int,
    height: int,
    background: Tensor | None,  # [C, 3]
) -> tuple[Tensor, Tensor, Tensor]:
    """Returns ``rgb [C, 3, H, W]``, ``alpha [C, 1, H, W]``, ``depth [C, 1, H, W]``."""
    try:
        import gsplat
    except ImportError as e:  # pragma: no cover - depends on the install
        raise ValueError("backend 'gsplat' needs the 'cuda' extra (pip install 'fastgha[cuda]') and a CUDA GPU") from e
    if not gaussians.means.is_cuda:
        raise ValueError(f"backend 'gsplat' needs CUDA tensors, got tensors on {gaussians.means.device}")
    g = gaussians
    colors, alphas, _meta = gsplat.rasterization(
        means=g.means,
        quats=g.quats,
        scales=g.scales,
        opacities=g.opacities,
        colors=g.colors,
        viewmats=w2c,
        Ks=K,
        width=width,
        height=height,
        near_plane=NEAR_PLANE,
        eps2d=EPS2D,
        tile_size=TILE_SIZE,
        render_mode="RGB+ED",
        rasterize_mode="classic",
        backgrounds=background,
        packed=False,
    )  # [C, H, W, 4], [C, H, W, 1]
    rgb = colors[..., :3].permute(0, 3, 1, 2)
    depth = colors[..., 3:4].permute(0, 3, 1, 2)
    return rgb, alphas.permute(0, 3, 1, 2), depth
