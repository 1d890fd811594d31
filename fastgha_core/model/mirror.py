"""Mirrored virtual views: a turned photo, flipped left-right, as a photo of the other side of the head.

Why (issue 17, measured on the real photo sets): leave-one-out renders of side views (phone-5's
-70° and +85°, studio-4's +55° and -70°) show the side of the head the left-out photo saw (cheek,
ear, hair) as horizontal stripes or leave it uncovered: no remaining photo sees it except frontal
views at grazing angles. Heads are nearly left-right symmetric, so the mirror image of a photo
turned to one side is a plausible photo of the other side, taken from the mirrored camera.

A view is mirrored across the head's sagittal plane (the head frame's ``x = 0`` plane;
``docs/conventions.md``: metres, +x the subject's left, +y up, +z out of the face):

- image and matte: flipped left-right (``flip_images``);
- camera (``mirror_cameras``): with the reflection ``S`` of the world across that plane
  (``sagittal_reflection``: ``diag(-1, 1, 1)`` in the head frame, conjugated by ``head_to_world``
  when the surface has one) and ``F = diag(-1, 1, 1)`` in camera coordinates (OpenCV, x right),
  ``w2c' = F w2c S`` (a proper rotation: two reflections), and the intrinsics mirrored in ``x``:
  ``cx' = W - cx``, skew negated. Pixel centres sit at ``j + 0.5`` (``cameras.py``), so a world point
  ``X`` that the original camera projects to ``(u, v)`` projects through the mirrored camera, as
  ``S X``, to ``(W - u, v)``: pixel column ``j`` becomes column ``W - 1 - j`` exactly;
- expression (``mirror_expressions``): the ict53 weights with each ``_L``/``_R`` pair and
  ``jawLeft``/``jawRight``, ``mouthLeft``/``mouthRight`` swapped (``ict53_mirror_permutation``);
- surface depth (``flip_surface_depth``): a mirror is an isometry, so the distance along the
  mirrored pixel's ray to the mirrored head equals the original pixel's distance: the tracked
  head's ray-depth maps (``model/surface.py``) flipped left-right. The mirrored Gaussians then lie on
  ``S`` of the tracked head (same identity, mirrored pose and expression), which differs from the
  tracked head itself only by the fitted identity's own asymmetry (millimetres).

Only views turned by at least ``GaussianHeadConfig.mirror_min_yaw_deg`` are mirrored
(``view_yaw_deg``): a near-frontal photo's mirror would lay a second, flipped copy of an asymmetric
face over the real one. ``FastGHA.reconstruct`` builds the mirrored views' Gaussians in a second
network pass (the network sees at most ``config.max_views`` views), fills their mattes only after
the real views' (``model/coverage.py``: the real views' Gaussians are exactly those without
mirroring), and registers them as extra source views of the view-dependent blending
(``model/viewblend.py``): a frame draws a mirrored view's Gaussians fully only where its camera is
nearer the render camera than every real view that sees the point.

Real photos keep precedence near their own cameras: the blending counts every mirrored view
``mirror_blend_offset_deg`` (40 by default) further from the render camera than it is
(``ViewBlend.offsets``), so at a photo's own camera a mirrored view 8.5 degrees away draws at
exp(-48.5 / 20) ~ 0.09 instead of ~0.65 (without it, phone-5's -70-degree photo was reproduced at its
own camera 1.2 dB worse than without mirroring; with it 0.1 dB), while a side no photo sees still
gets its mirrored view in full. Two other ways were measured and are off by default
(``docs/model-card-log.md``: each cost identity on some set): ``mirror_drop_seen_deg > 0`` drops the
mirrored Gaussians whose point a real view sees well (inside its matte, not occluded, at an incidence
below that angle: ``seen_by_views``), and ``mirror_midline_m > 0`` those near the sagittal plane
(``near_midline``; both in ``thin_mirrored``).
The feature is on by default (``mirror_views``): it raised leave-one-out PSNR on every real set
(+1.07 / +1.72 / +0.25 dB with the 40-degree offset) and turned the side views' stripes into cheek,
ear and hair, with mean identity unchanged (0.5302 -> 0.5304); it costs 24-42% more Gaussians and
frame time on avatars whose photos are turned (the server's ``FASTGHA_MIRROR_VIEWS=false`` turns it off).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..cameras import Cameras

__all__ = [
    "ict53_mirror_permutation",
    "mirror_expressions",
    "sagittal_reflection",
    "mirror_points",
    "mirror_cameras",
    "flip_images",
    "flip_surface_depth",
    "view_yaw_deg",
    "turned_views",
    "MirroredViews",
    "mirrored_views",
    "surface_normals",
    "seen_by_views",
    "near_midline",
    "thin_mirrored",
]


def _twin(name: str) -> str:
    """The ict53 name of ``name``'s mirror twin (itself for a symmetric shape)."""
    for a, b in (("_L", "_R"), ("Left", "Right")):
        if name.endswith(a):
            return name[: -len(a)] + b
        if name.endswith(b):
            return name[: -len(b)] + a
    return name


