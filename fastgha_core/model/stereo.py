"""Photo-consistency correction of the on-head pixels' depth: a plane sweep bounded around the tracked surface.

Why (issue 17, real photo sets): in the ``"replace"`` path every input pixel that hits the tracked
ICT-FaceKit head (``model/surface.py``, ``SurfaceDepth.hit``) gets its Gaussian at that mesh's
distance along the ray. The mesh is fitted to landmarks, so its nose, cheeks and brows are the
model's, not the person's, by several millimetres, and each photo's pose carries a residual error:
two views then put the same eye corner at two places and a novel view shows it twice. The photos
themselves say where a feature is when two of them see it: this module moves each hit pixel's
point along its own ray to where the other views' photos agree best with it, within a band around
the surface.

How (``stereo_ray_depth``), per input view ``i``:

- hypotheses: offsets ``delta_k`` along the pixel's unit ray, ``-range_m .. +range_m`` in steps of
  ``step_m``, around the surface distance ``t``;
- the other views ``j`` that see the pixel's surface point: it projects inside view ``j``, in front
  of it, on ``j``'s own head pixels and matte, and within ``occlusion_m`` of ``j``'s own surface
  distance there (else something is in front of it: the nose, the other cheek);
- for each hypothesis the point ``o + (t + delta_k) d`` is projected into ``j`` and ``j``'s
  band-passed grey image (luma minus its Gaussian blur taken inside the matte: exposure, white
  balance and slow shading differ between photos, and a matte's outline is no texture) is sampled
  there (bilinear); the score is the normalised cross-correlation (NCC)
  between view ``i``'s band-passed image and that warped one over a ``window x window`` patch,
  each pixel weighted by its visibility in ``j`` (fronto-parallel to the surface: neighbours keep
  the same offset, a surface sweep); NCC is unchanged by gain and bias;
- the cost ``1 - NCC`` is averaged over the views that see the pixel, aggregated over an
  ``aggregate x aggregate`` box of hit pixels (the smoothness term: one offset per small patch of
  skin), plus ``prior * (delta / range)^2`` that favours the surface;
- the offset is the argmin, refined to a sub-step by a parabola through its neighbours;
- fallback to the surface distance (offset 0) where no other view sees the pixel, where view
  ``i``'s patch is flat (band-passed standard deviation below ``min_texture``), or where the best
  cost is not at least ``min_gain`` below the cost at offset 0;
- the chosen offsets are finally averaged over a ``smooth x smooth`` box of hit pixels (fallbacks
  count as 0), so isolated picks do not become speckle and accepted patches join the surface
  without a step.

The different expressions of the photos are ignored (the world is taken as rigid between views);
where a photo's mouth or eyes move, the photos disagree at every offset and the fallback keeps
the surface. Units: metres along each pixel's unit ray (``Cameras.pixel_rays``, the quantity
``GaussianHead`` calls ``t``); the cameras' world is the head frame (``model/surface.py``).
``FastGHA.reconstruct`` applies it to the real views' hit pixels when
``GaussianHeadConfig.stereo_depth_mm > 0``. Off by default: on held-out synthetic subjects it
brings the bare face's depth closer to the truth (mean error 3.70 -> 3.16 mm), but on the real photo
sets it neither sharpens the eyes nor raises a leave-one-out mean (docs/model-card-log.md, "Photo-
consistency depth of the on-head pixels").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from ..cameras import Cameras

__all__ = ["StereoConfig", "StereoResult", "band_pass", "ncc_cost_volume", "stereo_ray_depth"]


@dataclass
class StereoConfig:
    """Parameters of ``stereo_ray_depth`` (module doc). Lengths in metres, sizes in pixels at an
    input side of 128 (scaled with the image)."""

    range_m: float = 0.012  # offsets tested: -range .. +range along the ray
    step_m: float = 0.002  # spacing of the offsets
    window: int = 5  # NCC patch side (odd)
    aggregate: int = 25  # cost aggregation box side (odd; 1 = none)
    blur_px: float = 2.0  # band-pass: luma minus its Gaussian blur of this sigma
    min_texture: float = 0.01  # fallback below this band-passed patch standard deviation (image units 0..1)
    min_gain: float = 0.1  # fallback unless the best cost is this much below the cost at offset 0
    prior: float = 0.05  # cost added at +-range (quadratic in the offset)
    occlusion_m: float = 0.015  # a view sees a surface point within this of its own surface distance
    smooth: int = 9  # final box average of the offsets over hit pixels (odd; fallbacks count as 0)

    def __post_init__(self) -> None:
        if not (self.range_m > 0 and self.step_m > 0 and self.step_m <= self.range_m):
            raise ValueError(f"StereoConfig: need range_m > 0 and 0 < step_m <= range_m, got {self.range_m}, {self.step_m}")
        if min(self.window, self.aggregate, self.smooth) < 1 or self.window % 2 == 0 or self.aggregate % 2 == 0 or self.smooth % 2 == 0:
            raise ValueError(f"StereoConfig: window, aggregate and smooth must be odd and >= 1, got {self.window}, {self.aggregate}, {self.smooth}")

    def offsets(self) -> Tensor:
        """``[K]`` the tested offsets (metres), symmetric about 0 and containing it."""
        n = round(self.range_m / self.step_m)
        return torch.arange(-n, n + 1, dtype=torch.float32) * self.step_m


@dataclass
class StereoResult:
    """Output of ``stereo_ray_depth``."""

    t: Tensor  # [V, H, W] corrected distances (metres); unchanged off the hit pixels and at fallbacks
    offset: Tensor  # [V, H, W] t - t_surface (metres)
    accepted: Tensor  # [V, H, W] bool: a hit pixel whose offset came from the photos (before the final smoothing)
    seen: Tensor  # [V, H, W] int: how many other views see the pixel's surface point


def _scaled(px: float, size: int) -> float:
    return px * size / 128.0


def _box(x: Tensor, k: int) -> Tensor:
    """Sum over a ``k x k`` box (zero padded) of ``x [N, H, W]``."""
    if k <= 1:
        return x
    return F.avg_pool2d(x[:, None], k, stride=1, padding=k // 2, count_include_pad=True)[:, 0] * (k * k)


def band_pass(images: Tensor, blur_px: float, mask: Tensor | None = None) -> Tensor:
    """``[V, H, W]`` luma (Rec. 601) of ``images [V, 3, H, W]`` minus its Gaussian blur of sigma
    ``blur_px`` pixels: the fine texture (pores, lashes, brow hairs, eye corners) without the
    exposure and shading differences between photos. With ``mask [V, H, W]`` (0..1, the matte) the
    blur is a normalised convolution over the masked pixels only and the result is 0 outside, so a
    matte's outline (an occluding contour, different in every view) is not taken for texture."""
    from kornia.color import rgb_to_grayscale
    from kornia.filters import gaussian_blur2d

    g = rgb_to_grayscale(images.float())[:, 0]
    m = torch.ones_like(g) if mask is None else mask.float()
    if blur_px <= 0:
        return (g - (g * m).sum(dim=(-1, -2), keepdim=True) / m.sum(dim=(-1, -2), keepdim=True).clamp_min(1e-6)) * m
    r = max(1, int(3 * blur_px + 0.5))

    def blur(a: Tensor) -> Tensor:
        return gaussian_blur2d(a[:, None], (2 * r + 1, 2 * r + 1), (blur_px, blur_px), border_type="reflect")[:, 0]

    low = blur(g * m) / blur(m).clamp_min(1e-6)
    return (g - low) * (m > 0.5)


