"""Front-to-back alpha compositing in plain torch (shared by the reference and torch_tiles).

Rules (identical in the numba kernels): per pixel, splats are visited in depth order; a splat
with ``alpha < ALPHA_MIN`` is skipped (its alpha is passed in as 0 here); a splat that would
bring the transmittance to ``<= T_MIN`` is *not* composited and the pixel stops there.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .projection import ALPHA_MAX, ALPHA_MIN, T_MIN

__all__ = ["splat_alpha", "composite"]


def splat_alpha(
    delta: Tensor,  # [..., 2] mean2d - pixel centre
    conic: Tensor,  # [..., 3]
    opacity: Tensor,  # [...]
    allowed: Tensor,  # [...] bool: the splat is listed in this pixel's tile
) -> Tensor:
    """Per-(pixel, splat) alpha ``[...]`` with the clamp and the 1/255 skip applied (skipped -> 0)."""
    dx, dy = delta[..., 0], delta[..., 1]
    sigma = 0.5 * (conic[..., 0] * dx * dx + conic[..., 2] * dy * dy) + conic[..., 1] * dx * dy
    alpha = torch.clamp(opacity * torch.exp(-sigma), max=ALPHA_MAX)
    keep = allowed & (sigma >= 0) & (alpha >= ALPHA_MIN)
    return torch.where(keep, alpha, torch.zeros_like(alpha))


def composite(
    alpha: Tensor,  # [..., K] in depth order, skipped splats = 0
    values: Tensor,  # [..., K, D]
    T0: Tensor,  # [...] transmittance before these K splats
    done0: Tensor,  # [...] bool: the pixel already stopped
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite K splats onto a running state.

    Returns:
        acc: ``[..., D]`` sum of ``w_i * values_i`` with ``w_i = alpha_i T_i``;
        T: ``[...]`` transmittance after the composited splats;
        done: ``[...]`` bool, the pixel has stopped (a splat would have brought T to <= T_MIN).
    """
    alpha = torch.where(done0[..., None], torch.zeros_like(alpha), alpha)
    one_minus = 1.0 - alpha
    P = T0[..., None] * torch.cumprod(one_minus, dim=-1)  # [..., K] inclusive
    keep = P > T_MIN  # a prefix: P is non-increasing
    T_excl = torch.cat([T0[..., None], P[..., :-1]], dim=-1)
    w = torch.where(keep, alpha * T_excl, torch.zeros_like(alpha))  # [..., K]
    acc = (w[..., None] * values).sum(dim=-2)
    T = T0 * torch.where(keep, one_minus, torch.ones_like(one_minus)).prod(dim=-1)
    done = done0 | ~keep.all(dim=-1)
    return acc, T, done
