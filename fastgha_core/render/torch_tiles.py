"""Pure-PyTorch tile rasterizer (the benchmark's baseline; also tested against the reference).

Same algorithm as the numba kernels, written with tensor ops: list every (splat, tile)
intersection, sort by (tile, depth), then walk the per-tile lists in chunks of ``chunk``
splats for all active tiles at once ([tiles, 256 pixels, chunk] tensors), carrying the
transmittance and the stopped flag of every pixel from chunk to chunk. Differentiable by
autograd.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .compositing import composite, splat_alpha
from .projection import TILE_SIZE, Projected, tile_rects

__all__ = ["bin_tiles_torch", "rasterize_torch_tiles"]


def bin_tiles_torch(proj: Projected, width: int, height: int) -> tuple[Tensor, Tensor, Tensor]:
    """Sorted intersections.

    Returns:
        offsets: ``[C*TH*TW + 1]`` int64, tile k's splats are ``ids[offsets[k]:offsets[k+1]]``;
        ids: ``[M]`` int64 splat index within its camera, per tile in (depth, index) order;
        tile_of: ``[M]`` int64 global tile index of each intersection.
    """
    C, N = proj.depths.shape
    tw = (width + TILE_SIZE - 1) // TILE_SIZE
    th = (height + TILE_SIZE - 1) // TILE_SIZE
    device = proj.depths.device
    rect = tile_rects(proj.means2d, proj.radii, width, height).reshape(C * N, 4)
    w = rect[:, 2] - rect[:, 0]
    h = rect[:, 3] - rect[:, 1]
    counts = (w * h).clamp_min(0)  # [C*N]
    owner = torch.repeat_interleave(torch.arange(C * N, device=device), counts)  # [M]
    start = torch.cumsum(counts, 0) - counts
    local = torch.arange(owner.numel(), device=device) - start[owner]
    tx = rect[owner, 0] + local % w[owner]
    ty = rect[owner, 1] + local // w[owner]
    cam = owner // N
    tile_of = cam * (th * tw) + ty * tw + tx  # [M]
    depth = proj.depths.detach().reshape(-1)[owner]
    o1 = torch.sort(depth, stable=True).indices
    o2 = torch.sort(tile_of[o1], stable=True).indices
    order = o1[o2]
    tile_of = tile_of[order]
    ids = owner[order] % N
    offsets = torch.zeros(C * th * tw + 1, dtype=torch.int64, device=device)
    offsets[1:] = torch.cumsum(torch.bincount(tile_of, minlength=C * th * tw), 0)
    return offsets, ids, tile_of


def rasterize_torch_tiles(
    proj: Projected,
    opacities: Tensor,  # [N]
    values: Tensor,  # [C, N, D]
    width: int,
    height: int,
    chunk: int = 32,
) -> tuple[Tensor, Tensor]:
    """Tile compositing. Returns ``acc [C, H, W, D]`` and ``alpha [C, H, W]``."""
    C, N = proj.depths.shape
    D = values.shape[-1]
    dtype, device = values.dtype, values.device
    tw = (width + TILE_SIZE - 1) // TILE_SIZE
    th = (height + TILE_SIZE - 1) // TILE_SIZE
    n_tiles = C * th * tw
    S = TILE_SIZE * TILE_SIZE
    offsets, ids, _ = bin_tiles_torch(proj, width, height)
    counts = offsets[1:] - offsets[:-1]  # [n_tiles]

    # pixel centres of every tile  [n_tiles, S, 2]
    t = torch.arange(n_tiles, device=device)
    cam_of_tile = t // (th * tw)
    ty0 = (t % (th * tw)) // tw * TILE_SIZE
    tx0 = (t % tw) * TILE_SIZE
    py, px = torch.meshgrid(torch.arange(TILE_SIZE, device=device), torch.arange(TILE_SIZE, device=device), indexing="ij")
    centre = torch.stack([tx0[:, None] + px.reshape(1, -1), ty0[:, None] + py.reshape(1, -1)], dim=-1).to(dtype) + 0.5

    m2d = proj.means2d.reshape(C * N, 2)
    con = proj.conics.reshape(C * N, 3)
    val = values.reshape(C * N, D)
    opac = opacities.repeat(C)  # [C*N]

    acc = torch.zeros(n_tiles, S, D, dtype=dtype, device=device)
    T = torch.ones(n_tiles, S, dtype=dtype, device=device)
    done = torch.zeros(n_tiles, S, dtype=torch.bool, device=device)
    max_len = int(counts.max()) if n_tiles else 0
    ar = torch.arange(chunk, device=device)
    for k0 in range(0, max_len, chunk):
        active = ((counts > k0) & ~done.all(dim=1)).nonzero().squeeze(1)  # [A]
        if active.numel() == 0:
            break
        pos = offsets[active, None] + k0 + ar[None, :]  # [A, K]
        inside = pos < offsets[active + 1, None]
        g = ids[pos.clamp(max=ids.numel() - 1)] + cam_of_tile[active, None] * N  # [A, K] flat splat index
        delta = m2d[g][:, None, :, :] - centre[active][:, :, None, :]  # [A, S, K, 2]
        alpha = splat_alpha(delta, con[g][:, None], opac[g][:, None], inside[:, None, :])  # [A, S, K]
        a_acc, a_T, a_done = composite(alpha, val[g][:, None], T[active], done[active])
        acc = acc.index_add(0, active, a_acc)
        T = T.index_copy(0, active, a_T)
        done = done.index_copy(0, active, a_done)

    def to_image(x: Tensor) -> Tensor:  # [n_tiles, S, ...] -> [C, H, W, ...]
        rest = x.shape[2:]
        x = x.reshape(C, th, tw, TILE_SIZE, TILE_SIZE, *rest).transpose(2, 3)
        return x.reshape(C, th * TILE_SIZE, tw * TILE_SIZE, *rest)[:, :height, :width]

    return to_image(acc), 1.0 - to_image(T)