def _sample(img: Tensor, uv: Tensor, mode: str = "bilinear") -> Tensor:
    """``img [C, H, W]`` at pixel coordinates ``uv [..., 2]`` (corner convention: the centre of pixel
    ``(x, y)`` is ``(x + 0.5, y + 0.5)``); zero outside. Returns ``[C, ...]``."""
    h, w = img.shape[-2:]
    g = torch.stack([uv[..., 0] * (2.0 / w) - 1.0, uv[..., 1] * (2.0 / h) - 1.0], -1)
    shp = g.shape[:-1]
    out = F.grid_sample(img[None].float(), g.reshape(1, 1, -1, 2), mode=mode, padding_mode="zeros", align_corners=False)
    return out[0, :, 0].reshape(img.shape[0], *shp)


def ncc_cost_volume(a: Tensor, b: Tensor, weight: Tensor, window: int, eps: float = 1e-6) -> tuple[Tensor, Tensor]:
    """Weighted NCC cost of ``a [H, W]`` against each of ``b [K, H, W]`` over ``window x window`` patches.

    Each pixel of the patch counts with ``weight [K, H, W]`` (0..1: e.g. whether the other view sees
    it); ``a`` is the reference patch, ``b[k]`` the other view's image warped by hypothesis ``k``.
    Returns ``(cost [K, H, W] = 1 - NCC in [0, 2], weight sum [K, H, W])``; where the weight sum is
    below 1 or either patch is flat (variance < ``eps``) the cost is 1 (no evidence).
    """
    w = weight.float()
    a = a.float().expand_as(b)
    sw = _box(w, window)
    safe = sw.clamp_min(1e-6)
    ma, mb = _box(w * a, window) / safe, _box(w * b, window) / safe
    va = (_box(w * a * a, window) / safe - ma * ma).clamp_min(0)
    vb = (_box(w * b * b, window) / safe - mb * mb).clamp_min(0)
    cov = _box(w * a * b, window) / safe - ma * mb
    ok = (sw >= 1.0) & (va > eps) & (vb > eps)
    ncc = torch.where(ok, cov / torch.sqrt(va * vb).clamp_min(eps), torch.zeros_like(cov))
    return torch.where(ok, 1.0 - ncc.clamp(-1, 1), torch.ones_like(ncc)), sw


