"""Non-rigid registration of the input views' textures to each other by dense optical flow (issue 17).

Why (measured on the real photo sets, ``docs/model-card-log.md`` "Is the blur input resolution?"): on
the tracked-surface path every pixel of every input view puts a Gaussian on the one tracked head
(``model/surface.py``), coloured from that pixel. Tracking leaves the photos a few millimetres off
each other on that head (landmark residuals ~2 px of a 256² crop on frontal photos, 3-4 px on
70-85° views), so in a frame the other views' Gaussians cover each face with their own texture a
little displaced: doubled eye edges, smears, lost identity. A rigid photometric correction of the
poses in tracking (``tracking/photoalign.py``) helps a little but bends the cameras off the truth.

What this does instead, at reconstruction only, per view (``register_views``):

1. The views are registered in a chain: the root is the most frontal view (``frontal_view``); the
   others follow in order of their camera's angle from the root's (seen from the head centre), and
   each is registered to the already registered view nearest it by that angle.
2. The neighbour's (registered) image is reprojected into view ``i`` through the tracked surface
   (``reproject``): each pixel of ``i`` whose ray hits the head is carried to its surface point and
   looked up in the neighbour's image, where the neighbour sees that point too (unoccluded, inside
   both mattes, both views within ``max_incidence_deg`` of the surface normal).
3. Dense optical flow (OpenCV's DIS, ``dense_flow``) from that reprojection to photo ``i``, on
   locally contrast-normalised grey images (the views' lighting differs), kept where a forward and
   a backward flow agree inside the overlap.
4. The kept flow is smoothed (normalised convolution, ``smooth_flow``) and extrapolated outside the
   overlap with a fade to zero, clipped to ``clip_px`` pixels, and held inside the view's matte
   (a pixel never samples beyond its matte, so the mattes and the silhouette do not move).
5. View ``i``'s image is resampled along it (``warp_image``): pixel ``p`` takes photo ``i``'s colour at
   ``p + flow(p)``, so its texture lands on the surface where the neighbour sees it.

Pixels whose flow is exactly zero keep their colour bit for bit, so a zero flow gives the inputs
unchanged. ``FastGHA.reconstruct`` calls this on the real views before the network sees them
(``GaussianHeadConfig.flow_register``), so the mirrored views are built from registered images.
Frames are untouched (the avatar is just built from other colours).

Measured on the real photo sets (``docs/model-card-log.md`` "Registering the views' textures by optical
flow"): the flows on the face are ~1 pixel of a 256² crop (median; p90 ~4), and registering them
leaves the leave-one-out identity where it was (mean 0.529) and lowers PSNR by up to 0.1 dB: the
frontal renders gain a little, the turned ones lose. A single photo's own avatar at its own camera
already reads about as far from the photo, so the cross-view misregistration is not what bounds
identity there. Off by default.

Units: flows are in pixels of the images given (``x`` to the right, ``y`` down, OpenCV's order);
``*_px`` parameters are in pixels at an image side of 256 and scale with the image (the tracker's
crops are 256², the tiny model's inputs 128²). Cameras as ``fastgha_core.cameras`` (OpenCV,
pixel ``(j, i)``'s centre at ``(j + 0.5, i + 0.5)``); distances in metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..cameras import Cameras

__all__ = [
    "FlowRegistration",
    "frontal_view",
    "registration_order",
    "surface_correspondence",
    "reproject",
    "dense_flow",
    "smooth_flow",
    "warp_image",
    "register_views",
]

FLOW_SIDE_PX = 256.0  # the image side at which the *_px parameters are given (they scale with the image)


@dataclass
class FlowRegistration:
    """What ``register_views`` did.

    Attributes:
        images: ``[V, 3, H, W]`` the registered images (the root and views without overlap unchanged).
        flow: ``[V, H, W, 2]`` float32 pixels ``(dx, dy)``: registered pixel ``p`` took the original's
            colour at ``p + flow[p]`` (zero for the root).
        parent: ``[V]`` the view each was registered to (-1 for the root and skipped views).
        overlap: ``[V, H, W]`` bool: the pixels whose flow was measured (kept by the consistency check).
    """

    images: Tensor
    flow: Tensor
    parent: list[int]
    overlap: Tensor


def _head_directions(cameras: Cameras, centre: Tensor | None) -> Tensor:
    """``[V, 3]`` unit directions from the head centre to each camera (world)."""
    c = cameras.flatten().centers.double()
    o = torch.zeros(3, dtype=torch.float64) if centre is None else torch.as_tensor(centre, dtype=torch.float64)
    return torch.nn.functional.normalize(c - o.to(c.device), dim=-1)


def frontal_view(cameras: Cameras, head_to_world=None) -> int:
    """Index of the camera nearest the face's front: the largest cosine between its direction from
    the head centre and the head's +z axis (out of the face, ``docs/conventions.md``), both in the
    world; ``head_to_world`` ``[4, 4]`` (None: the world is the head frame)."""
    if head_to_world is None:
        z, centre = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), None
    else:
        h = torch.as_tensor(np.asarray(head_to_world), dtype=torch.float64)
        z, centre = h[:3, 2], h[:3, 3]
    return int(torch.argmax(_head_directions(cameras, centre) @ z))


def registration_order(cameras: Cameras, root: int, centre: Tensor | None = None, views: list[int] | None = None) -> list[tuple[int, int]]:
    """``(view, parent)`` pairs in the order ``register_views`` registers them: the ``views`` (default
    all) other than ``root`` sorted by the angle of their camera from the root's (seen from
    ``centre``, default the world origin), each with the already registered view (the root or an
    earlier one) whose camera is nearest it by that angle."""
    d = _head_directions(cameras, centre)
    cos = (d @ d.T).clamp(-1, 1)
    todo = [i for i in (range(len(d)) if views is None else views) if i != root]
    todo.sort(key=lambda i: -float(cos[root, i]))
    done, out = [root], []
    for i in todo:
        p = max(done, key=lambda j: float(cos[i, j]))
        out.append((i, p))
        done.append(i)
    return out


def _points(cameras: Cameras, t: Tensor) -> Tensor:
    o, d = cameras.pixel_rays()
    return o + t[..., None] * d


def surface_correspondence(surface, dst: int, src: int, camera: Cameras, hair_m=0.0) -> Tensor:
    """``[H, W, 3]`` world points (metres): for each pixel of view ``dst`` (``camera``, ``W x H``), the
    point of view ``src``'s tracked surface (its own expression) that corresponds to the point
    ``dst``'s ray hits on ``dst``'s surface (the same place of the same triangle); NaN where the ray
    misses the head. ``hair_m``: as ``surface.surface_ray_depth``'s. Views of one expression give the
    hit point itself."""
    from ..data.headmodel import HeadModel
    from ..data.meshraster import render_mesh
    from .surface import _view_mesh

    head = HeadModel.load()
    faces = head.visible_faces(eyelashes=False)
    cam = camera.flatten().to("cpu", torch.float64)
    w2c, K = cam.w2c[0].numpy(), cam.K[0].numpy()
    vd = _view_mesh(surface, dst, head, faces, hair_m)
    vs = vd if src == dst else _view_mesh(surface, src, head, faces, hair_m)
    m = render_mesh((vd @ w2c[:3, :3].T + w2c[:3, 3]).astype(np.float32), faces, vs.astype(np.float32), K, cam.width, cam.height, supersample=1)
    a = m.alpha[..., None]
    out = np.where(a > 0.99, m.color / np.maximum(a, 1e-6), np.nan)
    return torch.from_numpy(out.astype(np.float32))


def reproject(image: Tensor, cam_src: Cameras, t_src: Tensor, hit_src: Tensor, fg_src: Tensor, cam_dst: Cameras, t_dst: Tensor, hit_dst: Tensor,
              fg_dst: Tensor, tol_m: float = 0.006, max_incidence_deg: float = 70.0, corr: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """View ``src``'s image seen at view ``dst``'s pixels through the tracked surface.

    Each pixel of ``dst`` whose ray hits the head (``hit_dst``) is carried to its surface point
    (``t_dst``, metres along its unit ray) and projected into ``src``; there the image is read
    bilinearly. The pixel is ``ok`` when ``src`` sees that point: it projects inside ``src``'s image
    onto a hit pixel whose own ray distance agrees with the point's distance from ``src``'s camera
    within ``tol_m`` (not occluded), inside both mattes (``fg > 0.5``), and both cameras see the
    surface there within ``max_incidence_deg`` of its normal (``mirror.surface_normals``).

    Args:
        image: ``[3, H, W]`` view ``src``'s image; cam_src, cam_dst: single cameras (batch ``[1]``
            or ``[]``) of ``W x H`` images in one world.
        t_src, t_dst: ``[H, W]`` ray distances (``surface.SurfaceDepth.t``); hit_src, hit_dst:
            ``[H, W]`` bool; fg_src, fg_dst: ``[H, W]`` foreground in [0, 1].
    Returns:
        ``(colour [3, H, W], ok [H, W] bool)``: ``colour`` is ``src``'s image where ``ok`` and 0 elsewhere.
    """
    from .mirror import surface_normals

    cs, cd = cam_src.flatten().to("cpu", torch.float32), cam_dst.flatten().to("cpu", torch.float32)
    h, w = t_dst.shape
    p = _points(cd, t_dst.float()[None])[0]  # [H, W, 3]
    q = p if corr is None else torch.where(torch.isfinite(corr), corr.float(), p)
    uv, z = cs[0].project(q.reshape(-1, 3))
    x, y = uv[:, 0], uv[:, 1]
    ix, iy = x.floor().long(), y.floor().long()
    inside = (z > 0) & (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    ixc, iyc = ix.clamp(0, w - 1), iy.clamp(0, h - 1)
    dist = (q.reshape(-1, 3) - cs.centers[0]).norm(dim=-1)
    seen = inside & hit_src[iyc, ixc] & ((t_src.float()[iyc, ixc] - dist).abs() < tol_m) & (fg_src[iyc, ixc] > 0.5)
    ok = seen.reshape(h, w) & hit_dst & (fg_dst > 0.5)
    cos_min = math.cos(math.radians(max_incidence_deg))
    n = surface_normals(t_dst.float()[None], cd)[0]  # [H, W, 3] towards dst's camera
    _, dd = cd.pixel_rays()
    cos_d = -(n * dd[0]).sum(-1)
    to_src = torch.nn.functional.normalize(cs.centers[0] - q, dim=-1)
    cos_s = (n * to_src).sum(-1)
    ok &= (cos_d > cos_min) & (cos_s > cos_min)
    grid = torch.stack([x / w * 2 - 1, y / h * 2 - 1], -1).reshape(1, h, w, 2)
    col = torch.nn.functional.grid_sample(image.float()[None].cpu(), grid, mode="bilinear", padding_mode="border", align_corners=False)[0]
    return col * ok, ok


def _normalised_grey(img: np.ndarray, sigma: float) -> np.ndarray:
    """``uint8 [H, W]``: the luminance of ``img [H, W, 3]`` (0..1) minus its local mean, divided by its
    local standard deviation (Gaussians of ``sigma`` pixels), mapped to 128 +- 40 per deviation."""
    import cv2

    g = img @ np.array([0.299, 0.587, 0.114], np.float32)
    mu = cv2.GaussianBlur(g, (0, 0), sigma)
    var = cv2.GaussianBlur(g * g, (0, 0), sigma) - mu * mu
    n = (g - mu) / np.sqrt(np.maximum(var, 0) + 1e-4)
    return np.clip(128 + 40 * n, 0, 255).astype(np.uint8)


def dense_flow(a: np.ndarray, b: np.ndarray, scale: int = 2, norm_sigma_px: float = 8.0) -> tuple[np.ndarray, np.ndarray]:
    """Forward and backward DIS optical flow between two colour images (OpenCV
    ``DISOpticalFlow``, medium preset, on ``_normalised_grey`` images enlarged ``scale`` times).

    Args:
        a, b: ``[H, W, 3]`` float32 images in [0, 1].
        scale: both images are enlarged by this factor (bicubic) before the flow and the flow is
            brought back, for sub-pixel flow on small inputs.
        norm_sigma_px: the local contrast normalisation's window (pixels at a side of 256).
    Returns:
        ``(f_ab, f_ba)``, ``[H, W, 2]`` float32 pixels: ``a(p) ~ b(p + f_ab(p))``, ``b(p) ~ a(p + f_ba(p))``.
    """
    import cv2

    h, w = a.shape[:2]
    up = lambda x: cv2.resize(x, (w * scale, h * scale), interpolation=cv2.INTER_CUBIC) if scale != 1 else x  # noqa: E731
    sig = norm_sigma_px * w * scale / FLOW_SIDE_PX
    ga, gb = _normalised_grey(up(a), sig), _normalised_grey(up(b), sig)
    dis = cv2.DISOpticalFlow_create(cv2.DISOpticalFlow_PRESET_MEDIUM)
    out = []
    for x, y in ((ga, gb), (gb, ga)):
        f = dis.calc(x, y, None)
        if scale != 1:
            f = cv2.resize(f, (w, h), interpolation=cv2.INTER_AREA) / scale
        out.append(f.astype(np.float32))
    return out[0], out[1]


def _consistent(f_ab: np.ndarray, f_ba: np.ndarray, tol_px: float) -> np.ndarray:
    """``bool [H, W]``: where following ``f_ab`` and then ``f_ba`` comes back within ``tol_px``."""
    import cv2

    h, w = f_ab.shape[:2]
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    back = cv2.remap(f_ba, gx + f_ab[..., 0], gy + f_ab[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.linalg.norm(f_ab + back, axis=-1) < tol_px


def smooth_flow(flow: np.ndarray, weight: np.ndarray, sigma_px: float, falloff_px: float) -> np.ndarray:
    """A smooth flow from the measured ``flow [H, W, 2]`` where ``weight [H, W] > 0``.

    Normalised convolution with a Gaussian of ``sigma_px`` pixels (``sum G w f / sum G w``), then
    multiplied by ``exp(-d / falloff_px)``, ``d`` the distance (pixels) to the nearest measured pixel:
    inside the overlap the local average of the measurement, outside it a continuation fading to
    zero (never invented motion). ``falloff_px <= 0``: zero outside the measured pixels. Zero
    everywhere when nothing is measured. Pixels here are the image's own."""
    import cv2
    from scipy.ndimage import distance_transform_edt

    wgt = weight.astype(np.float32)
    if not (wgt > 0).any():
        return np.zeros_like(flow, dtype=np.float32)
    num = np.stack([cv2.GaussianBlur(flow[..., c] * wgt, (0, 0), sigma_px) for c in range(2)], -1)
    den = cv2.GaussianBlur(wgt, (0, 0), sigma_px)
    f = num / np.maximum(den, 1e-6)[..., None]
    d = distance_transform_edt(wgt <= 0)
    fade = np.exp(-d / falloff_px) if falloff_px > 0 else (d == 0).astype(np.float32)
    f = f * fade[..., None] * (den > 1e-6)[..., None]
    return f.astype(np.float32)


