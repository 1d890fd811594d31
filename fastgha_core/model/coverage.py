"""Fill each input view's silhouette: raise the opacity of a view's own Gaussians where the avatar
leaves its matte uncovered.

Why (issue 17, measured on the real photo sets): the network spreads opacity over the input views
(each view's Gaussians are opaque only on part of the head, the others are expected to fill in).
Off the tracked head (long hair, neck, shoulders) its opacities are low (mean 0.14-0.45 per view on
the real sets, against 0.6-0.8 on the head), and when only one view sees such a region nobody fills
in: rendered at the inputs' own cameras the avatar leaves 3-8 % of the matte uncovered, and
leave-one-out renders leave up to 18 % (a long-haired subject's hair beside the face). Those pixels
cost more than the blur of the covered ones on some sets (``refine.realsets``, ``error_split``).

``fill_coverage``: render all views' Gaussians at every input camera (they sit on their pixel rays,
so view ``i``'s Gaussian of pixel ``p`` is centred on ``p`` in view ``i``), and where a foreground
pixel's accumulated opacity ``a`` is below ``target``, raise that pixel's own Gaussian's opacity
from ``o`` to the value that would bring the pixel to ``target`` if the others stayed as they are:
``o' = 1 - (1 - target) (1 - o) / (1 - a)`` (alpha compositing: the transmittance is the product
of the ``1 - o_k``; the own Gaussian peaks at 1 on its pixel's centre). Opacities only go up,
background and ``exclude``-d pixels are untouched, and pixels already covered keep theirs. It is
a closed-form step (no optimisation, no gradients): a rendering of ``V`` input views at input size.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..cameras import Cameras
from ..gaussians import Gaussians

__all__ = ["fill_coverage", "in_front_of_other_heads"]


def fill_coverage(
    g: Gaussians, cameras: Cameras, foreground: Tensor, target: float = 0.9, exclude: Tensor | None = None, max_opacity: float = 0.99
) -> tuple[Gaussians, Tensor]:
    """Raise the opacities of pixel-aligned Gaussians so that every input view's matte is covered.

    Args:
        g: ``V * H * W`` Gaussians, view-major, pixel ``(y, x)`` of view ``i`` at index
            ``i * H * W + y * W + x``, each centred on its own pixel's ray of ``cameras[i]``
            (``FastGHA.forward_gaussians``' layout, before any pruning).
        cameras: ``Cameras [V]`` of the ``W x H`` input views.
        foreground: ``[V, H, W]`` in [0, 1], the inputs' foreground (``gaussian_head.foreground_weight``);
            pixels above 0.5 are filled.
        target: accumulated opacity in (0, 1) each foreground pixel is brought to (at least).
        exclude: optional ``[V, H, W]`` bool, pixels whose Gaussian must stay as it is (e.g. dropped ones).
        max_opacity: upper bound of a raised opacity.
    Returns:
        ``(gaussians, alpha)``: the Gaussians with raised opacities (same order and count) and the
        accumulated opacity ``[V, H, W]`` of the input views before the change.
    Raises:
        ValueError: when the sizes disagree or ``target`` is not in (0, 1).
    """
    from ..render import render

    cams = cameras.flatten()
    v, h, w = len(cams.K), cams.height, cams.width
    if not 0.0 < target < 1.0:
        raise ValueError(f"fill_coverage: target must be in (0, 1), got {target}")
    if len(g) != v * h * w:
        raise ValueError(f"fill_coverage: expected {v} x {h} x {w} = {v * h * w} pixel-aligned Gaussians, got {len(g)}")
    if tuple(foreground.shape) != (v, h, w):
        raise ValueError(f"fill_coverage: foreground must have shape [{v}, {h}, {w}], got {list(foreground.shape)}")
    if exclude is not None and tuple(exclude.shape) != (v, h, w):
        raise ValueError(f"fill_coverage: exclude must have shape [{v}, {h}, {w}], got {list(exclude.shape)}")
    with torch.no_grad():
        alpha = render(g.detach(), cams.to(g.means.device, torch.float32)).alpha[:, 0].to(g.opacities)  # [V, H, W]
    need = (foreground.to(alpha.device) > 0.5) & (alpha < target)
    if exclude is not None:
        need &= ~exclude.to(alpha.device)
    o = g.opacities.reshape(v, h, w)
    raised = 1.0 - (1.0 - target) * (1.0 - o) / (1.0 - alpha).clamp_min(1.0 - target)
    new = torch.where(need, torch.maximum(o, raised.clamp(max=max_opacity)), o)
    return g.replace(opacities=new.reshape(-1)), alpha


def in_front_of_other_heads(t: Tensor, hit: Tensor, take: Tensor, cameras: Cameras, foreground: Tensor, views: int | None = None, tol_m: float = 0.01) -> Tensor:
    """``bool [V, H, W]``: the ``take`` pixels whose point lies in front of another view's head.

    Why (issue 17, real photos): on a tracked head surface each pixel that misses the head (hair
    beside the face, neck, shoulders) lies at the nearest head pixel's distance, a guess. Seen from
    another input camera such a point can fall onto that view's head pixels, between its camera and
    the head it sees there: that photo shows the head, not hair, at that pixel, so the point is in
    space the photo sees empty (free-space carving, as in space carving, Kutulakos and Seitz 2000).
    Drawn there, it streaks hair across the face in renders near that view.

    A pixel ``p`` of view ``s`` (with ``take[s, p]``) is flagged when, for some other view ``r``
    among the first ``views`` (the real photos; default all), its point ``o_s + t[s, p] d_s``
    projects inside ``r``'s image onto a pixel ``q`` with ``hit[r, q]`` and ``foreground[r, q] >
    0.5``, and its camera-space depth in ``r`` is smaller by more than ``tol_m`` than the smallest
    depth of ``r``'s head points over the 3x3 pixels around ``q`` (the 3x3 minimum forgives a pixel
    of misregistration at the head's outline).

    Args:
        t: ``[V, H, W]`` metres along each pixel's unit ray (``surface.SurfaceDepth.t``).
        hit: ``[V, H, W]`` bool, the pixels on the head (``SurfaceDepth.hit``): the judges' surface.
        take: ``[V, H, W]`` bool, the pixels to test (e.g. ``~hit`` inside the matte).
        cameras: ``Cameras [V]`` of size ``W x H`` (OpenCV, ``cameras.py``).
        foreground: ``[V, H, W]`` in [0, 1] (``gaussian_head.foreground_weight``).
        views: how many leading views judge (mirrored virtual views after them are judged only).
        tol_m: metres.
    Raises:
        ValueError: on mismatched shapes.
    """
    import torch.nn.functional as F

    cams = cameras.flatten().to("cpu", torch.float32)
    v, h, w = len(cams.K), cams.height, cams.width
    for name, x in (("t", t), ("hit", hit), ("take", take), ("foreground", foreground)):
        if tuple(x.shape) != (v, h, w):
            raise ValueError(f"in_front_of_other_heads: {name} must be [{v}, {h}, {w}], got {list(x.shape)}")
    nv = v if views is None else int(views)
    t, hit, take, fg = t.detach().float().cpu(), hit.cpu().bool(), take.cpu().bool(), foreground.detach().float().cpu() > 0.5
    o, d = cams.pixel_rays()  # [V, H, W, 3]
    pts = o + t[..., None] * d
    z = cams.world_to_camera(pts.reshape(v, -1, 3))[..., 2].reshape(v, h, w)  # each view's own depths
    zh = torch.where(hit & fg, z, torch.full_like(z, float("inf")))
    zmin = -F.max_pool2d(-zh[:, None], 3, stride=1, padding=1)[:, 0]  # [V, H, W], inf where no head point near
    out = torch.zeros(v, h, w, dtype=torch.bool)
    for s in range(v):
        idx = take[s].reshape(-1).nonzero()[:, 0]
        if len(idx) == 0:
            continue
        p = pts[s].reshape(-1, 3)[idx]
        bad = torch.zeros(len(idx), dtype=torch.bool)
        for r in range(nv):
            if r == s:
                continue
            uv, zr = cams[r].project(p)
            x, y = uv[:, 0].floor().long(), uv[:, 1].floor().long()
            inside = (x >= 0) & (x < w) & (y >= 0) & (y < h) & (zr > 0)
            xi, yi = x.clamp(0, w - 1), y.clamp(0, h - 1)
            on = hit[r, yi, xi] & fg[r, yi, xi]
            bad |= inside & on & (zr < zmin[r, yi, xi] - tol_m)
        out[s].view(-1)[idx] = bad
    return out