def _visible_in(j: int, pts: Tensor, cams: Cameras, t: Tensor, hit: Tensor, fg: Tensor, occlusion_m: float) -> Tensor:
    """``[...]`` bool: world points ``pts [..., 3]`` that view ``j`` sees on its own head: in front,
    inside the image, on a hit pixel inside its matte, and no more than ``occlusion_m`` from its own
    surface distance there (nearest pixel)."""
    cj = cams[j]
    flat = pts.reshape(-1, 3)
    uv, z = cj.project(flat)
    dist = (flat - cj.centers).norm(dim=-1)
    h, w = t.shape[-2:]
    x, y = torch.floor(uv[:, 0]).long(), torch.floor(uv[:, 1]).long()
    inside = (z > 1e-6) & (x >= 0) & (x < w) & (y >= 0) & (y < h)
    xc, yc = x.clamp(0, w - 1), y.clamp(0, h - 1)
    ok = inside & hit[j][yc, xc] & (fg[j][yc, xc] > 0.5) & ((dist - t[j][yc, xc]).abs() < occlusion_m)
    return ok.reshape(pts.shape[:-1])


def stereo_ray_depth(
    images: Tensor, cameras: Cameras, t: Tensor, hit: Tensor, fg: Tensor | None = None, config: StereoConfig | None = None, where: Tensor | None = None
) -> StereoResult:
    """Move the hit pixels' surface distances along their rays to where the photos agree (module doc).

    Args:
        images: ``[V, 3, H, W]`` the input views in [0, 1] (matted).
        cameras: ``Cameras [V]`` of the ``W x H`` views (world = the head frame).
        t: ``[V, H, W]`` surface distances along each pixel's unit ray (metres), ``SurfaceDepth.t``.
        hit: ``[V, H, W]`` bool, the pixels whose ray hits the head (``SurfaceDepth.hit``); only
            these change.
        fg: ``[V, H, W]`` matte (> 0.5 = the person); default: all foreground.
        config: ``StereoConfig``; default ``StereoConfig()``.
        where: ``[V, H, W]`` bool, the hit pixels to correct (e.g. ``SurfaceDepth.face_hit``, the
            bare face); default all of ``hit``. The others keep ``t`` but still count as surface for
            the other views' visibility test.
    Returns:
        ``StereoResult`` (``t`` on the CPU, float32).
    Raises:
        ValueError: when a shape disagrees with the cameras' batch and size.
    """
    cfg = config or StereoConfig()
    cams = cameras.flatten().to("cpu", torch.float32)
    v, h, w = len(cams.K), cams.height, cams.width
    if tuple(t.shape) != (v, h, w) or tuple(hit.shape) != (v, h, w) or tuple(images.shape) != (v, 3, h, w):
        raise ValueError(f"stereo_ray_depth: need images [{v}, 3, {h}, {w}], t and hit [{v}, {h}, {w}]; got {list(images.shape)}, {list(t.shape)}, {list(hit.shape)}")
    t = t.detach().float().cpu()
    hit = hit.detach().bool().cpu()
    fg = torch.ones(v, h, w) if fg is None else fg.detach().float().cpu()
    if fg.shape != t.shape or (where is not None and tuple(where.shape) != (v, h, w)):
        raise ValueError(f"stereo_ray_depth: fg and where must have shape {list(t.shape)}, got {list(fg.shape)} and {None if where is None else list(where.shape)}")
    todo = hit if where is None else (where.detach().bool().cpu() & hit)
    size = max(h, w)
    win = max(1, round(_scaled(cfg.window, size)) | 1)
    agg = max(1, round(_scaled(cfg.aggregate, size)) | 1)
    bp = band_pass(images.detach().float().cpu(), _scaled(cfg.blur_px, size), fg)
    offs = cfg.offsets()
    k0 = len(offs) // 2
    o, d = cams.pixel_rays()
    out_off = torch.zeros(v, h, w)
    accepted = torch.zeros(v, h, w, dtype=torch.bool)
    seen = torch.zeros(v, h, w, dtype=torch.int32)
    prior = cfg.prior * (offs / cfg.range_m) ** 2
    for i in range(v):
        if v < 2 or not todo[i].any():
            continue
        surf = o[i] + t[i][..., None] * d[i]  # [H, W, 3]
        pts = o[i][None] + (t[i][None] + offs.view(-1, 1, 1))[..., None] * d[i][None]  # [K, H, W, 3]
        cost_sum = torch.zeros(len(offs), h, w)
        n_views = torch.zeros(h, w)
        for j in range(v):
            if j == i:
                continue
            vis = _visible_in(j, surf, cams, t, hit, fg, cfg.occlusion_m) & todo[i] & (fg[i] > 0.5)  # [H, W]
            if not vis.any():
                continue
            uv, _ = cams[j].project(pts.reshape(-1, 3))
            warped = _sample(bp[j][None], uv.reshape(len(offs), h, w, 2))[0]  # [K, H, W]
            cost, _ = ncc_cost_volume(bp[i], warped, vis.float().expand(len(offs), h, w), win)
            cost_sum += cost * vis
            n_views += vis.float()
        seen[i] = n_views.int()
        any_view = n_views > 0
        if not any_view.any():
            continue
        cost = cost_sum / n_views.clamp_min(1)  # [K, H, W], 1 (no evidence) where no view
        wgt = (todo[i] & any_view).float()
        cost = _box(cost * wgt, agg) / _box(wgt[None], agg).clamp_min(1e-6) + prior.view(-1, 1, 1)
        best = cost.argmin(dim=0)  # [H, W]
        c_best = cost.gather(0, best[None])[0]
        # sub-step: a parabola through the best cost and its two neighbours
        lo, hi = (best - 1).clamp(0, len(offs) - 1), (best + 1).clamp(0, len(offs) - 1)
        c_lo, c_hi = cost.gather(0, lo[None])[0], cost.gather(0, hi[None])[0]
        den = c_lo - 2 * c_best + c_hi
        frac = torch.where((best > 0) & (best < len(offs) - 1) & (den > 1e-9), 0.5 * (c_lo - c_hi) / den.clamp_min(1e-9), torch.zeros_like(den))
        off = offs[best] + frac.clamp(-0.5, 0.5) * cfg.step_m
        # flat patches: the band-passed standard deviation of view i's own window
        hw = todo[i].float()
        m1 = _box((bp[i] * hw)[None], win)[0] / _box(hw[None], win)[0].clamp_min(1e-6)
        m2 = _box((bp[i] ** 2 * hw)[None], win)[0] / _box(hw[None], win)[0].clamp_min(1e-6)
        texture = (m2 - m1 * m1).clamp_min(0).sqrt()
        ok = todo[i] & any_view & (texture >= cfg.min_texture) & (cost[k0] - c_best >= cfg.min_gain)
        accepted[i] = ok
        out_off[i] = torch.where(ok, off, torch.zeros_like(off))
    # final smoothing: the mean of the offsets over a box of hit pixels (fallbacks count as 0)
    hf = todo.float()
    sm_px = max(1, round(_scaled(cfg.smooth, size)) | 1)
    sm = _box(out_off * hf, sm_px) / _box(hf, sm_px).clamp_min(1e-6)
    sm = torch.where(todo, sm, torch.zeros_like(sm))
    return StereoResult(t=t + sm, offset=sm, accepted=accepted, seen=seen)
