"""Dense pure-PyTorch rasterizer: every splat at every pixel, sorted by depth, with autograd.

It follows exactly the rules of the tile rasterizers (3-sigma tile footprint, alpha clamp,
1/255 skip, early stop), so it is the ground truth in tests. Cost is O(C H W N) memory and
time: meant for small scenes. Memory is bounded by processing rows of pixels at a time
(``pixel_chunk`` pixels, default about 2^24 / N; with activation checkpointing when gradients
are needed and there is more than one chunk).
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from .compositing import composite, splat_alpha
from .projection import TILE_SIZE, Projected, tile_rects

__all__ = ["rasterize_reference"]


def _pixels(width: int, rows: range, dtype, device) -> tuple[Tensor, Tensor]:
    ys = torch.arange(rows.start, rows.stop, device=device)
    xs = torch.arange(width, device=device)
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    centre = torch.stack([gx, gy], dim=-1).reshape(-1, 2).to(dtype) + 0.5  # [P, 2]
    tile = torch.stack([gx // TILE_SIZE, gy // TILE_SIZE], dim=-1).reshape(-1, 2)  # [P, 2]
    return centre, tile


def _dense_chunk(
    means2d: Tensor,  # [N, 2] in depth order
    conics: Tensor,  # [N, 3]
    opac: Tensor,  # [N]
    values: Tensor,  # [N, D]
    rect: Tensor,  # [N, 4]
    centre: Tensor,  # [P, 2]
    tile: Tensor,  # [P, 2]
) -> tuple[Tensor, Tensor]:
    delta = means2d[None, :, :] - centre[:, None, :]  # [P, N, 2]
    tx, ty = tile[:, 0:1], tile[:, 1:2]  # [P, 1]
    allowed = (tx >= rect[None, :, 0]) & (tx < rect[None, :, 2]) & (ty >= rect[None, :, 1]) & (ty < rect[None, :, 3])
    alpha = splat_alpha(delta, conics[None], opac[None], allowed)  # [P, N]
    P = alpha.shape[0]
    T0 = torch.ones(P, dtype=alpha.dtype, device=alpha.device)
    done0 = torch.zeros(P, dtype=torch.bool, device=alpha.device)
    acc, T, _ = composite(alpha, values[None], T0, done0)
    return acc, 1.0 - T


def rasterize_reference(
    proj: Projected,
    opacities: Tensor,  # [N]
    values: Tensor,  # [C, N, D] per-splat values to composite (rgb + depth)
    width: int,
    height: int,
    pixel_chunk: int | None = None,
) -> tuple[Tensor, Tensor]:
    """Dense compositing. Returns ``acc [C, H, W, D]`` (premultiplied sums) and ``alpha [C, H, W]``."""
    C, N = proj.depths.shape
    D = values.shape[-1]
    dtype, device = values.dtype, values.device
    rects = tile_rects(proj.means2d, proj.radii, width, height)  # [C, N, 4]
    if pixel_chunk is None:
        pixel_chunk = max(width, 2**24 // max(N, 1))
    rows_per_chunk = max(1, pixel_chunk // width)
    chunked = rows_per_chunk < height
    accs, alphas = [], []
    for c in range(C):
        vis = (proj.radii[c] > 0).nonzero().squeeze(1)
        order = vis[torch.sort(proj.depths[c, vis].detach(), stable=True).indices]
        args = (proj.means2d[c, order], proj.conics[c, order], opacities[order], values[c, order], rects[c, order])
        acc_rows, alpha_rows = [], []
        for r0 in range(0, height, rows_per_chunk):
            centre, tile = _pixels(width, range(r0, min(height, r0 + rows_per_chunk)), dtype, device)
            if order.numel() == 0:
                acc_rows.append(torch.zeros(centre.shape[0], D, dtype=dtype, device=device))
                alpha_rows.append(torch.zeros(centre.shape[0], dtype=dtype, device=device))
                continue
            if chunked and torch.is_grad_enabled():
                acc, alpha = checkpoint(_dense_chunk, *args, centre, tile, use_reentrant=False)
            else:
                acc, alpha = _dense_chunk(*args, centre, tile)
            acc_rows.append(acc)
            alpha_rows.append(alpha)
        accs.append(torch.cat(acc_rows).reshape(height, width, D))
        alphas.append(torch.cat(alpha_rows).reshape(height, width))
    return torch.stack(accs), torch.stack(alphas)
