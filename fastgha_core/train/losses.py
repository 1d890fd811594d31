"""The paper's training loss (§3.3):

    L = L_RGB + λ_SSIM L_SSIM + λ_perc L_perc + λ_sil L_sil + λ_geo L_geo

- ``L_RGB``  L1 between rendered and ground-truth images (both over ``BACKGROUND_RGB``);
- ``L_SSIM`` 1 - SSIM (kornia, Gaussian window 11, σ 1.5);
- ``L_perc`` L1 between VGG16 features (relu1_2 .. relu5_3, each layer's mean |Δ| averaged) of
  the two images; off when no VGG16 weights file is given (logged once, when the loss is built);
- ``L_sil``  L1 between the rendered alpha and the ground-truth mask;
- ``L_geo``  L1 between the rendered expected depth and the depth prior, over pixels where the prior
  is > 0 and the ground-truth mask is > 0.5.

Default weights are the paper's: λ_SSIM 1, λ_perc 0.5, λ_sil 1, λ_geo 0.5.

Not in the paper, off by default, on each *input view's* depth map (the depth along each pixel's
ray of its Gaussian, ``FastGHAOutput.view_depth``). Why: the shipped decoder learned depth maps
that alternate row by row, which draws bands on forehead and hair in novel views
(docs/model-card.md, "The row-alternating depth"):

- ``L_dparity`` (``w_depth_parity``): the mean (Huber) amplitude of the row- and column-alternating
  parts (``depth_parity_loss``); nothing else of the map is penalised;
- ``L_dsmooth`` (``w_depth_smooth``): an edge-aware second-order smoothness, rows and columns alike
  (``depth_smoothness_loss``); it also penalises real depth steps (silhouette, nose), which
  ``L_dparity`` leaves alone.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from .vgg import LPIPS_LAYERS, VGG16Features

__all__ = [
    "LossConfig",
    "FastGHALoss",
    "l1_loss",
    "ssim_loss",
    "silhouette_loss",
    "geometry_loss",
    "perceptual_loss",
    "depth_smoothness_loss",
    "depth_parity_loss",
    "LOSS_TERMS",
]

log = logging.getLogger(__name__)

LOSS_TERMS = ("rgb", "ssim", "perc", "sil", "geo", "dsmooth", "dparity")


@dataclass
class LossConfig:
    """Weights of the loss terms (paper §3.3) and their options."""

    w_rgb: float = 1.0  # L1 on RGB
    w_ssim: float = 1.0  # λ_SSIM (applied to 1 - SSIM)
    w_perc: float = 0.5  # λ_perc (VGG16 perceptual; 0 when no weights are given)
    w_sil: float = 1.0  # λ_sil (alpha vs mask)
    w_geo: float = 0.5  # λ_geo (expected depth vs depth prior)
    ssim_window: int = 11  # Gaussian window of SSIM (σ = 1.5 as in Wang et al.)
    perc_layers: tuple[int, ...] = LPIPS_LAYERS  # VGG16 ``features`` indices used by L_perc
    perc_max_size: int = 256  # images larger than this are downsampled before VGG (cost); 0 = never
    geo_mask_threshold: float = 0.5  # ground-truth mask value above which the depth prior counts
    w_depth_smooth: float = 0.0  # L_dsmooth: second-order smoothness of each input view's depth map (metres; 0 = off, not in the paper)
    w_depth_parity: float = 0.0  # L_dparity: amplitude of the row/column alternation of each input view's depth map (metres; 0 = off, not in the paper)
    depth_parity_sigma: float = 2.0  # L_dparity: pixels over which the alternation's amplitude is averaged (model/gaussian_head.py row_parity)
    depth_parity_delta: float = 0.0005  # L_dparity: metres below which the penalty is quadratic (Huber), so its gradient fades once the alternation is gone
    depth_smooth_edge: float = 5.0  # L_dsmooth's edge awareness: a pixel's weight is exp(-this * the input's colour change across it)


def _check_pair(name: str, a: Tensor, b: Tensor, channels: int | None = None) -> None:
    if a.shape != b.shape or a.ndim != 4 or (channels is not None and a.shape[1] != channels):
        want = f"[N, {channels}, H, W]" if channels else "[N, C, H, W]"
        raise ValueError(f"{name}: expected two tensors {want} of one shape, got {list(a.shape)} and {list(b.shape)}")


def l1_loss(pred: Tensor, target: Tensor) -> Tensor:
    """Mean absolute error, ``[N, C, H, W]`` x2 -> scalar."""
    _check_pair("l1_loss", pred, target)
    return (pred - target).abs().mean()


def ssim_loss(pred: Tensor, target: Tensor, window: int = 11) -> Tensor:
    """``1 - mean SSIM`` of ``[N, 3, H, W]`` images in [0, 1] (kornia, 'same' padding)."""
    from kornia.metrics import ssim

    _check_pair("ssim_loss", pred, target)
    return 1.0 - ssim(pred, target, window, max_val=1.0, padding="same").mean()


def silhouette_loss(alpha: Tensor, mask: Tensor) -> Tensor:
    """L1 between rendered alpha ``[N, 1, H, W]`` and the ground-truth mask ``[N, 1, H, W]``."""
    _check_pair("silhouette_loss", alpha, mask, channels=1)
    return (alpha - mask).abs().mean()


def geometry_loss(depth: Tensor, prior: Tensor, mask: Tensor | None = None, mask_threshold: float = 0.5) -> Tensor:
    """Masked L1 between rendered expected depth ``[N, 1, H, W]`` and the depth prior ``[N, 1, H, W]``.

    Pixels count where ``prior > 0`` (and ``mask > mask_threshold`` when a mask is given). With no
    valid pixel the loss is an exact zero that still belongs to the graph.
    """
    _check_pair("geometry_loss", depth, prior, channels=1)
    valid = prior > 0
    if mask is not None:
        _check_pair("geometry_loss (mask)", depth, mask, channels=1)
        valid = valid & (mask > mask_threshold)
    n = valid.sum()
    if int(n) == 0:
        return depth.sum() * 0.0
    diff = (depth - prior).abs() * valid.to(depth.dtype)
    return diff.sum() / n.to(depth.dtype)


def depth_smoothness_loss(depth: Tensor, images: Tensor | None = None, mask: Tensor | None = None, edge: float = 5.0) -> Tensor:
    """Edge-aware second-order smoothness of per-view depth maps, rows and columns alike.

    ``depth [N, H, W]`` (metres along each pixel's ray), ``images [N, 3, H, W]`` in [0, 1] (the input
    views the maps belong to; None = no edge weighting), ``mask [N, H, W]`` (bool or [0, 1], > 0.5
    counts; None = everywhere). For each interior pixel and each axis, the second difference
    ``|d[i-1] - 2 d[i] + d[i+1]|`` weighted by ``exp(-edge * mean_c |I[i+1] - I[i-1]| / 2)`` (weaker
    where the image has an edge across the pixel: depth may step there), over the triples whose three
    pixels lie in the mask; the loss is the weighted sum divided by the number of such triples of
    both axes (metres). With no such triple it is an exact zero that still belongs to the graph.
    A map that is linear in x and y costs 0; a row-alternating ``c * (-1)**y`` pattern costs ``4|c|``
    per vertical triple. Raises ``ValueError`` on shapes other than the above.
    """
    if depth.ndim != 3:
        raise ValueError(f"depth_smoothness_loss: depth must have shape [N, H, W], got {list(depth.shape)}")
    n, h, w = depth.shape
    if images is not None and tuple(images.shape) != (n, 3, h, w):
        raise ValueError(f"depth_smoothness_loss: images must have shape [{n}, 3, {h}, {w}], got {list(images.shape)}")
    if mask is not None and tuple(mask.shape) != (n, h, w):
        raise ValueError(f"depth_smoothness_loss: mask must have shape [{n}, {h}, {w}], got {list(mask.shape)}")
    m = torch.ones_like(depth) if mask is None else (mask > 0.5).to(depth.dtype)
    total = depth.sum() * 0.0
    count = 0
    for dim in (-2, -1):  # rows (y), then columns (x)
        if depth.shape[dim] < 3:
            continue
        lo, mid, hi = (depth.narrow(dim, k, depth.shape[dim] - 2) for k in (0, 1, 2))
        valid = m.narrow(dim, 0, depth.shape[dim] - 2) * m.narrow(dim, 1, depth.shape[dim] - 2) * m.narrow(dim, 2, depth.shape[dim] - 2)
        weight = valid
        if images is not None and edge > 0:
            change = (images.narrow(dim, 2, depth.shape[dim] - 2) - images.narrow(dim, 0, depth.shape[dim] - 2)).abs().mean(dim=1) * 0.5
            weight = valid * torch.exp(-edge * change.to(depth.dtype))
        total = total + ((lo - 2.0 * mid + hi).abs() * weight).sum()
        count += int(valid.sum())
    return total / count if count else total


def _huber(x: Tensor, delta: float) -> Tensor:
    a = x.abs()
    return torch.where(a < delta, 0.5 * a * a / delta, a - 0.5 * delta) if delta > 0 else a


def depth_parity_loss(depth: Tensor, mask: Tensor | None = None, sigma: float = 2.0, delta: float = 0.0) -> Tensor:
    """Mean Huber amplitude of the row- and column-alternating parts of per-view depth maps.

    ``depth [N, H, W]`` (metres), ``mask [N, H, W]`` (bool or [0, 1], > 0.5 counts; None = everywhere).
    ``mean huber(row_parity(depth)) + mean huber(row_parity(depth^T))`` over the mask's pixels
    (``model.gaussian_head.row_parity``: the local amplitude ``c`` of a ``c * (-1)**y`` component, and
    the same along x), ``huber(c) = c^2 / (2 delta)`` below ``delta`` metres, ``|c| - delta / 2`` above
    (``delta`` 0: ``|c|``). A map without alternation (linear in y, or in x, or any smooth map) costs
    (almost) 0, a pure ``c * (-1)**y`` pattern costs ``huber(c)``. With no mask pixel it is an exact
    zero that still belongs to the graph. Raises ``ValueError`` on shapes other than the above.
    Why Huber: an L1 penalty keeps a full-size gradient of random sign once the alternation is gone.
    """
    from ..model.gaussian_head import row_parity

    if depth.ndim != 3:
        raise ValueError(f"depth_parity_loss: depth must have shape [N, H, W], got {list(depth.shape)}")
    if mask is not None and tuple(mask.shape) != tuple(depth.shape):
        raise ValueError(f"depth_parity_loss: mask must have shape {list(depth.shape)}, got {list(mask.shape)}")
    m = torch.ones_like(depth) if mask is None else (mask > 0.5).to(depth.dtype)
    n = m.sum()
    if float(n) == 0:
        return depth.sum() * 0.0
    rows = _huber(row_parity(depth, m, sigma), delta)
    cols = _huber(row_parity(depth.transpose(-1, -2), m.transpose(-1, -2), sigma), delta).transpose(-1, -2)
    return ((rows + cols) * m).sum() / n


def perceptual_loss(vgg: VGG16Features, pred: Tensor, target: Tensor, layers=LPIPS_LAYERS, max_size: int = 0) -> Tensor:
    """Mean over ``layers`` of the mean |Δ| between VGG16 features of ``pred`` and ``target``."""
    _check_pair("perceptual_loss", pred, target, channels=3)
    if max_size and max(pred.shape[-2:]) > max_size:
        s = max_size / max(pred.shape[-2:])
        size = (max(1, round(pred.shape[-2] * s)), max(1, round(pred.shape[-1] * s)))
        pred = torch.nn.functional.interpolate(pred, size=size, mode="bilinear", antialias=True, align_corners=False)
        target = torch.nn.functional.interpolate(target, size=size, mode="bilinear", antialias=True, align_corners=False)
    f_pred = vgg(pred, layers)
    with torch.no_grad():
        f_tgt = vgg(target, layers)
    return torch.stack([(a - b).abs().mean() for a, b in zip(f_pred, f_tgt)]).mean()


class FastGHALoss(nn.Module):
    """The weighted sum of the paper's terms.

    ``forward(rgb, alpha, depth, target_rgb, target_mask, target_depth)`` with ``[N, 3|1, H, W]``
    tensors returns ``{"rgb", "ssim", "perc", "sil", "geo", "dsmooth", "dparity", "total"}`` (scalars;
    ``perc`` is 0 when it is off). Terms with weight 0 are not computed. ``dsmooth`` and ``dparity``
    need ``view_depth [M, H', W']`` (the input views' depth maps, ``FastGHAOutput.view_depth``
    flattened) and take their mask (``foreground_weight > 0.5``; ``dsmooth`` also its edges) from
    ``view_images [M, 3, H', W']``; they are 0 without ``view_depth``.
    """

    def __init__(self, config: LossConfig | None = None, vgg: VGG16Features | None = None) -> None:
        super().__init__()
        self.config = config or LossConfig()
        self.vgg = vgg
        if vgg is None and self.config.w_perc > 0:
            log.warning("perceptual loss is off: no VGG16 weights file was given (--vgg-weights); λ_perc=%g ignored", self.config.w_perc)

    @property
    def perceptual_enabled(self) -> bool:
        return self.vgg is not None and self.config.w_perc > 0

    def forward(
        self,
        rgb: Tensor,  # [N, 3, H, W] rendered over the background
        alpha: Tensor,  # [N, 1, H, W]
        depth: Tensor,  # [N, 1, H, W] expected depth
        target_rgb: Tensor,  # [N, 3, H, W]
        target_mask: Tensor,  # [N, 1, H, W]
        target_depth: Tensor,  # [N, 1, H, W] depth prior, 0 = no value
        view_depth: Tensor | None = None,  # [M, H', W'] the input views' depth maps (metres along the rays)
        view_images: Tensor | None = None,  # [M, 3, H', W'] the input views (edges and foreground of L_dsmooth)
    ) -> dict[str, Tensor]:
        c = self.config
        _check_pair("FastGHALoss rgb", rgb, target_rgb, channels=3)
        zero = rgb.sum() * 0.0
        terms: dict[str, Tensor] = {}
        terms["rgb"] = l1_loss(rgb, target_rgb) if c.w_rgb else zero
        terms["ssim"] = ssim_loss(rgb, target_rgb, c.ssim_window) if c.w_ssim else zero
        terms["perc"] = perceptual_loss(self.vgg, rgb, target_rgb, c.perc_layers, c.perc_max_size) if self.perceptual_enabled else zero
        terms["sil"] = silhouette_loss(alpha, target_mask) if c.w_sil else zero
        terms["geo"] = geometry_loss(depth, target_depth, target_mask, c.geo_mask_threshold) if c.w_geo else zero
        if c.w_depth_smooth and view_depth is not None:
            from ..model.gaussian_head import foreground_weight

            fg = None if view_images is None else foreground_weight(view_images)
            terms["dsmooth"] = depth_smoothness_loss(view_depth, view_images, fg, c.depth_smooth_edge)
        else:
            terms["dsmooth"] = zero
        if c.w_depth_parity and view_depth is not None:
            from ..model.gaussian_head import foreground_weight

            fg = None if view_images is None else foreground_weight(view_images)
            terms["dparity"] = depth_parity_loss(view_depth, fg, c.depth_parity_sigma, c.depth_parity_delta)
        else:
            terms["dparity"] = zero
        weights = {"rgb": c.w_rgb, "ssim": c.w_ssim, "perc": c.w_perc if self.perceptual_enabled else 0.0, "sil": c.w_sil, "geo": c.w_geo, "dsmooth": c.w_depth_smooth, "dparity": c.w_depth_parity}
        terms["total"] = sum(weights[k] * terms[k] for k in LOSS_TERMS)
        return terms
