"""Test-time refinement: a bounded optimisation of a reconstructed avatar against its own input photos.

The feed-forward pass (``FastGHA.reconstruct``) predicts one set of pixel-aligned Gaussians per input
view. Where the views (or the cameras tracking gave them) disagree, the avatar shows two overlapping
faces and reproduces its inputs poorly. ``refine_avatar`` then runs ``RefineConfig.steps`` steps of
Adam on small corrections, rendering every input view with its known expression and comparing it
with the photo:

- per Gaussian: an opacity logit offset, a colour logit offset, an isotropic log-scale offset
  (``RefineConfig.lr_scale``; its three scales multiplied by ``exp(d)``) and, off by default, a
  displacement along its own pixel ray (``lr_depth``, metres) or a free 3D offset (``lr_xyz``,
  metres); rotation and the per-Gaussian features stay as predicted. With
  ``RefineConfig.smooth_grid`` > 0 the opacity, colour and ray offsets live on a coarse grid per
  view instead, sampled at each Gaussian's pixel in its own view, so neighbouring
  Gaussians move together (the default before 2026-11-30: it held the colours to the 128² detail of
  the network's input, while the 256² photos show more);
- per view (``RefineConfig.optimize_cameras``, off by default): a camera correction
  ``w2c <- [exp(omega) | tau] w2c`` (rotation vector ``omega`` in radians, translation ``tau`` in
  metres, both in the camera frame), so that pose error left by tracking can be absorbed by the
  camera instead of distorting the head. Off by default because, with exact cameras, the
  corrections absorb the avatar's shape error instead (all cameras drift towards the head).

Loss per view, averaged over the views rendered in the step (``RefineConfig.views_per_step`` of
them, in turn; images at ``RefineConfig.resolution``, or ``coarse_resolution`` in the first
``coarse_fraction`` of the steps):

- photometric: L1 between the render over ``BACKGROUND_RGB`` and the matted photo;
- silhouette: squared error between the rendered alpha and the mask;
- cross-view depth consistency: every Gaussian of view ``v`` is pulled towards the depth that the
  whole avatar renders at its pixel in view ``v`` (a stop-gradient target), where that pixel is
  foreground, so the surfaces predicted from different views merge into one;
- regularisers keeping the corrections near the network's prediction: ``(dt / depth_sigma)^2``,
  squared logit and log-scale offsets, ``(|d_xyz| / xyz_sigma)^2``,
  ``(|omega| / rot_sigma)^2 + (|tau| / trans_sigma)^2``.

Each input view is drawn as ``FastGHA.animate`` draws a frame at its expression
(``RefineConfig.match_animation``): the deformation MLP's and the expression prior's displacement,
the prior's shading factor on the colours, and the avatar's appended Gaussians (back-of-head shell,
mouth interior, lids, with their expression gates) as fixed Gaussians that are not refined. The
refined avatar keeps the feed-forward avatar's binding and appended Gaussians
(``RefineConfig.keep_binding``), so it animates as it was refined.

The deformation to each input's expression is evaluated once at the predicted centres and kept fixed
(the corrections are small), and the render uses the rasterizer's float32 gradient path, with the
screen-space covariances of the current positions treated as constants except for the isotropic
scale factor (gradients flow through the projected centres and depths, and through the conics to
the scale offsets, ``scaled_conics``), which keeps a 4-view step at 256^2 in the tens of milliseconds.

This runs once when an avatar is created; the per-frame path is unchanged (the refined avatar is an
ordinary ``CanonicalAvatar``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from ..cameras import Cameras
from ..constants import BACKGROUND_RGB
from ..gaussians import Gaussians
from ..model.avatar import CanonicalAvatar

__all__ = ["RefineConfig", "RefineResult", "REFINE_PRESETS", "refine_preset_for", "refine_config_for", "refine_avatar", "prepare_targets", "source_views", "masked_psnr", "lr_factor", "scaled_conics", "realign_to_pixels"]


@dataclass
class RefineConfig:
    """Refinement settings (presets in ``REFINE_PRESETS``).

    Attributes:
        steps: Adam steps; 0 = no refinement (``refine_avatar`` returns the avatar unchanged).
        resolution: side in pixels of the square target images the views are rendered at in the
            last ``1 - coarse_fraction`` of the steps.
        coarse_resolution: side of the targets in the first ``coarse_fraction`` of the steps (cheaper
            steps, but at the ``input_size`` of the network's maps they cannot fit the photos' finer
            detail: 0 coarse steps by default).
        lr_depth: step size of the ray displacement (metres; 0 = depth stays as predicted, the
            default: it measured better in novel views); lr_opacity / lr_color: of the logits;
        lr_rotation (radians) / lr_translation (metres): of the camera corrections.
        w_photo, w_silhouette, w_depth: weights of the photometric, silhouette and depth terms.
        depth_sigma: metres; the ray displacement costs ``(dt / depth_sigma)^2`` times ``w_reg_depth``.
        w_reg_depth, w_reg_opacity, w_reg_color, w_reg_camera: regulariser weights.
        rot_sigma (radians), trans_sigma (metres): scales of the camera regulariser.
        optimize_cameras: learn the per-view camera corrections.
        noise_floor: Adam's epsilon of the per-Gaussian groups, in units of the median gradient
            magnitude of the first step (0 = plain Adam, where every Gaussian moves by about the
            step size whatever its gradient).
        smooth_grid: 0 = one correction per Gaussian; G > 0 = the corrections are ``G x G`` maps per
            view, sampled bilinearly at each Gaussian's pixel in its own view (smooth corrections).
        realign: before optimising, move every Gaussian (and its colour) back by the deformation of
            its own view's expression, so that deformed to that expression it lies on its pixel ray
            again with its pixel's colour (needs ``expressions``).
        realign_cap: metres; > 0 moves every Gaussian, before optimising, so that the deformation
            MLP's residual at its own view's expression takes it back to where the network put it
            (``realign_to_pixels``: three fixed-point steps; the expression prior's displacement is
            left alone, reconstruction undoes it), except Gaussians that would move further than
            this, which stay (the fixed point does not converge for them). 0 = off (the default).
        prune_opacity: drop Gaussians whose refined opacity falls below this (0 = keep all; nothing
            is dropped when ``lr_opacity`` is 0).
        phase_schedule: run the step-size schedule (constant, then a linear decay to 10% over the
            second half) separately in the coarse and in the fine phase, so the fine steps start
            at the full step size (False: one schedule over all steps, the fine steps then all
            fall in its decay).
        views_per_step: render this many input views per step, in turn (0 = all of them every step);
            the loss is averaged over the views rendered.
        lr_xyz: step size (metres) of a free 3D offset of every Gaussian (0 = off); it costs
            ``w_reg_xyz * (|d| / xyz_sigma)^2`` (``xyz_sigma`` in metres). Per Gaussian, also with
            ``smooth_grid``.
        lr_scale: step size of an isotropic log-scale correction of every Gaussian (0 = off; the
            3D scales are multiplied by ``exp(d)``), costing ``w_reg_scale * d^2``. Per Gaussian, also
            with ``smooth_grid``.
        match_animation: render the inputs as ``FastGHA.animate`` draws a frame: the expression
            prior's shading factor on the colours, and the avatar's appended Gaussians (back-of-head
            shell, mouth interior, lids, with their expression gates) drawn as fixed Gaussians,
            and, on avatars with per-view data (a tracked head surface), each input view drawn as
            ``animate(..., camera=)`` draws a frame at its camera: the view-dependent blending and
            the off-head Gaussians pushed under (``FastGHA.blend_views``). False: the network's
            Gaussians alone, without the shading or the blending.
        photo_in_mask: the photometric term counts only the pixels inside the photo's mask
            (``mask > 0.5``), so the background at the head's outline does not pull the colours of the
            Gaussians there (False: every pixel, the render over ``BACKGROUND_RGB`` against the matted
            photo).
        keep_binding: the refined avatar keeps the feed-forward avatar's expression-prior binding
            and appended Gaussians (shell, mouth interior, lids), so it animates exactly as the
            refinement rendered it (False: the head is refitted to the refined Gaussians and the
            appended Gaussians are rebuilt, ``FastGHA.attach_prior``).
        cheek_shell: when the refinement changes opacities or scales (``lr_opacity`` or ``lr_scale``
            > 0) and keeps the binding, back the refined avatar's cheeks with the expression prior's
            cheek shell (``model/prior.py`` ``cheek_shell``; not when the model already puts it in
            every avatar, ``DeformConfig.cheek_shell``): those corrections thin the cheeks, and seen
            from a side the mouth interior then shows through them as red dots.
    """

    steps: int = 60  # the measured setting (docs/model-card-log.md, test-time refinement)
    resolution: int = 256
    coarse_resolution: int = 128
    # 0 (was 0.75): the 128² steps cannot fit what the 256² photos show beyond the 128² inputs, and a
    # fine phase of 15 of 60 steps all fell in the step-size decay (docs/model-card-log.md, test-time refinement)
    coarse_fraction: float = 0.0
    # 0 (was 1.5e-3): on held-out synthetic subjects the ray-depth corrections cost novel-view PSNR
    # (40 steps: 20.26 vs 21.49 dB on seeds 1000200-1000203, 20.55 vs 20.89 on 1000000-1000003,
    # docs/model-card-log.md); colour and opacity corrections alone gain
    lr_depth: float = 0.0
    lr_opacity: float = 0.3  # was 0.08 (with views_per_step=2: 26.99 vs 24.92 dB on the sample's inputs)
    lr_color: float = 0.3
    lr_rotation: float = 2e-3
    lr_translation: float = 1e-3
    w_photo: float = 1.0
    w_silhouette: float = 0.5
    w_depth: float = 5.0
    depth_sigma: float = 0.02
    w_reg_depth: float = 1e-3
    w_reg_opacity: float = 1e-4
    # 0.01 (was 1e-4, 2026-12-02): semi-transparent Gaussians that matter little at their own camera no
    # longer drift to orange blotches seen from elsewhere (1,334 -> 53 on the demo sample); held-out
    # 21.70 / 21.88 -> 21.73 / 22.03 dB, the sample's inputs 29.33 -> 28.78 dB (docs/model-card-log.md)
    w_reg_color: float = 0.01
    w_reg_camera: float = 1e-2
    rot_sigma: float = 0.05
    trans_sigma: float = 0.01
    optimize_cameras: bool = False
    realign: bool = False
    # 0 (off): 6 mm gave 29.46 against 29.33 dB on the sample's inputs but lowered held-out PSNR
    # (21.47 / 21.84 against 21.74 / 22.15 dB; docs/model-card-log.md, test-time refinement)
    realign_cap: float = 0.0
    noise_floor: float = 0.0  # was 1.0, and smooth_grid 32: both held the per-Gaussian colours to the 128² detail
    smooth_grid: int = 0
    prune_opacity: float = 0.005
    phase_schedule: bool = False
    views_per_step: int = 2  # was all: half the cost per step, more steps in the same time
    # 0: free 3D offsets lowered the sample's inputs (60 steps: 25.59 dB at 2e-4 m, 28.03 at 5e-5 with
    # scale corrections against 29.16 without; docs/model-card-log.md, test-time refinement)
    lr_xyz: float = 0.0
    xyz_sigma: float = 0.002
    w_reg_xyz: float = 1e-3
    # was 0 (no scale corrections): 60 steps on the sample's inputs 26.80 -> 29.33 dB, held-out
    # (docs/model-card-log.md, test-time refinement); 0.03 / 0.1: 29.21 / 29.40 dB on the inputs
    lr_scale: float = 0.05
    w_reg_scale: float = 1e-3
    photo_in_mask: bool = False
    match_animation: bool = True  # was False: the shading was not applied and the shell not drawn
    # was a refit: the refit binding moved some neck Gaussians in view 1 of the sample, which showed as
    # coloured splats the refinement never saw (29.16 -> 29.21 dB kept)
    keep_binding: bool = True
    # after opacity / scale corrections (docs/model-card-log.md, "Red dots on the cheek"): the demo's red dots
    # gone; in every avatar it cost the smile response of avatars that are never refined
    cheek_shell: bool = True

    def __post_init__(self) -> None:
        if self.steps < 0:
            raise ValueError(f"steps must be >= 0, got {self.steps}")
        for name in ("resolution", "coarse_resolution"):
            r = getattr(self, name)
            if r < 16 or r % 16:
                raise ValueError(f"{name} must be a multiple of 16 (>= 16), got {r}")
        if self.views_per_step < 0:
            raise ValueError(f"views_per_step must be >= 0, got {self.views_per_step}")
        if self.realign_cap < 0:
            raise ValueError(f"realign_cap must be >= 0, got {self.realign_cap}")
        if self.xyz_sigma <= 0:
            raise ValueError(f"xyz_sigma must be > 0, got {self.xyz_sigma}")
        if self.smooth_grid < 0 or self.noise_floor < 0:
            raise ValueError(f"smooth_grid and noise_floor must be >= 0, got {self.smooth_grid} and {self.noise_floor}")
        if not 0.0 <= self.coarse_fraction <= 1.0:
            raise ValueError(f"coarse_fraction must lie in [0, 1], got {self.coarse_fraction}")
        for name in ("depth_sigma", "rot_sigma", "trans_sigma"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")


REFINE_PRESETS: dict[str, RefineConfig] = {
    "off": RefineConfig(steps=0),
    "fast": RefineConfig(steps=20, resolution=128, coarse_resolution=128),
    "default": RefineConfig(),
    "thorough": RefineConfig(steps=100),
    # the defaults before 2026-11-30 (night): smooth 32x32 correction grids, 75% of the steps at 128²,
    # every view every step; lower on synthetic inputs and novel views, a little higher on real photos
    # (docs/model-card-log.md, test-time refinement)
    "smooth": RefineConfig(steps=60, coarse_fraction=0.75, smooth_grid=32, lr_color=0.08, lr_opacity=0.08, noise_floor=1.0, views_per_step=0, lr_scale=0.0, match_animation=False, keep_binding=False, w_reg_color=1e-4),
    # the defaults of 2026-11-30 (night) before the scale corrections: colour and opacity only, the
    # network's Gaussians without the prior's shading, the head refitted to the result
    "colour": RefineConfig(steps=60, lr_scale=0.0, match_animation=False, keep_binding=False, w_reg_color=1e-4),
    # real photos (tracked cameras): colours only, inside the photos' masks, held near the network's
    # colours (w_reg_color 0.1; 0.03 moved identity as much but cost 0.1-0.25 dB on two sets); opacity
    # and scale corrections opened holes on real photos (docs/model-card-log.md, "Colours-only refinement
    # on real photos")
    # on the leave-one-out sets 30 steps scored as 60 (the colours settle near the regulariser's pull);
    # noise_floor 1 (2026-12-02): Adam's first steps no longer move the colours whose gradient is
    # below the median by the full step size (studio-4 at 2 steps: identity 0.619 -> 0.579)
    "photos": RefineConfig(steps=30, lr_opacity=0.0, lr_scale=0.0, photo_in_mask=True, w_reg_color=0.1, noise_floor=1.0),
}


def _with_cheek_shell(model, avatar: CanonicalAvatar, n: int) -> CanonicalAvatar:
    """``avatar`` (``n`` reconstructed Gaussians, then the model's shells, then the gated interior) with
    the cheek shell (``model/prior.py`` ``cheek_shell``) inserted after its shells, laid on the head
    its binding was fitted to and coloured from its ``n`` reconstructed Gaussians. Returned unchanged
    when the model has no expression prior, already puts the shell in every avatar
    (``DeformConfig.cheek_shell``) or its head model has no cheek shell."""
    import numpy as np

    from ..model.prior import HeadFit, PriorBinding, cheek_shell, cheek_shell_vertices

    d = model.config.deform
    b = avatar.prior
    if not d.prior or d.cheek_shell or b is None:
        return avatar
    basis = model.head_basis()
    if b.space != basis.space or not len(cheek_shell_vertices(basis)):
        return avatar
    T = b.transform.detach().cpu().double().numpy()
    ident = b.identity.detach().cpu().float().numpy()
    verts = basis.neutral.astype(np.float64) + np.tensordot(ident, basis.identity_basis, axes=1)
    fit = HeadFit(identity=ident, transform=T.astype(np.float32), vertices=(verts @ T[:3, :3].T + T[:3, 3]).astype(np.float32), rms=0.0)
    g = avatar.gaussians
    at = n + model._shell_count()  # after the back and chin shells, before the gated interior
    dev = b.vertex_ids.device
    ids = torch.from_numpy(cheek_shell_vertices(basis)).to(dev)
    if len(b) >= at + len(ids) and torch.equal(b.vertex_ids[at : at + len(ids), 0], ids):
        return avatar  # refined before: it has the shell already
    gs, bs = cheek_shell(fit, basis, g.features.shape[1], avatar=g[:n].detach())
    head, tail = torch.arange(at, device=dev), torch.arange(at, len(b), device=dev)
    binding = PriorBinding.concat(PriorBinding.concat(b.index(head), bs.to(dev)), b.index(tail))
    g_all = Gaussians.concat([g[:at], gs.to(g.means.device, g.means.dtype), g[at:]])
    return CanonicalAvatar(g_all, avatar.model_name, avatar.expression_space, binding, avatar.num_interior + len(gs), avatar.view_blend)


def refine_preset_for(avatar: CanonicalAvatar, preset: str = "auto") -> str:
    """The ``REFINE_PRESETS`` name to refine ``avatar`` with: ``preset`` itself when it names one, and
    for ``"auto"`` the one measured best for the avatar's kind: ``"photos"`` (colours only, inside the
    masks) for avatars on a tracked head surface (``avatar.view_blend`` set: real photos, tracked
    cameras), ``"default"`` for avatars on the network's depth (known cameras, the synthetic
    protocol). The figures behind the choice: docs/model-card-log.md, "Colours-only refinement on real
    photos" and "Scale corrections".

    Raises:
        ValueError: on an unknown preset name (the message lists the names).
    """
    if preset == "auto":
        return "photos" if avatar.view_blend is not None else "default"
    if preset not in REFINE_PRESETS:
        raise ValueError(f"unknown refinement preset {preset!r}; expected auto or one of {', '.join(REFINE_PRESETS)}")
    return preset


def refine_config_for(avatar: CanonicalAvatar, steps: int, preset: str = "auto", **overrides) -> RefineConfig:
    """``REFINE_PRESETS[refine_preset_for(avatar, preset)]`` with ``steps`` and any other
    ``RefineConfig`` field in ``overrides``. Raises ``ValueError`` on an unknown preset name."""
    return replace(REFINE_PRESETS[refine_preset_for(avatar, preset)], steps=steps, **overrides)


@dataclass
class RefineResult:
    """What ``refine_avatar`` returns.

    Attributes:
        avatar: the refined ``CanonicalAvatar`` (the input one when ``steps == 0``).
        cameras: the corrected input cameras ``[V]`` (same size as the cameras given).
        rotations: ``[V, 3]`` camera rotation corrections (rotation vectors, radians, camera frame).
        translations: ``[V, 3]`` camera translation corrections (metres, camera frame).
        losses: total loss per step (over the views that step rendered, ``RefineConfig.views_per_step``).
        timings: seconds: ``setup``, ``optimize`` (all steps), ``total``; ``steps``: steps run.
    """

    avatar: CanonicalAvatar
    cameras: Cameras
    rotations: Tensor
    translations: Tensor
    losses: list[float] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)


# ----------------------------------------------------------------------------- helpers
def prepare_targets(images: Tensor, cameras: Cameras, masks: Tensor | None, size: int) -> tuple[Tensor, Tensor, Cameras]:
    """Matte, centre-crop and resize photos to ``size x size`` targets.

    Args:
        images: ``[V, 3, H, W]`` float in [0, 1] or uint8; cameras: ``[V]`` of size ``W x H``.
        masks: ``[V, H, W]`` / ``[V, 1, H, W]`` alpha in [0, 1] (uint8 -> /255), or None: then the
            images must already be matted on ``BACKGROUND_RGB`` and the mask is their foreground
            weight (``model.gaussian_head.foreground_weight``).
    Returns:
        targets ``[V, 3, S, S]`` (matted on ``BACKGROUND_RGB``), masks ``[V, 1, S, S]``, cameras ``[V]``.
    Raises:
        ValueError: on mismatched shapes.
    """
    from ..model.gaussian_head import foreground_weight

    imgs = images.float() / 255.0 if images.dtype == torch.uint8 else images.float()
    if imgs.ndim != 4 or imgs.shape[1] != 3:
        raise ValueError(f"images must have shape [V, 3, H, W], got {list(imgs.shape)}")
    v, _, h, w = imgs.shape
    cams = cameras.flatten()
    if len(cams.K) != v or (cams.width, cams.height) != (w, h):
        raise ValueError(f"cameras must be [{v}] of size {w}x{h}, got [{len(cams.K)}] of size {cams.width}x{cams.height}")
    bg = imgs.new_tensor(BACKGROUND_RGB).view(1, 3, 1, 1)
    if masks is None:
        m = foreground_weight(imgs)[:, None]
    else:
        m = masks.float() / 255.0 if masks.dtype == torch.uint8 else masks.float()
        m = m.reshape(v, 1, h, w) if m.numel() == v * h * w else None
        if m is None:
            raise ValueError(f"masks must have shape [{v}, H={h}, W={w}] or [{v}, 1, {h}, {w}], got {list(masks.shape)}")
        imgs = imgs * m + bg * (1.0 - m)
    side = min(h, w)
    left, top = (w - side) // 2, (h - side) // 2
    imgs, m = imgs[..., top : top + side, left : left + side], m[..., top : top + side, left : left + side]
    cams = cams.crop(left, top, side, side)
    if side != size:
        imgs = F.interpolate(imgs, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
        m = F.interpolate(m, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
        cams = cams.resize(size, size)
    return imgs.clamp(0, 1), m.clamp(0, 1), cams


def source_views(means: Tensor, cameras: Cameras, grid: int) -> Tensor:
    """Index ``[N]`` of the input view whose pixel ray each pixel-aligned Gaussian lies on.

    ``FastGHA`` puts every Gaussian on the ray through a pixel centre of its view's ``grid x grid``
    map, so its projection into that view lands on a pixel centre ``(j + 0.5, i + 0.5)``; into
    another view it almost never does. The view with the smallest distance to a pixel centre wins.
    """
    cams = cameras.flatten().resize(grid, grid)
    uv, z = cams.project(means[None].to(cams.K.dtype))  # [V, N, 2], [V, N]
    off = (uv - 0.5 - torch.round(uv - 0.5)).abs().amax(dim=-1)  # [V, N] distance to a pixel centre
    inside = (uv >= 0).all(-1) & (uv < grid).all(-1) & (z > 0)
    off = torch.where(inside, off, torch.full_like(off, 2.0))
    return off.argmin(dim=0)


def lr_factor(step: int, steps: int, restart: int = 0) -> float:
    """Step-size factor of step ``step`` (from 0) of ``steps``: 1 over the first half, then a linear
    decay to 0.1 at the last step. ``restart > 0`` runs the schedule separately over steps
    ``[0, restart)`` and ``[restart, steps)`` (``RefineConfig.phase_schedule``: the fine phase
    starts again at the full step size)."""
    first, length = (0, steps) if restart <= 0 else ((0, restart) if step < restart else (restart, steps - restart))
    frac = (step - first) / max(1, length - 1)
    return 1.0 if frac < 0.5 else 1.0 - 1.8 * (frac - 0.5)


def masked_psnr(pred: Tensor, target: Tensor, mask: Tensor, threshold: float = 0.5) -> Tensor:
    """PSNR (dB, peak 1) per image over the pixels with ``mask > threshold``.

    ``pred``/``target`` ``[B, 3, H, W]`` in [0, 1], ``mask`` ``[B, 1, H, W]`` -> ``[B]``.
    """
    m = (mask > threshold).float().expand_as(pred)
    mse = ((pred - target) ** 2 * m).sum(dim=(1, 2, 3)) / m.sum(dim=(1, 2, 3)).clamp_min(1.0)
    return -10.0 * torch.log10(mse.clamp_min(1e-10))


def _rotvec_to_matrix(w: Tensor) -> Tensor:
    """Rodrigues: rotation vectors ``[V, 3]`` -> ``[V, 3, 3]`` (differentiable at 0)."""
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]  # [V, 1, 1]
    zero = torch.zeros_like(w[:, 0])
    Kx = torch.stack([zero, -w[:, 2], w[:, 1], w[:, 2], zero, -w[:, 0], -w[:, 1], w[:, 0], zero], -1).reshape(-1, 3, 3)
    theta = theta2.clamp_min(1e-12).sqrt()
    small = theta2 < 1e-8
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(1e-12))
    eye = torch.eye(3, dtype=w.dtype).expand_as(Kx)
    return eye + a * Kx + b * (Kx @ Kx)


def corrected_w2c(w2c: Tensor, rot: Tensor, trans: Tensor) -> Tensor:
    """``[V, 4, 4]`` world-to-camera matrices with the camera-frame corrections applied."""
    R = _rotvec_to_matrix(rot)
    top = torch.cat([R @ w2c[:, :3, :3], (R @ w2c[:, :3, 3:4]) + trans[..., None]], dim=-1)  # [V, 3, 4]
    return torch.cat([top, w2c[:, 3:4]], dim=1)


def scaled_conics(conics: Tensor, log_scale: Tensor, eps2d: float | None = None) -> Tensor:
    """Conics ``[N, 3]`` (a, b, c) of Gaussians whose 3D scales are multiplied by ``exp(log_scale [N])``
    (isotropically), from the conics ``conics [N, 3]`` projected at the current scales.

    The projected 2D covariance is ``Sigma2d = J W Sigma W^T J^T + EPS2D I`` (``render.projection``);
    an isotropic factor ``s`` on the 3D scales multiplies its first term by ``s^2``. The value is the
    input conic where ``log_scale`` is 0 (it is meant to be called with ``log_scale - log_scale.detach()``
    so that the forward pass keeps the exact projection and only the gradient comes from here); conics
    of culled Gaussians (all zero) stay zero.
    """
    from ..render.projection import EPS2D

    eps = EPS2D if eps2d is None else eps2d
    a, b, c = conics.unbind(-1)
    det = a * c - b * b
    ok = det > 0
    inv = torch.where(ok, 1.0 / torch.where(ok, det, torch.ones_like(det)), torch.zeros_like(det))
    # covariance of the current projection without the low-pass term, scaled by s^2, low-pass added back
    s2 = torch.exp(2.0 * log_scale)
    ca, cb, cc = (c * inv - eps) * s2 + eps, -b * inv * s2, (a * inv - eps) * s2 + eps
    d2 = ca * cc - cb * cb
    d2 = torch.where(ok & (d2 > 0), d2, torch.ones_like(d2))
    out = torch.stack([cc / d2, -cb / d2, ca / d2], dim=-1)
    return torch.where(ok[:, None], out, conics)


def realign_to_pixels(model, g: Gaussians, src: Tensor, expressions: Tensor, cap: float, iters: int = 3) -> tuple[Tensor, Tensor]:
    """Canonical centres ``[N, 3]`` that the deformation MLP's residual at each Gaussian's own view's
    expression takes back to ``g.means`` (where the network put it, on its pixel ray), and the
    ``[N]`` bool mask of the Gaussians left in place.

    Solves ``m + mlp(m, z_src) = g.means`` by ``iters`` fixed-point steps ``m <- g.means - mlp(m, z_src)``
    (``src [N]``: each Gaussian's input view, ``expressions [V, E]``). For a part of the Gaussians the
    iteration does not converge and moves them by centimetres (on the shipped sample 23 mm at the
    90th percentile, up to 17 cm, without a cap); those whose move exceeds ``cap`` metres keep
    ``g.means``. The expression prior's displacement is not touched (reconstruction undoes it).
    """
    dev = model.device
    target = g.means.detach().float().cpu()
    m = target.clone()
    feats = g.features.detach().to(dev)
    with torch.no_grad():
        for _ in range(iters):
            res = torch.zeros_like(m)
            for i in range(len(expressions)):
                sel = (src == i).nonzero().squeeze(1)
                if len(sel):
                    res[sel] = model.deform(feats[sel.to(dev)], m[sel].to(dev), expressions[i].to(dev))[0].float().cpu()
            m = target - res
    stay = (m - target).norm(dim=-1) > cap
    return torch.where(stay[:, None], target, m), stay


def _render_view(
    g: Gaussians, means: Tensor, colors: Tensor, opac: Tensor, K: Tensor, w2c: Tensor, size: int, bg: Tensor,
    log_scale: Tensor | None = None,
):
    """Differentiable render of one view.

    ``means [N, 3]``, ``colors [N, 3]``, ``opac [N]`` carry gradients, ``K [3, 3]`` and ``w2c [4, 4]``
    too (through the projected centres); ``g`` gives the quaternions and scales. The screen-space
    covariances are those of the current positions, treated as constants, except for an isotropic
    scale correction ``log_scale [N]`` (or None): the scales are multiplied by ``exp(log_scale)`` and
    its gradient flows through the conics (``scaled_conics``). Returns rgb ``[3, S, S]``, alpha
    ``[1, S, S]``, depth ``[1, S, S]``, the camera z ``[N]`` and the pixel positions ``[N, 2]``.
    """
    from ..render.cpu_backend import project_cpu, rasterize_cpu
    from ..render.projection import Projected

    scales = g.scales if log_scale is None else g.scales * torch.exp(log_scale.detach())[:, None]
    with torch.no_grad():
        proj, rects = project_cpu(means.detach(), g.quats, scales, K.detach()[None], w2c.detach()[None], size, size)
    pc = means @ w2c[:3, :3].T + w2c[:3, 3]  # [N, 3]
    z = pc[:, 2]
    zs = torch.where(z > 1e-3, z, torch.ones_like(z))
    uv = torch.stack([K[0, 0] * pc[:, 0] / zs + K[0, 2], K[1, 1] * pc[:, 1] / zs + K[1, 2]], dim=-1)  # [N, 2]
    conics = proj.conics
    if log_scale is not None and log_scale.requires_grad:
        sc = scaled_conics(proj.conics[0], log_scale - log_scale.detach())[None]
        conics = proj.conics + (sc - sc.detach())  # the exact projection forward, the scale's gradient backward
    p = Projected(uv[None], conics, z.detach()[None], proj.radii)
    values = torch.cat([colors, z[:, None]], dim=-1)[None]  # [1, N, 4]
    acc, alpha = rasterize_cpu(p, opac, values, size, size, rects)
    rgb = acc[0, ..., :3] + (1.0 - alpha[0])[..., None] * bg
    depth = acc[0, ..., 3] / alpha[0].clamp_min(1e-6)
    return rgb.permute(2, 0, 1), alpha[0][None], depth[None], z, uv


def _input_view_blend(model, avatar: CanonicalAvatar, g0: Gaussians, dxyz: Tensor, cams: Cameras, expressions: Tensor | None):
    """Per input view ``i``: ``(f [N], k [N])``, the opacity factor ``FastGHA.blend_views`` gives each
    of the avatar's ``N`` reconstructed Gaussians at camera ``i`` (``model/viewblend.py``: the
    view-dependent blending of real-photo avatars) and the depth factor that draws the off-head ones
    under the others there (``push_under``: centre ``c + k (mean - c)``, scales ``x k``, ``c`` the
    camera centre; 1 for the others). Constants, from the Gaussians deformed to view ``i``'s
    expression (``dxyz [V, N, 3]``). None when ``blend_views`` leaves frames unchanged (no per-view
    data, ``gaussians.view_blend_tau_deg`` 0: network-depth avatars), so those refine as before."""
    n = len(g0)
    vb = avatar.view_blend
    if vb is None or len(vb) != n or float(model.config.gaussians.view_blend_tau_deg) <= 0:
        return None
    out = []
    with torch.no_grad():
        for i in range(len(cams.K)):
            probe = g0.replace(means=g0.means + dxyz[i], opacities=torch.ones(n))
            z = None if expressions is None else expressions[i]
            # the probe stands for the frame's first N Gaussians (animate's trailing ones are not needed)
            b = model.blend_views(avatar, probe.to(model.device), cams[i : i + 1].to(model.device), None if z is None else z.to(model.device))
            b = b.to("cpu")
            k = (b.scales[:n, 0] / probe.scales[:, 0].clamp_min(1e-12)).float()
            out.append((b.opacities[:n].float(), k))
    return out


# ----------------------------------------------------------------------------- main entry
def refine_avatar(
    model,
    avatar: CanonicalAvatar,
    images: Tensor,
    cameras: Cameras,
    masks: Tensor | None = None,
    *,
    config: RefineConfig,
    progress: Callable[[int, int], None] | None = None,
    expressions: Tensor | None = None,
) -> RefineResult:
    """Refine ``avatar`` (from ``model.reconstruct``) against the photos it was made from.

    Args:
        model: the ``FastGHA`` that made the avatar (its deformation MLP renders the expressions).
        avatar: the feed-forward ``CanonicalAvatar``.
        images: ``[V, 3, H, W]`` the input photos (float in [0, 1] or uint8), any size; the same
            views, in the same order, as the images given to ``reconstruct``.
        cameras: ``[V]`` cameras of ``images`` (``W x H``).
        masks: ``[V, H, W]`` / ``[V, 1, H, W]`` foreground alpha, or None when the images are
            already matted on ``BACKGROUND_RGB`` (see ``prepare_targets``).
        config: a ``RefineConfig``; ``steps == 0`` returns the avatar unchanged.
        progress: called as ``progress(step, steps)`` after every step (``step`` from 1).
        expressions: ``[V, E]`` the inputs' expression codes (tracked or known); None renders the
            canonical Gaussians without deformation.
    Returns:
        ``RefineResult`` (refined avatar, corrected cameras of size ``W x H``, timings).
    Raises:
        ValueError: on mismatched shapes, or when the avatar and model disagree.
    """
    with torch.enable_grad():  # works under torch.no_grad() too (e.g. in evaluation loops)
        return _refine_avatar(
            model, avatar, images, cameras, masks, config=config, progress=progress, expressions=expressions
        )


def _refine_avatar(
    model,
    avatar: CanonicalAvatar,
    images: Tensor,
    cameras: Cameras,
    masks: Tensor | None = None,
    *,
    config: RefineConfig,
    progress: Callable[[int, int], None] | None = None,
    expressions: Tensor | None = None,
) -> RefineResult:
    """The body of ``refine_avatar`` (gradients on)."""
    t_start = time.perf_counter()
    cams_in = cameras.flatten()
    v = len(cams_in.K)
    zero3 = torch.zeros(v, 3)
    if config.steps == 0:
        return RefineResult(avatar, cams_in, zero3, zero3.clone(), [], {"setup": 0.0, "optimize": 0.0, "total": 0.0, "steps": 0})
    if images.ndim != 4 or images.shape[0] != v:
        raise ValueError(f"images must have shape [V={v}, 3, H, W] (one per camera), got {list(images.shape)}")
    e = model.config.expression_dim
    if expressions is not None:
        expressions = torch.as_tensor(expressions, dtype=torch.float32)
        if tuple(expressions.shape) != (v, e):
            raise ValueError(f"expressions must have shape [V={v}, E={e}], got {list(expressions.shape)}")
    levels = {}
    for size in {config.resolution, config.coarse_resolution}:
        levels[size] = prepare_targets(images.cpu(), cams_in.to("cpu", torch.float32), None if masks is None else masks.cpu(), size)
    tcams = levels[config.resolution][2]
    n_coarse = int(round(config.coarse_fraction * config.steps))
    # only the network's Gaussians are refined; the result keeps the avatar's binding and appended
    # Gaussians (``keep_binding``), or refits them (``FastGHA.attach_prior``)
    g0 = avatar.gaussians[: avatar.num_reconstructed].detach().to("cpu").to(dtype=torch.float32)
    n = len(g0)
    grid = model.config.input_size
    src = source_views(g0.means, tcams, grid)  # [N]
    centers = tcams.centers  # [V, 3]
    ray = F.normalize(g0.means - centers[src], dim=-1)  # [N, 3]

    if config.realign_cap > 0 and expressions is not None:
        g0 = g0.replace(means=realign_to_pixels(model, g0, src, expressions, config.realign_cap)[0])

    # fixed per-view deformation at the predicted centres
    dxyz = torch.zeros(v, n, 3)
    drgb = torch.zeros(v, n, 3)
    shade = torch.ones(v, n)  # the prior's colour factor per view (match_animation)
    gate_rec = torch.ones(v, n)  # the expression gate of the network's own Gaussians (match_animation)
    extra: list[Gaussians] = []  # fixed appended Gaussians per view, deformed (match_animation)
    if expressions is not None:
        with torch.no_grad():
            dev = model.device
            feats, xyz = g0.features.to(dev), g0.means.to(dev)
            for i in range(v):
                a, b = model.deform(feats, xyz, expressions[i].to(dev))
                dxyz[i], drgb[i] = a.float().cpu(), b.float().cpu()
            anchor = model.residual_anchor(avatar)  # as animate() draws it: relative to each Gaussian's own view (deform.anchor_residual)
            if anchor is not None and anchor.shape[0] == n:
                dxyz -= anchor.float().cpu()[None]
            if avatar.prior is not None:  # the head model's displacement under the MLP's residual
                rt = model._runtime(avatar.prior, avatar.gaussians, avatar.num_interior)
                prior_d = rt.displacement(expressions.to(rt.basis_u.device)).float().cpu()  # [V, N_all, 3]
                dxyz += prior_d[:, :n]
                if config.match_animation:
                    from ..render.projection import ALPHA_MIN

                    gi = avatar.gaussians[n:].detach().to("cpu").to(dtype=torch.float32)
                    for i in range(v):
                        zi = expressions[i].to(rt.basis_u.device)
                        gate = model._gate(zi, rt)
                        gate = torch.ones(len(avatar.gaussians)) if gate is None else gate.float().cpu()
                        gate_rec[i] = gate[:n]
                        if rt.shading_on:
                            shade[i] = rt.shading(zi).float().cpu()[:n]
                        op = gi.opacities * gate[n:]
                        keep = op >= ALPHA_MIN
                        extra.append(gi.replace(means=gi.means + prior_d[i, n:], opacities=op)[keep])

    if config.realign and expressions is not None:
        # Pixel re-alignment: the network predicts each Gaussian on its own pixel ray (and with its
        # pixel's colour) but in canonical space; deformed to its own view's expression it leaves
        # the ray. Moving it back by its own view's offsets puts it where that view saw it.
        ar = torch.arange(n)
        g0 = g0.replace(means=g0.means - dxyz[src, ar], colors=(g0.colors - drgb[src, ar]).clamp(0.0, 1.0))
        ray = F.normalize(g0.means + dxyz[src, ar] - centers[src], dim=-1)
    o_logit0 = torch.logit(g0.opacities.clamp(1e-4, 1 - 1e-4))
    c_logit0 = torch.logit(g0.colors.clamp(1e-3, 1 - 1e-3))
    if config.smooth_grid > 0:
        # corrections live on a coarse grid per view and are sampled (bilinearly) at each Gaussian's
        # pixel in its own view, so neighbouring Gaussians of a view move together
        gs = config.smooth_grid
        p_dt = torch.zeros(v, 1, gs, gs, requires_grad=True)
        p_o = torch.zeros(v, 1, gs, gs, requires_grad=True)
        p_c = torch.zeros(v, 3, gs, gs, requires_grad=True)
        uv_src, _ = tcams.resize(grid, grid).project(g0.means[None])  # [V, N, 2]
        pos = uv_src[src, torch.arange(n)] / grid * 2 - 1  # [N, 2] in [-1, 1]
        order = torch.cat([(src == i).nonzero().squeeze(1) for i in range(v)])
        inv = torch.empty_like(order)
        inv[order] = torch.arange(n)
        pos_v = [pos[src == i] for i in range(v)]

        def corrections():
            out = []
            for i in range(v):
                maps = torch.cat([p_dt[i], p_o[i], p_c[i]], 0)[None]  # [1, 5, G, G]
                out.append(F.grid_sample(maps, pos_v[i][None, None], mode="bilinear", padding_mode="border", align_corners=False)[0, :, 0].T)
            c = torch.cat(out)[inv]  # [N, 5]
            return c[:, 0], c[:, 1], c[:, 2:5]

        params = (p_dt, p_o, p_c)
    else:
        p_dt = torch.zeros(n, requires_grad=True)
        p_o = torch.zeros(n, requires_grad=True)
        p_c = torch.zeros(n, 3, requires_grad=True)

        def corrections():
            return p_dt, p_o, p_c

        params = (p_dt, p_o, p_c)
    p_xyz = torch.zeros(n, 3, requires_grad=config.lr_xyz > 0)
    p_ls = torch.zeros(n, requires_grad=config.lr_scale > 0)
    rot = torch.zeros(v, 3, requires_grad=True)
    trans = torch.zeros(v, 3, requires_grad=True)
    groups = [
        {"params": [params[0]], "lr": config.lr_depth},
        {"params": [params[1]], "lr": config.lr_opacity},
        {"params": [params[2]], "lr": config.lr_color},
    ]
    if config.optimize_cameras:
        groups += [{"params": [rot], "lr": config.lr_rotation}, {"params": [trans], "lr": config.lr_translation}]
    if config.lr_xyz > 0:
        groups.append({"params": [p_xyz], "lr": config.lr_xyz})
    if config.lr_scale > 0:
        groups.append({"params": [p_ls], "lr": config.lr_scale})
    opt = torch.optim.Adam(groups, betas=(0.9, 0.99), eps=1e-12)
    base_lr = [gr["lr"] for gr in opt.param_groups]
    bg = torch.tensor(BACKGROUND_RGB, dtype=torch.float32)
    w2c0 = tcams.w2c.float()
    own = [(src == i).nonzero().squeeze(1) for i in range(v)]
    # per view: the network's Gaussians followed by that view's fixed appended ones (quats, scales)
    extra_all = [
        Gaussians(
            means=torch.cat([g0.means, ex.means]), quats=torch.cat([g0.quats, ex.quats]),
            scales=torch.cat([g0.scales, ex.scales]), opacities=torch.cat([g0.opacities, ex.opacities]),
            colors=torch.cat([g0.colors, ex.colors]),
        )
        for ex in extra
    ]
    # each input view drawn as ``animate(..., camera=)`` draws a frame there: the view-dependent blend
    # factors and the off-head Gaussians pushed under the others (``FastGHA.blend_views``)
    blend = _input_view_blend(model, avatar, g0, dxyz, tcams, expressions) if config.match_animation else None
    t_setup = time.perf_counter() - t_start
    losses: list[float] = []
    t0 = time.perf_counter()
    nv = v if config.views_per_step <= 0 else min(v, config.views_per_step)
    for step in range(config.steps):
        factor = lr_factor(step, config.steps, n_coarse if config.phase_schedule else 0)
        for gr, lr in zip(opt.param_groups, base_lr):
            gr["lr"] = lr * factor
        opt.zero_grad(set_to_none=True)
        size = config.coarse_resolution if step < n_coarse else config.resolution
        targets, tmasks, lcams = levels[size]
        K = lcams.K.float()
        dt, d_o, d_c = corrections()
        means = g0.means + dt[:, None] * ray + p_xyz
        opac = torch.sigmoid(o_logit0 + d_o) if config.lr_opacity > 0 else g0.opacities
        colors = torch.sigmoid(c_logit0 + d_c) if config.lr_color > 0 else g0.colors
        w2c = corrected_w2c(w2c0, rot, trans)
        log_scale = p_ls if config.lr_scale > 0 else None
        total = torch.zeros(())
        for i in ((step * nv + j) % v for j in range(nv)):  # all views, or nv of them in turn
            col_i = (colors + drgb[i]).clamp(0, 1)
            means_i, opac_i, g_i = means + dxyz[i], opac, g0
            if blend is not None:
                f_i, k_i = blend[i]
                c_i = centers[i]
                means_i = c_i + k_i[:, None] * (means_i - c_i)  # pushed under: the same splat, deeper
                opac_i = opac * f_i
                g_i = g0.replace(scales=g0.scales * k_i[:, None])
            if extra:
                col_i = (col_i * shade[i][:, None]).clamp(0, 1)
                ex, gv = extra[i], extra_all[i]
                if blend is not None:
                    gv = gv.replace(scales=torch.cat([g_i.scales, ex.scales]))
                ls_i = None if log_scale is None else torch.cat([log_scale, torch.zeros(len(ex))])
                rgb, alpha, depth, z, uv = _render_view(
                    gv, torch.cat([means_i, ex.means]), torch.cat([col_i, ex.colors]),
                    torch.cat([opac_i * gate_rec[i], ex.opacities]), K[i], w2c[i], size, bg, ls_i,
                )
                z, uv = z[:n], uv[:n]
            else:
                rgb, alpha, depth, z, uv = _render_view(g_i, means_i, col_i, opac_i, K[i], w2c[i], size, bg, log_scale)
            if config.photo_in_mask:
                inside = (tmasks[i] > 0.5).float()  # [1, S, S]
                l_photo = ((rgb - targets[i]).abs() * inside).sum() / (3.0 * inside.sum()).clamp_min(1.0)
            else:
                l_photo = (rgb - targets[i]).abs().mean()
            l_sil = ((alpha - tmasks[i]) ** 2).mean()
            loss = config.w_photo * l_photo + config.w_silhouette * l_sil
            if config.w_depth > 0 and len(own[i]):
                with torch.no_grad():  # rendered depth and foreground at the own Gaussians' pixels
                    gpos = (uv.detach()[own[i]] / size) * 2 - 1  # [M, 2] in [-1, 1]
                    samp = lambda img: F.grid_sample(img[None], gpos[None, None], align_corners=False)[0, :, 0]  # noqa: E731
                    d_at = samp(depth)[0]
                    fg = (samp(alpha)[0] > 0.5) & (samp(tmasks[i])[0] > 0.5)
                if fg.any():
                    diff = (z[own[i]] - d_at).abs() / config.depth_sigma
                    loss = loss + config.w_depth * 1e-2 * (diff * fg).sum() / fg.sum()
            total = total + loss / nv
        reg = config.w_reg_depth * (dt / config.depth_sigma).pow(2).mean()
        reg = reg + config.w_reg_opacity * d_o.pow(2).mean() + config.w_reg_color * d_c.pow(2).mean()
        if config.lr_xyz > 0:
            reg = reg + config.w_reg_xyz * (p_xyz / config.xyz_sigma).pow(2).sum(-1).mean()
        if config.lr_scale > 0:
            reg = reg + config.w_reg_scale * p_ls.pow(2).mean()
        if config.optimize_cameras:
            reg = reg + config.w_reg_camera * ((rot / config.rot_sigma).pow(2).sum(-1) + (trans / config.trans_sigma).pow(2).sum(-1)).mean()
        total = total + reg
        total.backward()
        if step == 0 and config.noise_floor > 0:
            # Adam moves every parameter by about its step size whatever the size of its gradient, so
            # the many Gaussians with tiny, noisy gradients would jitter. A per-group epsilon at
            # ``noise_floor`` x the median gradient magnitude lets only clear gradients move them.
            for gr in opt.param_groups[:3]:
                if gr["params"][0].grad is None:  # a frozen group (step size 0)
                    continue
                gmag = gr["params"][0].grad.abs()
                gmag = gmag[gmag > 0]
                if gmag.numel():
                    gr["eps"] = float(gmag.median()) * config.noise_floor
        opt.step()
        losses.append(float(total.detach()))
        if progress is not None:
            progress(step + 1, config.steps)
    t_opt = time.perf_counter() - t0

    with torch.no_grad():
        dt, d_o, d_c = corrections()
        means = g0.means + dt[:, None] * ray + p_xyz
        # a group with step size 0 keeps the network's values exactly (the logit round trip clamps them)
        g = g0.replace(
            means=means,
            scales=g0.scales * torch.exp(p_ls)[:, None],
            opacities=torch.sigmoid(o_logit0 + d_o) if config.lr_opacity > 0 else g0.opacities,
            colors=torch.sigmoid(c_logit0 + d_c) if config.lr_color > 0 else g0.colors,
        )
        # pruning drops Gaussians the refinement made transparent; with opacities frozen it would only
        # drop faint ones the feed-forward avatar draws too
        prune = config.prune_opacity > 0 and config.lr_opacity > 0
        kept = g.opacities >= config.prune_opacity if prune else torch.ones(n, dtype=torch.bool)
        g = g[kept]
        w2c_full = corrected_w2c(cams_in.w2c.float().cpu(), rot.detach(), trans.detach())
    dev = avatar.gaussians.device
    if config.keep_binding and avatar.prior is not None and len(avatar.prior) == len(avatar.gaussians):
        # the feed-forward binding and appended Gaussians, as the refinement rendered them
        b = avatar.prior
        kept_d = kept.to(b.vertex_ids.device)
        binding = b.concat(b.index(torch.nonzero(kept_d).squeeze(1)), b.index(torch.arange(n, len(b), device=b.vertex_ids.device)))
        g_all = Gaussians.concat([g.to(dev), avatar.gaussians[n:].detach().to(dev, g.means.dtype)])
        vb = avatar.view_blend  # per-view data of the kept reconstructed Gaussians (model/viewblend.py)
        vb = vb.subset(kept.to(vb.source_view.device)) if vb is not None and len(vb) == n else None
        out = CanonicalAvatar(g_all, avatar.model_name, avatar.expression_space, binding, avatar.num_interior, vb)
        if config.cheek_shell and (config.lr_opacity > 0 or config.lr_scale > 0):
            out = _with_cheek_shell(model, out, int(kept.sum()))
    else:
        out = CanonicalAvatar(g.to(dev), avatar.model_name, avatar.expression_space)
        if avatar.prior is not None:
            model.attach_prior(out)
    cams_out = Cameras(cams_in.K.float().cpu(), w2c_full, cams_in.width, cams_in.height)
    timings = {"setup": t_setup, "optimize": t_opt, "total": time.perf_counter() - t_start, "steps": config.steps}
    return RefineResult(out, cams_out, rot.detach().clone(), trans.detach().clone(), losses, timings)