def warp_image(image: Tensor, flow: Tensor) -> Tensor:
    """``image [3, H, W]`` resampled along ``flow [H, W, 2]`` (pixels, ``(dx, dy)``): pixel ``p`` takes
    the bilinear colour at ``p + flow(p)`` (borders replicated). Pixels whose flow is exactly zero
    keep their own colour bit for bit."""
    h, w = image.shape[-2:]
    f = flow.to(image.device, torch.float32)
    gy, gx = torch.meshgrid(torch.arange(h, dtype=torch.float32, device=f.device), torch.arange(w, dtype=torch.float32, device=f.device), indexing="ij")
    x, y = gx + 0.5 + f[..., 0], gy + 0.5 + f[..., 1]
    grid = torch.stack([x / w * 2 - 1, y / h * 2 - 1], -1)[None]
    out = torch.nn.functional.grid_sample(image[None].float(), grid, mode="bilinear", padding_mode="border", align_corners=False)[0].to(image.dtype)
    moved = (f != 0).any(-1)
    return torch.where(moved[None], out, image)


def _inside_matte_distance(fg: np.ndarray) -> np.ndarray:
    """Distance (pixels) from each pixel to the nearest pixel not fully inside the matte (``fg < 1``)."""
    from scipy.ndimage import distance_transform_edt

    return distance_transform_edt(fg >= 1.0).astype(np.float32)


