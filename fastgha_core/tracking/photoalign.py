"""Photometric registration of the photos of one person (colour-map optimisation of the head poses).

The landmark fit (``fit.py``) places the head in every photo to within a few pixels; where two
photos see the same skin those few pixels put the same eye corner at two places once the photos
are fused into one avatar. This step registers the photos to each other through their pixels, in
the manner of Zhou & Koltun's colour-map optimisation ("Color Map Optimization for 3D
Reconstruction with Consumer Depth Cameras", SIGGRAPH 2014): with the jointly fitted head surface
fixed (shared identity, each photo's own expression), each photo's pose gets a small 6-DoF
correction so that the colours the photos project onto shared surface points agree.

- **Surface points**: ``PhotoAlignConfig.points`` points sampled by area on the ICT face
  triangles of the inner face (``M_Face`` between chin and a little above the brows, not the ears,
  neck, eyeballs, mouth interior or back of the head: hair, collars and gaze differ between
  photos), at each photo's own expression, so the same point follows the face across photos.
- **Visibility** (fixed at the landmark fit's poses): a point counts in a photo when the fitted
  mesh's rasterized depth there is the point's own (within ``depth_tol_m``), its normal faces
  the camera (cosine >= ``min_cos``: no grazing flanks, where the matte's outline and the
  background take over) and, when the photo has a matte, inside it.
- **Robust to exposure and lighting**: the images are compared band-passed (difference of
  Gaussians, ``sigma`` and ``3 sigma``, per colour channel, each a normalised convolution over the
  pixels inside the fitted head's silhouette and the matte, so the background does not bleed
  into the face near its outline), and each pair of photos by the
  normalised cross-correlation of those values over the points both see: a gain, an offset and
  smooth shading differences between photos drop out.
- **Coarse to fine**: ``levels`` (the band's ``sigma`` in working pixels, where the face spans
  ``work_face_px``), L-BFGS at each level.
- **Gauge**: the most frontal photo (smallest yaw + pitch) keeps its pose; corrections are
  bounded (``max_rot_deg``, ``max_shift_mm``, ``max_depth_mm`` through a tanh) and pulled to zero
  (``prior_rot_deg``, ``prior_shift_mm``, ``prior_depth_mm``).
- **Landmarks stay fitted**: the fitted landmarks' projections are held near where the landmark
  fit put them (their mean squared displacement in units of 1 % of the face size, weight
  ``landmark_weight``; a displacement, not the residual to the detections, so the fit's own
  compromises, such as the yaw prior's, are kept), and afterwards a photo whose landmark RMS
  against the detections grew beyond ``max_rms_growth`` x its own + ``rms_slack_frac`` x its face
  size has its correction halved until it fits, or dropped.

The correction of photo ``v`` is a rotation ``exp([w_v]x)`` about the head's origin in the
camera and a shift ``d_v`` (camera axes): ``R_v <- exp([w_v]x) R_v``, ``t_v <- t_v + d_v``. With
``identity_modes > 0`` the shared identity's first modes move too (one change for all photos).

``PhotoAlignConfig.free_min_yaw_deg`` limits the corrections to the photos that the given poses
turn at least that far; the others hold their poses (and still serve as references for the
colours). Tracking uses it by default for the photos turned >= 55 degrees
(``TrackConfig.photo_align``, ``pipeline.TURNED_MIN_YAW_DEG``), where the landmark fit saturates:
on held-out synthetic photo sets with known poses it brings the +70-degree photos' rotation error
from 7.7 to 5.0 degrees on average. Registering every photo turns the less turned ones away from
the truth on synthetic renders and is an option (``TrackConfig.with_photo_align("all")``). Figures
in ``docs/tracking-log.md`` ("Registering the turned photos"); per-photo read-out:
``python -m fastgha_core.tracking.photoalign``.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from dataclasses import dataclass, field

import numpy as np
import torch

__all__ = ["PhotoAlignConfig", "PhotoAlignResult", "SurfaceSamples", "sample_face_surface", "register_photos", "axis_angle_to_matrix", "main"]

log = logging.getLogger(__name__)


@dataclass
class PhotoAlignConfig:
    """Options of :func:`register_photos` (module doc)."""

    points: int = 15000  # surface points sampled on the face triangles
    work_face_px: float = 256.0  # each photo is resampled so its face (68-landmark box diagonal) spans this
    levels: tuple[float, ...] = (6.0, 3.0, 1.5)  # band-pass sigma (working pixels), coarse to fine
    iterations: int = 15  # L-BFGS iterations per level
    min_cos: float = 0.35  # a point counts in a photo where its normal faces the camera at least this much
    depth_tol_m: float = 0.004  # visible: within this of the rasterized depth
    min_shared: int = 300  # pairs of photos sharing fewer points are not compared
    max_rot_deg: float = 15.0  # bound of each rotation component
    max_shift_mm: float = 15.0  # bound of the lateral (x, y) shift
    max_depth_mm: float = 10.0  # bound of the depth (z) shift
    prior_rot_deg: float = 8.0  # Gaussian prior's scale on the rotation
    prior_shift_mm: float = 5.0
    prior_depth_mm: float = 3.0
    prior_weight: float = 0.002  # weight of the prior against the mean (1 - NCC)
    landmark_weight: float = 0.002  # weight of the landmark term (mean squared displacement / (1 % of the face)^2)
    max_rms_growth: float = 1.5  # a photo's landmark RMS may grow to this x its own ...
    rms_slack_frac: float = 0.004  # ... + this fraction of its face size
    seed: int = 0  # surface sampling
    identity_modes: int = 0  # also move the shared head shape along its first this many ICT identity modes (0: poses only)
    prior_identity: float = 0.5  # Gaussian prior's scale on each identity mode's change (the modes are unit-variance)
    free_min_yaw_deg: float = 0.0  # only photos the given poses turn at least this much (|yaw|, degrees) get a correction; 0: all but the reference


@dataclass
class PhotoAlignResult:
    """What :func:`register_photos` found for ``V`` photos."""

    rotations: np.ndarray  # [V, 3, 3] corrected head -> camera rotations
    translations: np.ndarray  # [V, 3] corrected head origins in the cameras (metres)
    rotation_deg: np.ndarray  # [V] angle of each correction (degrees)
    shift_mm: np.ndarray  # [V, 3] each translation correction (mm, camera axes)
    rms_before: np.ndarray  # [V] landmark RMS (px) at the landmark fit's poses (nan: no landmarks given)
    rms_after: np.ndarray  # [V] landmark RMS (px) at the corrected poses
    ncc_before: float  # mean pairwise NCC of the band-passed colours at the finest level (weighted by shared points)
    ncc_after: float
    reference: int  # the photo held fixed
    shared: np.ndarray  # [V, V] points seen by both photos
    shrunk: list[int] = field(default_factory=list)  # photos whose correction the landmark guard reduced
    seconds: float = 0.0
    identity: np.ndarray | None = None  # [100] the shared identity after registration (moved with identity_modes > 0)


@dataclass
class SurfaceSamples:
    """Points on the head mesh by barycentric coordinates (the same points in every photo)."""

    tri: np.ndarray  # [N, 3] int vertex ids
    bary: np.ndarray  # [N, 3] float64 barycentric weights

    def points(self, vertices: np.ndarray) -> np.ndarray:
        """``[N, 3]`` positions on ``vertices [Nv, 3]``."""
        V = np.asarray(vertices, np.float64)
        return np.einsum("nk,nkd->nd", self.bary, V[self.tri])

    def normals(self, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """``[N, 3]`` unit normals (the mesh's area-weighted vertex normals, interpolated)."""
        from ..data.headmodel import vertex_normals

        n = vertex_normals(np.asarray(vertices, np.float64), faces)
        n = np.einsum("nk,nkd->nd", self.bary, n[self.tri])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def sample_face_surface(head, count: int, seed: int = 0, materials: tuple[str, ...] = ("M_Face",), inner: bool = True,
                        half_width_m: float = 0.065, above_brows_m: float = 0.035) -> SurfaceSamples:
    """``count`` points uniform by area (on the generic neutral head) on the triangles of ``materials``.

    With ``inner``, only the inner face: triangles above the chin (ICT landmark 8 of the neutral
    head; the neck moves apart from the head and is covered by collars), at most ``above_brows_m``
    above the brows (landmarks 17-26; above, hair) and within ``half_width_m`` of the midline (not
    the ears, often under hair). Raises ValueError for ``count < 1``."""
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    V = head.neutral.astype(np.float64)
    keep = head.material_mask(*materials)
    if inner:
        c = V[head.faces].mean(1)
        lm = V[head.landmarks68]
        keep &= (c[:, 1] > lm[8, 1]) & (c[:, 1] < lm[17:27, 1].mean() + above_brows_m) & (np.abs(c[:, 0]) < half_width_m) & (c[:, 2] > lm[0, 2] - 0.02)
    F = head.faces[keep].astype(np.int64)
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(F), size=count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    return SurfaceSamples(F[idx], bary)


def axis_angle_to_matrix(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula, differentiable (also at 0): ``w [..., 3]`` radians -> ``[..., 3, 3]``."""
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]  # [..., 1, 1]
    theta = torch.sqrt(theta2 + 1e-20)
    small = theta2 < 1e-8
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(1e-20))
    z = torch.zeros_like(w[..., 0])
    Kx = torch.stack([
        torch.stack([z, -w[..., 2], w[..., 1]], -1),
        torch.stack([w[..., 2], z, -w[..., 0]], -1),
        torch.stack([-w[..., 1], w[..., 0], z], -1),
    ], -2)  # fmt: skip
    eye = torch.eye(3, dtype=w.dtype).expand(Kx.shape)
    return eye + a * Kx + b * (Kx @ Kx)


def _gauss(img: np.ndarray, sigma: float) -> np.ndarray:
    import cv2

    return cv2.GaussianBlur(img, (0, 0), sigmaX=float(sigma), sigmaY=float(sigma), borderType=cv2.BORDER_REFLECT)


def _masked_gauss(img: np.ndarray, m: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of ``img [h, w, 3]`` over the pixels where ``m [h, w]`` is 1 (normalised convolution)."""
    num = _gauss(img * m[..., None], sigma)
    den = _gauss(m, sigma)[..., None]
    return num / np.maximum(den, 1e-3)


@dataclass
class _View:
    bands: list[torch.Tensor]  # per level [1, 3, h, w] float64
    K: torch.Tensor  # [3, 3] of the working image
    size: tuple[int, int]  # (w, h) working image
    X: torch.Tensor  # [N, 3] surface points in head axes (this photo's expression)
    visible: torch.Tensor  # [N] bool
    lm_X: torch.Tensor  # [L, 3] landmark model points (head axes)
    lm_uv0: torch.Tensor  # [L, 2] their projections at the landmark fit's pose (photo pixels)
    lm_uv: torch.Tensor | None  # [L, 2] detected landmarks (photo pixels) or None
    K_photo: torch.Tensor  # [3, 3] of the photo
    face_px: float  # face size in the photo
    X_basis: torch.Tensor | None = None  # [k, N, 3] the surface points' identity modes (identity_modes > 0)
    lm_basis: torch.Tensor | None = None  # [k, L, 3] the landmark points' identity modes


def _working_view(img, R, t, K, X, normals, mesh_v, mesh_f, lm68_X, cfg, mask=None):
    """Crop + resample one photo around the head; visibility of the surface points; band-passed images."""
    import cv2

    from ..data.meshraster import render_mesh

    H, W = img.shape[:2]
    P = X @ R.T + t
    uv = (P @ K.T)[:, :2] / (P @ K.T)[:, 2:]
    lm = lm68_X @ R.T + t
    lm = (lm @ K.T)[:, :2] / (lm @ K.T)[:, 2:]
    face_px = float(np.linalg.norm(lm.max(0) - lm.min(0)))
    s = min(1.0, cfg.work_face_px / max(face_px, 1.0))
    lo, hi = uv.min(0), uv.max(0)
    m = 0.15 * (hi - lo).max()
    x0, y0 = int(max(0, math.floor(lo[0] - m))), int(max(0, math.floor(lo[1] - m)))
    x1, y1 = int(min(W, math.ceil(hi[0] + m))), int(min(H, math.ceil(hi[1] + m)))
    if x1 - x0 < 8 or y1 - y0 < 8:
        raise ValueError(f"the head projects outside the photo (box {x0},{y0} - {x1},{y1} in {W}x{H})")
    w, h = max(8, int(round((x1 - x0) * s))), max(8, int(round((y1 - y0) * s)))
    sx, sy = w / (x1 - x0), h / (y1 - y0)
    crop = img[y0:y1, x0:x1].astype(np.float32) / 255.0
    work = cv2.resize(crop, (w, h), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    Kw = np.array([[K[0, 0] * sx, K[0, 1] * sx, (K[0, 2] - x0) * sx], [0.0, K[1, 1] * sy, (K[1, 2] - y0) * sy], [0.0, 0.0, 1.0]])
    # visibility at the landmark fit's pose
    pc = mesh_v @ R.T + t
    r = render_mesh(pc.astype(np.float32), mesh_f, np.ones((len(pc), 1), np.float32), Kw, w, h, supersample=1)
    uvw = (P @ Kw.T)[:, :2] / (P @ Kw.T)[:, 2:]
    ix, iy = np.floor(uvw[:, 0]).astype(int), np.floor(uvw[:, 1]).astype(int)
    inside = (ix >= 1) & (iy >= 1) & (ix < w - 1) & (iy < h - 1)
    ixc, iyc = np.clip(ix, 0, w - 1), np.clip(iy, 0, h - 1)
    depth = r.depth[iyc, ixc].astype(np.float64)
    alpha = r.alpha[iyc, ixc]
    vis = inside & (alpha > 0.5) & (P[:, 2] <= depth + cfg.depth_tol_m)
    view_dir = -P / np.linalg.norm(P, axis=1, keepdims=True)
    vis &= ((normals @ R.T) * view_dir).sum(1) >= cfg.min_cos
    if mask is not None:
        mw = cv2.resize(np.asarray(mask, np.float32)[y0:y1, x0:x1], (w, h), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
        vis &= mw[iyc, ixc] > 0.5
    # band-pass by normalised convolution inside the head (the rasterized mesh, and the matte when
    # given): the background must not bleed into the face's bands near its outline
    inside_head = (r.alpha > 0.5).astype(np.float32)
    if mask is not None:
        inside_head *= (mw > 0.5).astype(np.float32)
    bands = []
    for sig in cfg.levels:
        b = _masked_gauss(work, inside_head, sig) - _masked_gauss(work, inside_head, 3.0 * sig)
        bands.append(torch.from_numpy(np.ascontiguousarray(b.transpose(2, 0, 1)))[None].double())
    return bands, torch.from_numpy(Kw), (w, h), torch.from_numpy(vis), face_px


def _project(X: torch.Tensor, R: torch.Tensor, t: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    P = X @ R.T + t
    q = P @ K.T
    return q[:, :2] / q[:, 2:].clamp_min(1e-6)


def _sample(band: torch.Tensor, uv: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Bilinear values ``[N, 3]`` of ``band [1, 3, h, w]`` at pixel positions ``uv [N, 2]`` (corner convention)."""
    w, h = size
    g = torch.stack([2 * uv[:, 0] / w - 1, 2 * uv[:, 1] / h - 1], -1)[None, None]  # [1, 1, N, 2]
    return torch.nn.functional.grid_sample(band, g, mode="bilinear", padding_mode="border", align_corners=False)[0, :, 0].T


def _pair_ncc(fa: torch.Tensor, fb: torch.Tensor, sel: torch.Tensor) -> torch.Tensor:
    a, b = fa[sel], fb[sel]
    a = a - a.mean(0, keepdim=True)
    b = b - b.mean(0, keepdim=True)
    return (a * b).sum() / torch.sqrt((a * a).sum() * (b * b).sum() + 1e-20)


class _Objective:
    """Photometric + landmark + prior objective over the free photos' 6 parameters (degrees, mm)."""

    def __init__(self, views: list[_View], R0: torch.Tensor, t0: torch.Tensor, ref: int, cfg: PhotoAlignConfig, free: list[bool] | None = None):
        self.views, self.R0, self.t0, self.ref, self.cfg = views, R0, t0, ref, cfg
        V = len(views)
        self.keep = torch.tensor([[float(free is None or free[v])] for v in range(V)], dtype=torch.float64)  # [V, 1] 1 = corrected
        self.keep[ref] = 0.0
        vis = torch.stack([v.visible for v in views])  # [V, N]
        self.pairs = []
        shared = torch.zeros(V, V, dtype=torch.long)
        for a in range(V):
            for b in range(a + 1, V):
                sel = vis[a] & vis[b]
                shared[a, b] = shared[b, a] = int(sel.sum())
                if int(sel.sum()) >= cfg.min_shared:
                    self.pairs.append((a, b, sel))
        self.shared = shared
        self.total = float(sum(int(s.sum()) for _, _, s in self.pairs)) or 1.0

    def pose(self, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``p [V, 6]`` (rotation in degrees, shift in mm; unbounded) -> corrected ``R [V, 3, 3]``, ``t [V, 3]``."""
        c = self.cfg
        rot = c.max_rot_deg * torch.tanh(p[:, :3] / c.max_rot_deg)
        lat = c.max_shift_mm * torch.tanh(p[:, 3:5] / c.max_shift_mm)
        dep = c.max_depth_mm * torch.tanh(p[:, 5:6] / c.max_depth_mm)
        keep = self.keep.to(p.dtype)
        rot, shift = rot * keep, torch.cat([lat, dep], 1) * keep
        R = axis_angle_to_matrix(torch.deg2rad(rot)) @ self.R0
        return R, self.t0 + shift / 1000.0

    def corrections(self, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(rotation vector in degrees [V, 3], shift in mm [V, 3])`` of ``p`` after the bounds and the gauge."""
        c = self.cfg
        keep = self.keep.to(p.dtype)
        rot = c.max_rot_deg * torch.tanh(p[:, :3] / c.max_rot_deg) * keep
        shift = torch.cat([c.max_shift_mm * torch.tanh(p[:, 3:5] / c.max_shift_mm), c.max_depth_mm * torch.tanh(p[:, 5:6] / c.max_depth_mm)], 1) * keep
        return rot, shift

    @staticmethod
    def _shape(X: torch.Tensor, basis: torch.Tensor | None, q: torch.Tensor | None) -> torch.Tensor:
        return X if q is None or basis is None else X + torch.einsum("k,knd->nd", q, basis)

    def photometric(self, R, t, level: int, q: torch.Tensor | None = None) -> torch.Tensor:
        """Mean over pairs (weighted by shared points) of 1 - NCC; ``q [k]``: the identity's change."""
        feats = [_sample(v.bands[level], _project(self._shape(v.X, v.X_basis, q), R[i], t[i], v.K), v.size) for i, v in enumerate(self.views)]
        if not self.pairs:
            return torch.zeros((), dtype=torch.float64)
        return sum(float(s.sum()) * (1 - _pair_ncc(feats[a], feats[b], s)) for a, b, s in self.pairs) / self.total

    def landmarks(self, R, t, q: torch.Tensor | None = None) -> torch.Tensor:
        """Mean over photos of the landmarks' mean squared displacement from the landmark fit, in (1 % of the face)^2."""
        terms = []
        for i, v in enumerate(self.views):
            r = (_project(self._shape(v.lm_X, v.lm_basis, q), R[i], t[i], v.K_photo) - v.lm_uv0) / (0.01 * v.face_px)
            terms.append((r * r).sum(1).mean())
        return torch.stack(terms).mean()

    def prior(self, p) -> torch.Tensor:
        c = self.cfg
        rot, shift = self.corrections(p)
        return ((rot / c.prior_rot_deg) ** 2).sum() + ((shift[:, :2] / c.prior_shift_mm) ** 2).sum() + ((shift[:, 2] / c.prior_depth_mm) ** 2).sum()

    def __call__(self, p: torch.Tensor, level: int, q: torch.Tensor | None = None) -> torch.Tensor:
        R, t = self.pose(p)
        c = self.cfg
        out = self.photometric(R, t, level, q) + c.landmark_weight * self.landmarks(R, t, q) + c.prior_weight * self.prior(p)
        if q is not None:
            out = out + c.prior_weight * ((q / c.prior_identity) ** 2).sum()
        return out


def _rms(view: _View, R: torch.Tensor, t: torch.Tensor, q: torch.Tensor | None = None) -> float:
    if view.lm_uv is None:
        return float("nan")
    r = _project(_Objective._shape(view.lm_X, view.lm_basis, q), R, t, view.K_photo) - view.lm_uv
    return float(torch.sqrt((r * r).sum(1).mean()))


def _reference(rotations: np.ndarray) -> int:
    from .realsets import head_angles_deg

    return int(np.argmin([abs(head_angles_deg(R)[0]) + abs(head_angles_deg(R)[1]) for R in rotations]))


def register_photos(
    images: list[np.ndarray],  # V x [H_i, W_i, 3] uint8 RGB photos
    identity: np.ndarray,  # [100] or [Ki] fitted identity (zeros beyond)
    expressions: np.ndarray,  # [V, 53] fitted ict53 codes
    rotations: np.ndarray,  # [V, 3, 3] fitted head -> camera rotations
    translations: np.ndarray,  # [V, 3] fitted head origins (metres, camera axes)
    K: np.ndarray,  # [V, 3, 3] the photos' intrinsics (pixels, corner convention)
    config: PhotoAlignConfig | None = None,
    landmarks: list[np.ndarray | None] | None = None,  # V x [L, 2] detected landmarks (photo pixels) or None
    landmark_model=None,  # fit.LandmarkModel of those landmarks, or V of them (one per photo; needed with landmarks)
    masks: list[np.ndarray | None] | None = None,  # V x [H_i, W_i] alpha in [0, 1] or None
    reference: int | None = None,  # the photo held fixed (default: the most frontal)
) -> PhotoAlignResult:
    """Register the photos' head poses to each other photometrically (module doc).

    Returns a :class:`PhotoAlignResult` whose ``rotations`` / ``translations`` replace the inputs;
    with one photo, or photos that share too few visible points, the poses come back unchanged.
    Raises ValueError on mismatched shapes or a head that projects outside its photo.
    """
    from ..data.headmodel import HeadModel

    cfg = config or PhotoAlignConfig()
    t_start = time.perf_counter()
    V = len(images)
    rotations = np.asarray(rotations, np.float64)
    translations = np.asarray(translations, np.float64)
    K = np.asarray(K, np.float64)
    expressions = np.asarray(expressions, np.float64)
    if rotations.shape != (V, 3, 3) or translations.shape != (V, 3) or K.shape != (V, 3, 3) or expressions.shape != (V, 53):
        raise ValueError(
            f"register_photos: expected {V} photos' rotations [V, 3, 3], translations [V, 3], K [V, 3, 3] and expressions [V, 53], "
            f"got {list(rotations.shape)}, {list(translations.shape)}, {list(K.shape)}, {list(expressions.shape)}"
        )
    landmarks = list(landmarks) if landmarks is not None else [None] * V
    masks = list(masks) if masks is not None else [None] * V
    if len(landmarks) != V or len(masks) != V:
        raise ValueError(f"register_photos: got {V} photos, {len(landmarks)} landmark sets and {len(masks)} masks")
    if any(lm is not None for lm in landmarks) and landmark_model is None:
        raise ValueError("register_photos: landmarks need their landmark_model (fit.LandmarkModel)")
    head = HeadModel.load()
    beta = np.zeros(head.num_identity)
    ident = np.asarray(identity, np.float64).reshape(-1)
    beta[: len(ident)] = ident
    ref = _reference(rotations) if reference is None else int(reference)
    if not 0 <= ref < max(V, 1):
        raise ValueError(f"register_photos: reference must index one of the {V} photos, got {reference}")

    def unchanged(shared=None) -> PhotoAlignResult:
        return PhotoAlignResult(rotations.copy(), translations.copy(), np.zeros(V), np.zeros((V, 3)), np.full(V, np.nan), np.full(V, np.nan),
                                float("nan"), float("nan"), ref, np.zeros((V, V), np.int64) if shared is None else shared,
                                seconds=time.perf_counter() - t_start, identity=beta.copy())  # fmt: skip

    if V < 2:
        return unchanged()
    free = None
    if cfg.free_min_yaw_deg > 0:
        from .fit import head_angles_deg

        free = [abs(head_angles_deg(r)[0]) >= cfg.free_min_yaw_deg and v != ref for v, r in enumerate(rotations)]
        if not any(free):
            log.info("photo registration: no photo turned >= %.0f degrees; poses unchanged", cfg.free_min_yaw_deg)
            return unchanged()
    samples = sample_face_surface(head, cfg.points, cfg.seed)
    mesh_f = head.visible_faces(eyelashes=False)
    views = []
    for v in range(V):
        mv = head.vertices(beta.astype(np.float32), expressions[v].astype(np.float32)).astype(np.float64)
        X = samples.points(mv)
        nrm = samples.normals(mv, mesh_f)
        bands, Kw, size, vis, face_px = _working_view(images[v], rotations[v], translations[v], K[v], X, nrm, mv, mesh_f,
                                                      mv[head.landmarks68], cfg, masks[v])  # fmt: skip
        lm_uv = None
        nk = max(0, int(cfg.identity_modes))
        Xb = lmb = None
        if nk:
            Xb = torch.from_numpy(np.einsum("nj,knjd->knd", samples.bary, head.identity_basis[:nk][:, samples.tri].astype(np.float64)))
        if landmarks[v] is not None:
            lmod = landmark_model[v] if isinstance(landmark_model, (list, tuple)) else landmark_model
            lm_X = torch.from_numpy(lmod.points(beta[: lmod.num_identity], expressions[v]))
            lm_uv = torch.from_numpy(np.asarray(landmarks[v], np.float64))
            if lm_X.shape[0] != lm_uv.shape[0] or lm_uv.shape[-1] != 2:
                raise ValueError(f"register_photos: photo {v} has {list(lm_uv.shape)} landmarks, its model {lm_X.shape[0]} points")
            if nk:
                lmb = torch.from_numpy(np.asarray(lmod.identity[:nk], np.float64))
                if lmb.shape[0] < nk:
                    raise ValueError(f"register_photos: identity_modes {nk} > the landmark model's {lmb.shape[0]} modes")
        else:
            lm_X = torch.from_numpy(mv[head.landmarks68])
            lmb = torch.from_numpy(head.identity_basis[:nk, head.landmarks68].astype(np.float64)) if nk else None
        lm_uv0 = _project(lm_X, torch.from_numpy(rotations[v]), torch.from_numpy(translations[v]), torch.from_numpy(K[v]))
        views.append(_View(bands, Kw, size, torch.from_numpy(X), vis, lm_X, lm_uv0, lm_uv, torch.from_numpy(K[v]), face_px, Xb, lmb))
    R0, t0 = torch.from_numpy(rotations), torch.from_numpy(translations)
    obj = _Objective(views, R0, t0, ref, cfg, free)
    shared = obj.shared.numpy()
    linked, grown = {ref}, True
    while grown:  # photos connected to the reference through pairs that share enough points
        grown = False
        for a, b, _ in obj.pairs:
            if (a in linked) != (b in linked):
                linked |= {a, b}
                grown = True
    if not obj.pairs:
        log.info("photo registration: no two photos share %d visible points; poses unchanged", cfg.min_shared)
        return unchanged(shared)
    last = len(cfg.levels) - 1
    with torch.no_grad():
        ncc0 = 1.0 - float(obj.photometric(R0, t0, last))
        rms0 = np.array([_rms(v, R0[i], t0[i]) for i, v in enumerate(views)])
    p = torch.zeros(V, 6, dtype=torch.float64, requires_grad=True)
    q = torch.zeros(max(0, int(cfg.identity_modes)), dtype=torch.float64, requires_grad=True) if cfg.identity_modes > 0 else None
    for level in range(len(cfg.levels)):
        opt = torch.optim.LBFGS([p] + ([q] if q is not None else []), lr=1.0, max_iter=cfg.iterations, line_search_fn="strong_wolfe",
                                tolerance_grad=1e-9, tolerance_change=1e-12)  # fmt: skip

        def closure():
            opt.zero_grad()
            loss = obj(p, level, q)
            loss.backward()
            return loss

        opt.step(closure)
    p = p.detach()
    q = None if q is None else q.detach()
    unlinked = [v for v in range(V) if v not in linked]
    p[unlinked] = 0.0  # photos without a chain of shared points to the reference: nothing registers them
    # the landmark guard: halve a photo's correction until its landmark RMS is acceptable
    shrunk = []
    for v, view in enumerate(views):
        if view.lm_uv is None or v == ref:
            continue
        for k in range(6):
            R, t = obj.pose(p)
            if _rms(view, R[v], t[v], q) <= cfg.max_rms_growth * rms0[v] + cfg.rms_slack_frac * view.face_px:
                break
            p[v] *= 0.5 if k < 5 else 0.0
            if v not in shrunk:
                shrunk.append(v)
    with torch.no_grad():
        R, t = obj.pose(p)
        ncc1 = 1.0 - float(obj.photometric(R, t, last, q))
        rms1 = np.array([_rms(v, R[i], t[i], q) for i, v in enumerate(views)])
        rot, shift = obj.corrections(p)
    ang = np.degrees(np.linalg.norm(np.radians(rot.numpy()), axis=1))
    res = PhotoAlignResult(R.numpy().copy(), t.numpy().copy(), ang, shift.numpy().copy(), rms0, rms1, ncc0, ncc1, ref, shared, shrunk,
                           time.perf_counter() - t_start)  # fmt: skip
    res.identity = beta.copy()
    if q is not None:
        res.identity[: len(q)] += q.numpy()
    log.info("photo registration: NCC %.3f -> %.3f, corrections %s deg, %.1f s", ncc0, ncc1, np.round(ang, 2), res.seconds)
    return res


def main(argv: list[str] | None = None) -> int:  # pragma: no cover - evaluation on the real sets (not shipped)
    """Per photo of every real set: the correction, landmark RMS and yaw before/after, the pairwise NCC."""
    from pathlib import Path

    from .pipeline import TrackConfig, track_photos
    from .realsets import _read, annotated_yaw, head_angles_deg, realsets_root

    ap = argparse.ArgumentParser(prog="python -m fastgha_core.tracking.photoalign", description=__doc__.split("\n")[0])
    ap.add_argument("--root", default=None, help="folder of photo sets (default: ../shared/realsets or $FASTGHA_REALSETS)")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    root = Path(a.root) if a.root else realsets_root()
    if not root.is_dir():
        print(f"no real photo sets under {root}: nothing to measure")
        return 0
    print("| set | photo | yaw annotated | yaw before | yaw after | correction (deg) | shift (mm) | landmark RMS px before -> after | face px |")
    print("|---|---|---|---|---|---|---|---|---|")
    for d in sorted(q for q in root.iterdir() if q.is_dir()):
        paths = sorted(q for q in d.iterdir() if q.suffix.lower() in (".jpg", ".jpeg", ".png"))
        imgs = [_read(q) for q in paths]
        res = track_photos(imgs, TrackConfig(photo_align=False), names=[q.name for q in paths])
        fit = res.fit
        from .fit import LandmarkModel, landmark_models

        cfg = TrackConfig()
        model = LandmarkModel.from_head_model(num_identity=cfg.fit.num_identity, layout=res.layout)
        al = register_photos(imgs, fit.identity, fit.expressions, fit.rotations, fit.translations, fit.K, cfg.align, landmarks=res.landmarks,
                             landmark_model=landmark_models(model, fit.rotations, cfg.fit))  # fmt: skip
        log.info("%s: the fit's own RMS %s", d.name, np.round(fit.rms_px, 2))
        for v, q in enumerate(paths):
            face = float(np.linalg.norm(res.landmarks[v].max(0) - res.landmarks[v].min(0)))
            print(f"| {d.name} | {q.name[:2]}{' (fixed)' if v == al.reference else ''} | {annotated_yaw(q.name)} | "
                  f"{head_angles_deg(fit.rotations[v])[0]:.1f} | {head_angles_deg(al.rotations[v])[0]:.1f} | {al.rotation_deg[v]:.2f} | "
                  f"{', '.join(f'{x:+.1f}' for x in al.shift_mm[v])} | {al.rms_before[v]:.2f} -> {al.rms_after[v]:.2f} | {face:.0f} |")  # fmt: skip
        print(f"| {d.name} | NCC {al.ncc_before:.3f} -> {al.ncc_after:.3f}, {al.seconds:.1f} s, guard shrank {al.shrunk or 'none'} | | | | | | | |")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
