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
(docs/model-card-log.md, "The row-alternating depth"):

- ``L_dparity`` (``w_depth_parity``): the mean (Huber) amplitude of the row- and column-alternating
  parts (``depth_parity_loss``); nothing else of the map is penalised;
- ``L_dsmooth`` (``w_depth_smooth``): an edge-aware second-order smoothness, rows and columns alike
  (``depth_smoothness_loss``); it also penalises real depth steps (silhouette, nose), which
  ``L_dparity`` leaves alone.

Also off by default, against the other failure of those maps: the input views' depths disagree with
each other (~13 mm, ``bench/depth_parity.py``'s cross-view column), so the same eye lands at two
places in a novel view (the doubled eye at ~30° yaw):

- ``L_indepth`` (``w_input_depth``): Huber of each input view's depth map against that view's true
  depth along the same rays (``input_depth_loss``), where the sample has one (synthetic data:
  ``TrainingSample.input_depths``, the mesh's camera z, not degraded); 0 for samples without it;
- ``L_xview`` (``w_cross_view``): the input views' depth maps against each other, with no ground
  truth (``cross_view_depth_loss``): each view's foreground points projected into every other view and
  compared with that view's depth; one-sided (only points in front of the other view's surface
  count: the rest may be occluded); works on any data.
"""

from __future__ import annotations

import logging
import math
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
    "ray_depth_from_z",
    "input_depth_loss",
    "cross_view_depth_loss",
    "LOSS_TERMS",
]

log = logging.getLogger(__name__)

LOSS_TERMS = ("rgb", "ssim", "perc", "sil", "geo", "dsmooth", "dparity", "indepth", "xview")


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
    w_input_depth: float = 0.0  # L_indepth: each input view's depth map against its true depth (metres, Huber; 0 = off, not in the paper)
    input_depth_delta: float = 0.001  # L_indepth: metres below which the penalty is quadratic (Huber)
    w_cross_view: float = 0.0  # L_xview: the input views' depth maps against each other (metres, Huber; 0 = off, not in the paper)
    cross_view_delta: float = 0.001  # L_xview: metres below which the penalty is quadratic (Huber)
    cross_view_margin: float = 0.03  # L_xview: points farther than this (metres) in front of the other view's depth are not compared (not the same surface; bench/depth_parity.py's 3 cm)
    cross_view_range: float = 0.02  # L_xview: the other view's depth is not read where its 4 neighbouring pixels span this much (metres): a depth edge


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


def ray_depth_from_z(z: Tensor, K: Tensor) -> Tensor:
    """Camera z ``[..., H, W]`` (metres, 0 = no value) -> distance along each pixel-centre ray ``[..., H, W]``.

    ``K [..., 3, 3]``: the intrinsics of the ``W x H`` image (leading dims broadcast with ``z``'s).
    A pixel's ray is ``K^-1 (u + 0.5, v + 0.5, 1)`` (pixel centres, ``Cameras.pixel_rays``), whose
    third component is 1, so the distance is ``z * |K^-1 (u + 0.5, v + 0.5, 1)|``; 0 stays 0.
    Raises ``ValueError`` when ``z`` has fewer than 2 dims or ``K`` is not ``[..., 3, 3]``.
    """
    if z.ndim < 2 or K.shape[-2:] != (3, 3):
        raise ValueError(f"ray_depth_from_z: expected z [..., H, W] and K [..., 3, 3], got {list(z.shape)} and {list(K.shape)}")
    from ..cameras import camera_rays

    h, w = z.shape[-2:]
    return z * camera_rays(K, h, w).norm(dim=-1).to(z.dtype)


def input_depth_loss(view_depth: Tensor, true_depth: Tensor, mask: Tensor | None = None, delta: float = 0.001) -> Tensor:
    """Mean Huber error of the input views' depth maps against their true depth, in metres.

    ``view_depth [M, H, W]`` (metres along each pixel's ray, ``FastGHAOutput.view_depth`` flattened),
    ``true_depth [M, H, W]`` (metres along the same rays, ``ray_depth_from_z`` of the views' camera z;
    0 = no value), ``mask [M, H, W]`` (bool or [0, 1], > 0.5 counts; None = everywhere). Over the pixels
    with ``true_depth > 0`` inside the mask: ``mean huber(view_depth - true_depth)``, ``huber(e) =
    e^2 / (2 delta)`` below ``delta`` metres and ``|e| - delta / 2`` above (``delta`` 0: ``|e|``). With
    no such pixel it is an exact zero that still belongs to the graph. Raises ``ValueError`` on
    shapes other than the above.
    """
    if view_depth.ndim != 3 or tuple(true_depth.shape) != tuple(view_depth.shape):
        raise ValueError(f"input_depth_loss: expected view_depth and true_depth [M, H, W] of one shape, got {list(view_depth.shape)} and {list(true_depth.shape)}")
    if mask is not None and tuple(mask.shape) != tuple(view_depth.shape):
        raise ValueError(f"input_depth_loss: mask must have shape {list(view_depth.shape)}, got {list(mask.shape)}")
    valid = true_depth > 0
    if mask is not None:
        valid = valid & (mask > 0.5)
    n = valid.sum()
    if int(n) == 0:
        return view_depth.sum() * 0.0
    err = _huber(view_depth - true_depth.to(view_depth.dtype), delta)
    return (err * valid.to(err.dtype)).sum() / n.to(err.dtype)


def cross_view_depth_loss(
    view_depth: Tensor, K: Tensor, w2c: Tensor, mask: Tensor | None = None, margin: float = 0.03, delta: float = 0.001, max_range: float = 0.02
) -> Tensor:
    """Mean Huber free-space violation between the input views' depth maps, in metres (no ground truth).

    ``view_depth [B, V, H, W]`` (metres along each pixel-centre ray, ``FastGHAOutput.view_depth``),
    ``K [B, V, 3, 3]`` and ``w2c [B, V, 4, 4]`` the input cameras of the ``W x H`` images, ``mask
    [B, V, H, W]`` the foreground (bool or [0, 1], > 0.5 counts; None = everywhere).

    For every ordered pair of views ``a != b`` of a sample, each foreground pixel's point of ``a``
    (``P = centre_a + ray * depth``) is projected into ``b`` (``Cameras.project``, pixel corners at
    integers). It is compared where it lands in front of ``b``, inside the image, on ``b``'s
    foreground only (the 4 pixels of its bilinear read all on ``b``'s mask, as far as they weigh),
    away from ``b``'s depth edges (those 4 pixels' depths span less than ``max_range`` metres), with
    residual ``r = |P - centre_b| - depth_b(uv)`` (``depth_b`` read bilinearly). ``r < 0`` means ``b``
    looks through a surface that ``a`` puts there: the two maps disagree. ``r > 0`` may be a point
    that ``b`` does not see (occluded) and is not penalised, so the loss is one-sided:
    ``huber(min(r, 0))`` over the compared points with ``r > -margin`` (farther in front is not the
    same surface: a silhouette or an outlier), ``huber(e) = e^2 / (2 delta)`` below ``delta`` metres
    and ``|e| - delta / 2`` above (``delta`` 0: ``|e|``), summed and divided by the number of compared
    points of all pairs. Two views that disagree by ``e`` along a shared surface show it as ``r = -e``
    from one side of the pair, so the one-sided term still sees every disagreement. On the true depth
    of synthetic views (same timestep, 128², ``max_range`` 2 cm) it is 0.2 mm, against 11 mm for the
    shipped network's maps (L1).

    Gradients reach both depth maps (``a`` through ``P``, ``b`` through the bilinear read); the
    projected position ``uv`` is held constant (no gradient through ``b``'s slope). With no compared
    point (or one view) it is an exact zero that still belongs to the graph. Raises ``ValueError`` on
    shapes other than the above.
    """
    from ..cameras import Cameras

    if view_depth.ndim != 4:
        raise ValueError(f"cross_view_depth_loss: view_depth must have shape [B, V, H, W], got {list(view_depth.shape)}")
    b, v, h, w = view_depth.shape
    if tuple(K.shape) != (b, v, 3, 3) or tuple(w2c.shape) != (b, v, 4, 4):
        raise ValueError(f"cross_view_depth_loss: expected K [{b}, {v}, 3, 3] and w2c [{b}, {v}, 4, 4], got {list(K.shape)} and {list(w2c.shape)}")
    if mask is not None and tuple(mask.shape) != (b, v, h, w):
        raise ValueError(f"cross_view_depth_loss: mask must have shape {[b, v, h, w]}, got {list(mask.shape)}")
    total = view_depth.sum() * 0.0
    if v < 2:
        return total
    F = torch.nn.functional
    cams = Cameras(K.to(view_depth.dtype), w2c.to(view_depth.dtype), w, h)  # geometry in the maps' precision
    origins, dirs = cams.pixel_rays()  # [B, V, H, W, 3]
    pts = origins + dirs * view_depth[..., None]  # [B, V, H, W, 3]
    fg = torch.ones_like(view_depth) if mask is None else (mask > 0.5).to(view_depth.dtype)
    centers = cams.centers.to(view_depth.dtype)  # [B, V, 3]
    with torch.no_grad():  # hi/lo[y, x]: max/min depth of the pixels (y-1..y, x-1..x), [B, V, H+1, W+1]
        d = view_depth.detach().flatten(0, 1)[:, None]
        hi = F.max_pool2d(F.pad(d, (1, 1, 1, 1), value=-math.inf), 2, 1)[:, 0].unflatten(0, (b, v))
        lo = -F.max_pool2d(F.pad(-d, (1, 1, 1, 1), value=-math.inf), 2, 1)[:, 0].unflatten(0, (b, v))
    count = 0
    for a in range(v):
        p = pts[:, a].reshape(b, h * w, 3)  # [B, N, 3]
        src = fg[:, a].reshape(b, h * w) > 0.5
        for o in range(v):
            if o == a:
                continue
            cam_o = Cameras(cams.K[:, o], cams.w2c[:, o], w, h)
            with torch.no_grad():
                uv, z = cam_o.project(p.detach())  # [B, N, 2], [B, N]
                grid = torch.stack([uv[..., 0] / w * 2.0 - 1.0, uv[..., 1] / h * 2.0 - 1.0], dim=-1)[:, None]  # [B, 1, N, 2]
                inside = (grid[:, 0].abs() < 1.0).all(dim=-1) & (z > 0)
                seen = F.grid_sample(fg[:, o : o + 1], grid, mode="bilinear", padding_mode="zeros", align_corners=False)[:, 0, 0]
                ix = (uv[..., 0] + 0.5).floor().long().clamp(0, w)
                iy = (uv[..., 1] + 0.5).floor().long().clamp(0, h)
                flat = iy * (w + 1) + ix
                span = hi[:, o].reshape(b, -1).gather(1, flat) - lo[:, o].reshape(b, -1).gather(1, flat)
            d_o = F.grid_sample(view_depth[:, o : o + 1], grid, mode="bilinear", padding_mode="zeros", align_corners=False)[:, 0, 0]  # [B, N]
            r = (p - centers[:, o, None]).norm(dim=-1) - d_o
            ok = src & inside & (seen > 0.999) & (span < max_range) & (r.detach() > -margin)
            total = total + (_huber(r.clamp(max=0.0), delta) * ok.to(r.dtype)).sum()
            count += int(ok.sum())
    return total / count if count else total

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
    tensors returns ``{"rgb", "ssim", "perc", "sil", "geo", "dsmooth", "dparity", "indepth", "xview",
    "total"}`` (scalars; ``perc`` is 0 when it is off). Terms with weight 0 are not computed.
    ``dsmooth``, ``dparity``, ``indepth`` and ``xview`` need ``view_depth [M, H', W']`` (the input
    views' depth maps, ``FastGHAOutput.view_depth`` flattened, ``M = B * V``) and take their mask
    (``foreground_weight > 0.5``; ``dsmooth`` also its edges) from ``view_images [M, 3, H', W']``;
    they are 0 without ``view_depth``. ``indepth`` also needs ``view_true_depth [M, H', W']`` (metres
    along the same rays, 0 = none; ``ray_depth_from_z``), ``xview`` the input cameras ``view_K
    [B, V, 3, 3]`` and ``view_w2c [B, V, 4, 4]``; each is 0 without them.
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
        view_true_depth: Tensor | None = None,  # [M, H', W'] the input views' true depth along the rays (0 = none)
        view_K: Tensor | None = None,  # [B, V, 3, 3] input cameras (L_xview)
        view_w2c: Tensor | None = None,  # [B, V, 4, 4]
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
        fg_views = None
        if view_depth is not None and view_images is not None and (c.w_input_depth or c.w_cross_view):
            from ..model.gaussian_head import foreground_weight

            fg_views = foreground_weight(view_images)
        if c.w_input_depth and view_depth is not None and view_true_depth is not None:
            terms["indepth"] = input_depth_loss(view_depth, view_true_depth, fg_views, c.input_depth_delta)
        else:
            terms["indepth"] = zero
        if c.w_cross_view and view_depth is not None and view_K is not None and view_w2c is not None:
            bv = tuple(view_K.shape[:2])
            terms["xview"] = cross_view_depth_loss(
                view_depth.unflatten(0, bv), view_K, view_w2c, None if fg_views is None else fg_views.unflatten(0, bv), c.cross_view_margin, c.cross_view_delta, c.cross_view_range
            )
        else:
            terms["xview"] = zero
        weights = {"rgb": c.w_rgb, "ssim": c.w_ssim, "perc": c.w_perc if self.perceptual_enabled else 0.0, "sil": c.w_sil, "geo": c.w_geo}
        weights.update(dsmooth=c.w_depth_smooth, dparity=c.w_depth_parity, indepth=c.w_input_depth, xview=c.w_cross_view)
        terms["total"] = sum(weights[k] * terms[k] for k in LOSS_TERMS)
        return terms
