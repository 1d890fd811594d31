"""Image metrics of the evaluation (paper §4.4): PSNR, SSIM, LPIPS (see ``lpips.py``), and the
face metrics CSIM / AKD (see ``faces.py``).

Every function takes images composited over the background, float in [0, 1], ``[N, 3, H, W]``,
and returns one value per image ``[N]``.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["psnr", "ssim", "mse"]


def _check(pred: Tensor, target: Tensor) -> None:
    if pred.shape != target.shape or pred.ndim != 4:
        raise ValueError(f"metrics expect two images [N, C, H, W] of one shape, got {list(pred.shape)} and {list(target.shape)}")


def mse(pred: Tensor, target: Tensor) -> Tensor:
    """Mean squared error per image ``[N]`` (computed in float64)."""
    _check(pred, target)
    return (pred.double() - target.double()).pow(2).flatten(1).mean(1)


def psnr(pred: Tensor, target: Tensor, max_val: float = 1.0, eps: float = 1e-12) -> Tensor:
    """Peak signal-to-noise ratio in dB per image ``[N]``: ``10 log10(max² / MSE)``.

    Images are clamped to [0, max_val] first (what is saved and seen). Identical images give
    ``10 log10(max² / eps)`` (= 120 dB for max 1) instead of infinity.
    """
    _check(pred, target)
    e = mse(pred.clamp(0, max_val), target.clamp(0, max_val))
    return (10.0 * torch.log10(max_val**2 / e.clamp_min(eps))).float()


def ssim(pred: Tensor, target: Tensor, window: int = 11, max_val: float = 1.0) -> Tensor:
    """Structural similarity (Wang et al. 2004: Gaussian window 11, σ 1.5, K1 .01, K2 .03) per image
    ``[N]``, averaged over channels and the valid (unpadded) window positions, as in scikit-image's
    ``gaussian_weights=True`` and the common evaluation code."""
    from kornia.metrics import ssim as kornia_ssim

    _check(pred, target)
    if min(pred.shape[-2:]) < window:
        raise ValueError(f"SSIM needs images at least {window}x{window}, got {list(pred.shape[-2:])}")
    m = kornia_ssim(pred.clamp(0, max_val).float(), target.clamp(0, max_val).float(), window, max_val=max_val, padding="valid")
    return m.flatten(1).mean(1)