def register_views(images: Tensor, cameras: Cameras, depth, surface=None, hair_m=0.0, views: list[int] | None = None, clip_px: float = 4.0,
                   sigma_px: float = 4.0, falloff_px: float = 6.0, consistency_px: float = 1.0, max_incidence_deg: float = 70.0,
                   tol_m: float = 0.006, min_overlap: int = 50, where: Tensor | None = None, mode: str = "chain", flow_fn=None) -> FlowRegistration:
    """Register the textures of input views to each other by optical flow (module doc).

    Args:
        images: ``[V, 3, H, W]`` in [0, 1], matted on ``BACKGROUND_RGB``.
        cameras: ``Cameras [V]`` of the ``W x H`` images (one world with the surface).
        depth: their ``surface.SurfaceDepth`` (``t``, ``hit``).
        surface: the ``surface.HeadSurface`` of the views (optional): its ``head_to_world`` orients
            the head, and its per-view expressions give ``surface_correspondence`` (without it the
            views are taken to share one expression, world = head frame).
        hair_m: the hair thickness ``depth`` was laid out with (``surface.surface_ray_depth``).
        views: the views to register (default all); the others are left as they are.
        clip_px: the largest flow (pixels at a side of 256).
        sigma_px, falloff_px: ``smooth_flow``'s smoothing and fade (pixels at a side of 256).
        consistency_px: the forward-backward tolerance (pixels at a side of 256).
        max_incidence_deg, tol_m: ``reproject``'s.
        min_overlap: a view with fewer measured pixels is left unchanged.
        where: optional ``[V, H, W]`` bool: the only pixels whose flow is measured (e.g.
            ``SurfaceDepth.face_hit``, the bare face); the flow still continues beyond them, fading.
        mode: ``"chain"`` (module doc: each view onto its registered neighbour, from the most frontal
            one) or ``"mean"`` (each view, unregistered, halfway towards every other view that sees
            its points: ``sum_j c_j f_j / (1 + sum_j c_j)``, ``f_j`` its faded flow onto view ``j`` and
            ``c_j`` that flow's fade weight; no root, ``parent`` stays -1).
        flow_fn: the flow estimator (default ``dense_flow``): ``(a, b) -> (f_ab, f_ba)`` as there.
    Returns:
        ``FlowRegistration``.
    Raises:
        ValueError: on mismatched shapes or a negative parameter.
    """
    from .gaussian_head import foreground_weight

    cams = cameras.flatten().to("cpu", torch.float32)
    v, _, h, w = images.shape
    if len(cams.K) != v or (cams.width, cams.height) != (w, h) or tuple(depth.t.shape) != (v, h, w):
        raise ValueError(f"register_views: expected {v} cameras of {w}x{h} and depth [{v}, {h}, {w}], got {len(cams.K)}, {cams.width}x{cams.height}, {list(depth.t.shape)}")
    if mode not in ("chain", "mean"):
        raise ValueError(f"register_views: mode must be 'chain' or 'mean', got {mode!r}")
    if min(clip_px, sigma_px, consistency_px, tol_m) <= 0 or falloff_px < 0 or not 0 < max_incidence_deg <= 90:
        raise ValueError("register_views: clip_px, sigma_px, consistency_px and tol_m must be > 0, falloff_px >= 0, max_incidence_deg in (0, 90]")
    flow_fn = flow_fn or dense_flow
    k = w / FLOW_SIDE_PX
    imgs = images.detach().float().cpu()
    fg = foreground_weight(imgs)
    t, hit = depth.t.float().cpu(), depth.hit.cpu()
    out = imgs.clone()
    flows = torch.zeros(v, h, w, 2)
    overlap = torch.zeros(v, h, w, dtype=torch.bool)
    parent = [-1] * v
    sel = list(range(v)) if views is None else [int(i) for i in views]
    if len(sel) < 2:
        return FlowRegistration(images.clone(), flows, parent, overlap)
    head_to_world = None if surface is None else surface.head_to_world
    centre = None if head_to_world is None else torch.as_tensor(np.asarray(head_to_world)[:3, 3])

    def pair(i: int, p: int, src: Tensor):
        """View ``i``'s smoothed, faded flow onto view ``p`` (whose image is ``src``) and its measured pixels, or None."""
        corr = None if surface is None else surface_correspondence(surface, i, p, cams[i], hair_m)
        ref, ok = reproject(src, cams[p], t[p], hit[p], fg[p], cams[i], t[i], hit[i], fg[i], tol_m, max_incidence_deg, corr)
        if where is not None:
            ok = ok & where[i].cpu()
        if int(ok.sum()) < min_overlap:
            return None
        a = imgs[i].permute(1, 2, 0).numpy()
        ref_np = torch.where(ok[None], ref, imgs[i]).permute(1, 2, 0).numpy().astype(np.float32)  # outside the overlap: the photo itself (no motion)
        f_ab, f_ba = flow_fn(np.ascontiguousarray(ref_np), np.ascontiguousarray(a))
        good = ok.numpy() & _consistent(f_ab, f_ba, consistency_px * k)
        if int(good.sum()) < min_overlap:
            return None
        return smooth_flow(f_ab, good.astype(np.float32), sigma_px * k, falloff_px * k), good

    def apply(i: int, f: np.ndarray, good: np.ndarray) -> None:
        mag = np.linalg.norm(f, axis=-1, keepdims=True)
        f = f * np.minimum(1.0, clip_px * k / np.maximum(mag, 1e-12))
        room = np.maximum(_inside_matte_distance(fg[i].numpy()) - 1.5, 0.0)  # never sample beyond the matte
        mag = np.linalg.norm(f, axis=-1, keepdims=True)
        f = f * np.minimum(1.0, room[..., None] / np.maximum(mag, 1e-12))
        flows[i] = torch.from_numpy(f)
        out[i] = warp_image(imgs[i], flows[i])
        overlap[i] = torch.from_numpy(good)

    if mode == "mean":  # every view halfway towards each neighbour: the mean placement of it and the views that see its points
        from scipy.ndimage import distance_transform_edt

        for i in sel:
            num, den, seen = np.zeros((h, w, 2), np.float32), np.ones((h, w), np.float32), np.zeros((h, w), bool)
            for j in sel:
                if j == i:
                    continue
                r = pair(i, j, imgs[j])
                if r is None:
                    continue
                num += r[0]  # already faded by its weight outside the measured pixels
                d = distance_transform_edt(~r[1])
                den += np.exp(-d / (falloff_px * k)) if falloff_px > 0 else (d == 0)
                seen |= r[1]
            if seen.any():
                apply(i, num / den[..., None], seen)
        return FlowRegistration(out.to(images), flows, parent, overlap)
    root = sel[frontal_view(cams[sel], head_to_world)]
    for i, p in registration_order(cams, root, centre, sel):
        r = pair(i, p, out[p])
        if r is None:
            continue
        apply(i, *r)
        parent[i] = p
    return FlowRegistration(out.to(images), flows, parent, overlap)