def ict53_mirror_permutation(names=None) -> list[int]:
    """``perm [53]`` with ``mirrored[i] = expression[perm[i]]``: each name's mirror twin.

    ``names``: the expression names (default ``expressions.ICT53_NAMES``, the ict53 vector layout).
    ``xxx_L`` <-> ``xxx_R`` (brows, cheeks, eyes incl. ``eyeLookIn``/``Out`` of each eye, mouth
    corners), ``jawLeft`` <-> ``jawRight``, ``mouthLeft`` <-> ``mouthRight``; the symmetric shapes
    (``jawOpen``, ``mouthFunnel``, ...) map to themselves.
    Raises ``ValueError`` when a name's twin is missing from ``names``.
    """
    if names is None:
        from ..expressions import ICT53_NAMES as names
    names = list(names)
    index = {n: i for i, n in enumerate(names)}
    perm = []
    for n in names:
        t = _twin(n)
        if t not in index:
            raise ValueError(f"ict53_mirror_permutation: {n!r} has no twin {t!r} among the names")
        perm.append(index[t])
    return perm


def mirror_expressions(expressions: Tensor | np.ndarray) -> Tensor:
    """``[..., 53]`` ict53 weights of the mirrored faces (left and right shapes swapped)."""
    e = torch.as_tensor(expressions)
    if e.shape[-1] != 53:
        raise ValueError(f"mirror_expressions: expected ict53 weights [..., 53], got {list(e.shape)}")
    return e[..., ict53_mirror_permutation()]


def sagittal_reflection(head_to_world: Tensor | np.ndarray | None = None, dtype=torch.float64) -> Tensor:
    """``[4, 4]`` world reflection across the head's sagittal plane: ``H diag(-1, 1, 1, 1) H^-1``.

    ``head_to_world``: the surface's rigid ``[4, 4]`` head-to-world transform (``HeadSurface``),
    None for the tracker's head-centric world (then ``diag(-1, 1, 1, 1)``). An involution (``S S = I``).
    """
    s = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=dtype))
    if head_to_world is None:
        return s
    h = torch.as_tensor(np.asarray(head_to_world), dtype=dtype)
    if tuple(h.shape) != (4, 4):
        raise ValueError(f"sagittal_reflection: head_to_world must be [4, 4], got {list(h.shape)}")
    return h @ s @ torch.linalg.inv(h)


def mirror_points(points: Tensor, head_to_world=None) -> Tensor:
    """``[..., 3]`` world points (metres) reflected across the head's sagittal plane."""
    s = sagittal_reflection(head_to_world).to(points.device, points.dtype)
    return points @ s[:3, :3].T + s[:3, 3]


def mirror_cameras(cameras: Cameras, head_to_world=None) -> Cameras:
    """The mirrored cameras (module doc): ``w2c' = F w2c S``, ``cx' = W - cx``, skew negated.

    ``cameras``: any batch of ``W x H`` cameras (world = the head frame, or ``head_to_world``'s world).
    Returns cameras of the same batch shape, size and dtype. An involution: mirroring twice gives
    the cameras back (up to rounding).
    """
    dt = cameras.K.dtype
    s = sagittal_reflection(head_to_world).to(cameras.K.device)
    f = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=torch.float64, device=cameras.K.device))
    w2c = (f @ cameras.w2c.double() @ s).to(dt)
    K = cameras.K.clone()
    K[..., 0, 2] = cameras.width - cameras.K[..., 0, 2]
    K[..., 0, 1] = -cameras.K[..., 0, 1]
    return Cameras(K, w2c, cameras.width, cameras.height)


def flip_images(images: Tensor) -> Tensor:
    """``[..., H, W]`` images, mattes or per-pixel maps flipped left-right (column ``j`` -> ``W - 1 - j``)."""
    return images.flip(-1)


def flip_surface_depth(sd):
    """A ``surface.SurfaceDepth`` of the mirrored views: every per-pixel map flipped left-right
    (ray distances are unchanged by a mirror; module doc)."""
    from .surface import SurfaceDepth

    return SurfaceDepth(flip_images(sd.t), flip_images(sd.hit), flip_images(sd.beyond_face), None if sd.face_hit is None else flip_images(sd.face_hit))


def _to_head(points: Tensor, head_to_world=None) -> Tensor:
    """``[N, 3]`` world points in the head frame (float64): ``R^T (p - t)`` of ``head_to_world``
    (None: the world is the head frame)."""
    p = points.double()
    if head_to_world is None:
        return p
    h = torch.as_tensor(np.asarray(head_to_world), dtype=torch.float64, device=p.device)
    return (p - h[:3, 3]) @ h[:3, :3]


def view_yaw_deg(cameras: Cameras, head_to_world=None) -> Tensor:
    """``[V]`` yaw of each camera around the head, degrees: ``atan2(c_x, c_z)`` of its centre ``c`` in
    the head frame (0 frontal, +90 seeing the subject's left side, -90 the right side)."""
    c = _to_head(cameras.flatten().centers, head_to_world)  # [V, 3]
    return torch.rad2deg(torch.atan2(c[:, 0], c[:, 2]))


def turned_views(cameras: Cameras, min_yaw_deg: float, head_to_world=None, limit: int | None = None) -> list[int]:
    """Indices of the views whose ``|yaw| >= min_yaw_deg`` (``view_yaw_deg``), most turned first,
    at most ``limit`` of them (None: all)."""
    yaw = view_yaw_deg(cameras, head_to_world).abs()
    idx = [int(i) for i in torch.argsort(yaw, descending=True, stable=True) if float(yaw[i]) >= float(min_yaw_deg)]
    return idx if limit is None else idx[: max(0, int(limit))]


@dataclass
class MirroredViews:
    """The mirrored virtual views of some input views (module doc).

    Attributes:
        source: ``[M]`` indices of the real views they mirror.
        images: ``[M, 3, S, S]`` flipped images in [0, 1] (matted on ``BACKGROUND_RGB``).
        cameras: ``Cameras [M]`` mirrored cameras of size ``S x S``.
        expressions: ``[M, 53]`` ict53 weights with left and right swapped, or None.
        depth: ``surface.SurfaceDepth`` of the mirrored views (the real views' maps, flipped).
    """

    source: list[int]
    images: Tensor
    cameras: Cameras
    expressions: Tensor | None
    depth: object

    def __len__(self) -> int:
        return len(self.source)


def mirrored_views(images: Tensor, cameras: Cameras, depth, expressions: Tensor | None, min_yaw_deg: float, head_to_world=None, limit: int | None = None) -> MirroredViews | None:
    """The mirrored views of the real views turned by at least ``min_yaw_deg`` (at most ``limit``,
    most turned first); None when there is none.

    Args:
        images: ``[V, 3, S, S]`` the real views; cameras: ``Cameras [V]`` of size ``S x S``.
        depth: their ``surface.SurfaceDepth``; expressions: ``[V, 53]`` ict53 weights or None.
        head_to_world: the surface's head-to-world transform (None: world = head frame).
    """
    src = turned_views(cameras, min_yaw_deg, head_to_world, limit)
    if not src:
        return None
    from .surface import SurfaceDepth

    sub = SurfaceDepth(depth.t[src], depth.hit[src], depth.beyond_face[src], None if depth.face_hit is None else depth.face_hit[src])
    return MirroredViews(
        source=src,
        images=flip_images(images[src]),
        cameras=mirror_cameras(cameras[src], head_to_world),
        expressions=None if expressions is None else mirror_expressions(expressions[src]),
        depth=flip_surface_depth(sub),
    )


def surface_normals(t: Tensor, cameras: Cameras) -> Tensor:
    """``[V, H, W, 3]`` unit normals of the surface that per-pixel ray distances ``t [V, H, W]``
    (metres) describe, from the steps to the neighbouring pixels' points (``surface.surface_steps``),
    turned towards the view's camera; zero where a pixel has no neighbour on the same surface."""
    from .surface import surface_steps

    steps, _ = surface_steps(t, cameras)
    n = torch.linalg.cross(steps[..., 0, :], steps[..., 1, :])
    o, d = cameras.flatten().to(t.device, torch.float32).pixel_rays()
    n = torch.where(((n * d).sum(-1, keepdim=True) > 0), -n, n)
    return torch.nn.functional.normalize(n, dim=-1)


def seen_by_views(points: Tensor, normals: Tensor, cameras: Cameras, foreground: Tensor, depth: Tensor, max_incidence_deg: float) -> Tensor:
    """``[N]`` bool: points that at least one of ``cameras`` sees well.

    A view sees a point well when the point is inside the view's matte and not occluded in it
    (``viewblend.coverage_masks`` with the view's own depth map) and the angle between the point's
    ``normals`` and its direction to the camera centre is below ``max_incidence_deg``.

    Args:
        points: ``[N, 3]`` world points (metres); normals: ``[N, 3]`` unit normals (zero: never well seen).
        cameras: ``Cameras [R]`` (``R <= 8``) of size ``W x H``; foreground, depth: ``[R, H, W]`` as
            ``coverage_masks`` takes them.
    """
    from .viewblend import coverage_masks

    cams = cameras.flatten().to(points.device, torch.float32)
    mask = coverage_masks(points, cams, foreground, depth).long()
    cos_max = float(np.cos(np.radians(max_incidence_deg)))
    out = torch.zeros(len(points), dtype=torch.bool, device=points.device)
    for i, c in enumerate(cams.centers):
        to_cam = torch.nn.functional.normalize(c[None] - points.float(), dim=-1)
        out |= (((mask >> i) & 1) == 1) & ((normals.float() * to_cam).sum(-1) >= cos_max)
    return out


def near_midline(points: Tensor, width_m: float, head_to_world=None) -> Tensor:
    """``[N]`` bool: world ``points [N, 3]`` within ``width_m`` metres of the head's sagittal plane
    (``|x| < width_m`` in the head frame; ``head_to_world`` as in ``sagittal_reflection``). There a
    point and its mirror image nearly coincide: a mirrored view adds no side the real views miss,
    only a flipped copy of an asymmetric midline (nose, parting)."""
    return _to_head(points, head_to_world)[:, 0].abs() < float(width_m)


def thin_mirrored(g, v_real: int, images: Tensor, cameras: Cameras, t: Tensor, config, head_to_world=None):
    """Drop mirrored Gaussians by ``config`` (a ``GaussianHeadConfig``): those within
    ``mirror_midline_m`` of the sagittal plane (``near_midline``) and those a real view sees at an
    incidence below ``mirror_drop_seen_deg`` (``seen_by_views``; both 0 = off, the defaults).

    Args:
        g: ``V * S * S`` pixel-aligned Gaussians, view-major, the first ``v_real`` views real, the
            rest mirrored (``FastGHA.reconstruct``'s layout before pruning).
        images: ``[V, 3, S, S]`` matted views; cameras: ``Cameras [V]``; t: ``[V, S, S]`` ray depths (metres).
        head_to_world: the surface's head-to-world transform (None: world = head frame).
    Returns:
        ``(gaussians, dropped)``: dropped Gaussians get opacity 0 (pruning removes them), and
        ``dropped [V, S, S]`` bool marks their pixels (None when nothing was asked): a mirrored view
        must not count as seeing a point there (``viewblend.coverage_masks``), or the real views'
        Gaussians would fade towards it over a hole.
    """
    from .gaussian_head import foreground_weight
    from .viewblend import view_depth_maps

    v = images.shape[0]
    n_r = len(g) // v * v_real
    dev = g.means.device
    drop = torch.zeros(len(g) - n_r, dtype=torch.bool, device=dev)
    asked = False
    if config.mirror_midline_m > 0:
        drop |= near_midline(g.means[n_r:], config.mirror_midline_m, head_to_world)
        asked = True
    if config.mirror_drop_seen_deg > 0:
        c32, fg = cameras.to(dev, torch.float32), foreground_weight(images.to(dev, torch.float32))
        thr = max(float(config.prune_opacity), 1e-6)
        depth = view_depth_maps(g.means[:n_r], c32[:v_real], (g.opacities[:n_r] >= thr) & (fg[:v_real].reshape(-1) > 0.5))
        normals = surface_normals(t[v_real:].to(dev), c32[v_real:]).reshape(-1, 3)
        drop |= seen_by_views(g.means[n_r:], normals, c32[:v_real], fg[:v_real], depth, config.mirror_drop_seen_deg)
        asked = True
    if not asked:
        return g, None
    g = g.replace(opacities=torch.cat([g.opacities[:n_r], g.opacities[n_r:] * (~drop).to(g.opacities.dtype)]))
    return g, torch.cat([torch.zeros(n_r, dtype=torch.bool, device=dev), drop]).reshape(v, *images.shape[-2:])
