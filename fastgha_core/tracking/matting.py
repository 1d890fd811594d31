"""Foreground masks for tracked photos when the user gives none.

The mask is built from the fitted head model (a trimap whose only sure foreground is the face)
and one of three classifiers for the rest (``MattingConfig.method``):

- ``"segmentation"`` (default when MediaPipe is installed): MediaPipe's selfie segmentation
  (``silhouette.person_mask``, the general model shipped in the wheel) > 0.5, plus long hair
  below the hair zone when its colour is the hair's and not the clothes' (``_long_hair``); when
  it covers less than ``min_person_share`` (half) of the likely head, the mixture decides instead;
- ``"mixture"``: Gaussian mixtures (numpy EM) of colour features that a shadow or a shading ramp
  hardly changes (``shading_features``), background = everything outside the zone;
- ``"grabcut"``: OpenCV's GrabCut on the same features, initialised with the trimap and the
  mixtures' verdict; what the mixtures call wall stays wall.

Why the face only: on real photos the fitted ICT head's back of the skull and neck often lie over
the wall (side views; a skull longer than the person's; a few degrees of yaw error: about 5 cm on a
phone profile). When the whole eroded silhouette was sure foreground, that wall and the person's
shadow on it were kept (pale blobs behind the head and beside the neck; docs/tracking-log.md, "Why the face only").

Steps:

1. **Silhouette**: the fitted ICT head (identity + expression + pose, all visible surfaces) is
   rendered into the crop with the CPU mesh rasterizer (``data/meshraster.py``).
2. **Trimap**: sure foreground (``core``) = the convex hull of the 68 fitted landmarks (brows to
   chin, ``face_region``) eroded by ``core_erode_m`` (1 cm), inside the silhouette eroded by
   ``erode_m`` (1 cm); without landmarks, the silhouette eroded by both. The zone where the head may
   be: hair up to ``hair_m`` (5 cm) outside the silhouette and above the mouth row +
   ``hair_below_m`` (2 cm; landmark 57), elsewhere a band of ``edge_m`` (0.8 cm) (ears, cheeks,
   neck edge), and the silhouette itself. The rest of the photo is sure background; pixels outside
   the photo (crop padding) are background.
3. **Classifier** for the zone minus the core (above).
4. **Clean-up**: opening (1.5 px), keep only regions connected to the face, fill holes, and
   soften the edge with a Gaussian blur of ``feather_px`` pixels.

Limits: the neck and clothes below the fitted mesh are background by design (the synthetic
training heads end at the top of the chest), so shoulders are cut along the fitted silhouette;
hair longer than ``long_hair_m`` (15 cm) below the mouth, or farther than ``hair_m`` from the head,
is cut; hats, hands and glasses frames are treated like hair; without MediaPipe, a shirt of the
wall's colour (grey on grey) is cut and hair tips against a white wall may be lost. A user mask
(``<name>_mask.png``) always wins. ``matting_eval.py`` measures the masks against known alpha.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

__all__ = ["MattingConfig", "head_silhouette", "face_region", "matte_from_head", "GaussianMixture"]

logger = logging.getLogger(__name__)


@dataclass
class MattingConfig:
    erode_m: float = 0.01  # likely head = silhouette eroded by this much
    core_erode_m: float = 0.01  # sure foreground = the fitted face region (brows to chin) eroded by this much
    hair_m: float = 0.05  # hair may extend this far beyond the skull
    hair_below_m: float = 0.02  # ... down to this far below the mouth centre (landmark 57)
    min_person_share: float = 0.5  # segmentation covering less of the likely head than this: fall back to "mixture"
    long_hair_m: float = 0.15  # segmentation: hair-coloured person pixels near the head down to this far below the mouth (_long_hair)
    edge_m: float = 0.008  # width of the uncertain band elsewhere
    # how uncertain pixels are decided: "segmentation" | "mixture" | "grabcut" (module doc); "auto" =
    # segmentation when MediaPipe is installed, else mixture
    method: str = "auto"
    components: int = 4  # Gaussians per colour model
    samples: int = 4000  # pixels per colour model fit
    feather_px: float = 1.0  # edge softening (Gaussian sigma, output pixels)
    grabcut_iterations: int = 5
    wall_quantile: float = 0.1  # mixture / GrabCut: a pixel the background model scores above this quantile of its own pixels is wall-like
    seed: int = 0


class GaussianMixture:
    """Full-covariance Gaussian mixture fitted by EM (numpy)."""

    def __init__(self, k: int, iterations: int = 20, seed: int = 0):
        self.k, self.iterations, self.seed = k, iterations, seed

    def fit(self, x: np.ndarray) -> "GaussianMixture":  # x [N, D]
        x = np.asarray(x, dtype=np.float64)
        n, d = x.shape
        if n < self.k:
            raise ValueError(f"need at least {self.k} samples to fit {self.k} Gaussians, got {n}")
        rng = np.random.default_rng(self.seed)
        self.means = x[rng.choice(n, self.k, replace=False)].copy()  # [k, D]
        self.covs = np.repeat((np.cov(x.T) + 1e-4 * np.eye(d))[None], self.k, axis=0)
        self.weights = np.full(self.k, 1.0 / self.k)
        for _ in range(self.iterations):
            logp = self._component_logp(x)  # [N, k]
            m = logp.max(1, keepdims=True)
            r = np.exp(logp - m)
            r /= r.sum(1, keepdims=True)
            nk = r.sum(0) + 1e-9
            self.weights = nk / n
            self.means = (r.T @ x) / nk[:, None]
            for j in range(self.k):
                dx = x - self.means[j]
                self.covs[j] = (r[:, j, None] * dx).T @ dx / nk[j] + 1e-4 * np.eye(d)
        return self

    def _component_logp(self, x: np.ndarray) -> np.ndarray:
        out = np.empty((x.shape[0], self.k))
        for j in range(self.k):
            L = np.linalg.cholesky(self.covs[j])
            z = np.linalg.solve(L, (x - self.means[j]).T)  # [D, N]
            out[:, j] = np.log(self.weights[j] + 1e-12) - np.log(np.diag(L)).sum() - 0.5 * (z * z).sum(0) - 0.5 * x.shape[1] * np.log(2 * np.pi)
        return out

    def score(self, x: np.ndarray) -> np.ndarray:
        """Log-likelihood ``[N]`` of samples ``[N, D]``."""
        logp = self._component_logp(np.asarray(x, dtype=np.float64))
        m = logp.max(1)
        return m + np.log(np.exp(logp - m[:, None]).sum(1))


def head_silhouette(vertices: np.ndarray, faces: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray, size: int) -> np.ndarray:
    """Coverage ``[size, size]`` float32 in [0, 1] of the head mesh ``vertices [Nv, 3]`` (head space)
    seen by the camera ``(R, t, K)``."""
    from ..data.meshraster import render_mesh

    pts = np.asarray(vertices, dtype=np.float64) @ np.asarray(R).T + np.asarray(t)
    ones = np.ones((pts.shape[0], 1), dtype=np.float32)
    return render_mesh(pts.astype(np.float32), faces, ones, np.asarray(K), size, size, supersample=1).alpha


def _disk(r: float) -> np.ndarray:
    r = max(int(round(r)), 1)
    y, x = np.mgrid[-r : r + 1, -r : r + 1]
    return x * x + y * y <= r * r


def face_region(points: np.ndarray, size: int) -> np.ndarray:
    """``[size, size]`` bool: pixels whose centres lie in the convex hull of ``points [N, 2]``
    (crop pixels, corner convention: the top-left pixel's centre is (0.5, 0.5)). Raises
    ValueError for fewer than 3 points; collinear points give an empty region."""
    from scipy.spatial import ConvexHull, QhullError

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if pts.shape[0] < 3:
        raise ValueError(f"need at least 3 face points for a face region, got {pts.shape[0]}")
    try:
        eq = ConvexHull(pts).equations  # [M, 3]: a x + b y + c <= 0 inside
    except QhullError:  # all points on a line: no area
        return np.zeros((size, size), dtype=bool)
    c = np.arange(size) + 0.5
    inside = np.ones((size, size), dtype=bool)
    for a, b, off in eq:
        inside &= (a * c[None, :] + b * c[:, None] + off) <= 1e-9
    return inside


def shading_features(rgb: np.ndarray) -> np.ndarray:
    """Colour features ``[N, 3]`` of ``rgb [N, 3]`` uint8 for the colour models: chromaticity
    ``(r, g) / (r + g + b + 0.05)`` (a shadow or a shading ramp on a wall scales r, g, b together and
    leaves it nearly unchanged; the 0.05 offset in [0, 3] units keeps near-black hair apart from
    grey) and ``0.03 x`` the mean brightness."""
    x = np.asarray(rgb, dtype=np.float64) / 255.0
    tot = x.sum(1, keepdims=True)
    return np.concatenate([x[:, :2] / (tot + 0.05), 0.03 * tot / 3.0], axis=1)


def _erode(mask: np.ndarray, r: float) -> np.ndarray:
    """Erosion by a disk of radius ``r`` px (outside the array counts as background)."""
    pad = np.pad(mask, 1, constant_values=False)
    return (ndimage.distance_transform_edt(pad) > max(r, 1.0))[1:-1, 1:-1]


def _dilate(mask: np.ndarray, r: float) -> np.ndarray:
    """Dilation by a disk of radius ``r`` px."""
    if not mask.any():
        return mask.copy()
    return ndimage.distance_transform_edt(~mask) <= max(r, 1.0)


def _long_hair(fg, person, sil, hair_zone, zone, face, face_points, pix, px_per_m, mouth_row, cfg) -> np.ndarray:
    """Hair hanging below the hair zone (beside the neck, on the shoulders): person pixels within
    ``hair_m`` of the silhouette, down to ``long_hair_m`` below the mouth, whose colour the hair
    model (person pixels of the hair zone above the brows, off the face) explains better than the
    clothes model (person pixels below the mouth farther than ``hair_m`` from the head), and that
    touch the mask. ``[S, S]`` bool (empty when either model has too few pixels)."""
    s = fg.shape[0]
    rows = np.arange(s)[:, None]
    brow_row = float(np.min(face_points[:, 1]))
    near = _dilate(sil, cfg.hair_m * px_per_m)
    below = (rows > mouth_row + cfg.hair_below_m * px_per_m) & (rows <= mouth_row + cfg.long_hair_m * px_per_m)
    cand = person & near & below & ~zone
    hair = fg & hair_zone & (rows < brow_row) & ~face & ~sil
    clothes = person & ~near & (rows > mouth_row + cfg.hair_below_m * px_per_m)
    k = cfg.components
    if not cand.any() or hair.sum() < 20 * k or clothes.sum() < 20 * k:
        return np.zeros_like(fg)
    rng = np.random.default_rng(cfg.seed)

    def sample(mask):
        idx = np.flatnonzero(mask.reshape(-1))
        return pix[rng.choice(idx, min(cfg.samples, idx.size), replace=False)]

    gh = GaussianMixture(k, seed=cfg.seed).fit(sample(hair))
    gc = GaussianMixture(k, seed=cfg.seed).fit(sample(clothes))
    idx = np.flatnonzero(cand.reshape(-1))
    keep = np.zeros(s * s, dtype=bool)
    keep[idx] = gh.score(pix[idx]) > gc.score(pix[idx])
    keep = ndimage.binary_opening(keep.reshape(s, s), _disk(1.5))
    lab, n = ndimage.label(keep | fg)
    ids = np.unique(lab[fg])
    return keep & np.isin(lab, ids[ids > 0])


def matte_from_head(
    img: np.ndarray,  # [S, S, 3] uint8 crop
    silhouette: np.ndarray,  # [S, S] coverage of the fitted head
    px_per_m: float,  # crop pixels per metre at the head's depth (f / t_z)
    mouth_row: float,  # row (pixels) of landmark 57 in the crop
    valid: np.ndarray | None = None,  # [S, S] bool: pixels inside the photo (not padding)
    config: MattingConfig | None = None,
    face_points: np.ndarray | None = None,  # [N, 2] fitted face landmarks in crop pixels (brows to chin)
) -> np.ndarray:
    """Foreground alpha ``[S, S]`` float32 in [0, 1] (module doc).

    Raises ValueError when the silhouette is empty or ``config.method`` is unknown.
    """
    cfg = config or MattingConfig()
    s = img.shape[0]
    valid = np.ones((s, s), dtype=bool) if valid is None else valid.astype(bool)
    sil = silhouette > 0.5
    if not sil.any():
        raise ValueError("the fitted head is not visible in the crop; cannot build a mask")
    method = cfg.method
    if method not in ("auto", "mixture", "grabcut", "segmentation"):
        raise ValueError(f"matting method must be 'auto', 'mixture', 'grabcut' or 'segmentation', got {method!r}")
    if method == "auto":
        try:
            import mediapipe  # noqa: F401

            method = "segmentation"
        except ImportError:
            method = "mixture"
    sil_in = _erode(sil, cfg.erode_m * px_per_m) & valid  # likely head; not sure (module doc)
    if sil_in.sum() < 50:
        sil_in = sil & valid
    # sure foreground: the face between brows and chin, eroded (the fitted silhouette's back of the head
    # and neck can lie over the wall when the skull, the hair or the yaw is off)
    if face_points is not None:
        core = _erode(face_region(face_points, s), cfg.core_erode_m * px_per_m) & sil_in
    else:
        core = _erode(sil, (cfg.core_erode_m + cfg.erode_m) * px_per_m) & valid
    if core.sum() < 20:
        core = sil_in
    rows = np.arange(s)[:, None]
    hair_zone = _dilate(sil, cfg.hair_m * px_per_m) & (rows <= mouth_row + cfg.hair_below_m * px_per_m)
    edge_zone = _dilate(sil, cfg.edge_m * px_per_m)
    zone = (hair_zone | edge_zone | sil) & valid  # where the head may be
    maybe = zone & ~core
    sure_bg = valid & ~zone
    fg = core.copy()
    pix = shading_features(img.reshape(-1, 3))
    rng = np.random.default_rng(cfg.seed)
    def sample(mask):
        idx = np.flatnonzero(mask.reshape(-1))
        return pix[rng.choice(idx, min(cfg.samples, idx.size), replace=False)]

    colour_ok = sure_bg.sum() >= 10 * cfg.components and sil_in.sum() >= 10 * cfg.components
    person = None
    if method == "segmentation":
        from .silhouette import person_mask

        person = (person_mask(img) > 0.5) & valid
        if (person & sil_in).sum() < cfg.min_person_share * sil_in.sum():
            # the segmentation missed the person (a drawing, a render, extreme light): colour models instead
            logger.info("matting: the segmentation covers %.0f%% of the fitted head; using the colour mixture",
                        100.0 * (person & sil_in).sum() / max(sil_in.sum(), 1))
            method, person = "mixture", None
    if person is not None:
        fg |= maybe & person
        if cfg.long_hair_m > cfg.hair_below_m and face_points is not None:
            fg |= _long_hair(fg, person, sil, hair_zone, zone, face_region(face_points, s), face_points, pix, px_per_m, mouth_row, cfg)
    elif maybe.any() and colour_ok:
        # background colour model: everything outside the zone (the crop's wall, floor, studio grey);
        # a likely-head pixel it explains as well as its typical pixels is wall, not head
        gb = GaussianMixture(cfg.components, seed=cfg.seed).fit(sample(sure_bg))
        thr = np.quantile(gb.score(sample(sure_bg)), cfg.wall_quantile)
        lb = gb.score(pix).reshape(s, s)
        wall_like = lb >= thr
        head_like = core | (sil_in & ~wall_like)
        if head_like.sum() < 10 * cfg.components:
            head_like = sil_in
        gf = GaussianMixture(cfg.components, seed=cfg.seed).fit(sample(head_like))
        lf = gf.score(pix).reshape(s, s)
        if method == "grabcut":
            import cv2  # opencv-contrib-python-headless (faces extra)

            gc = np.full((s, s), cv2.GC_BGD, np.uint8)
            wall = lb > lf  # the colour models say wall
            gc[maybe] = np.where(wall[maybe], cv2.GC_PR_BGD, cv2.GC_PR_FGD)
            gc[core] = cv2.GC_FGD
            bgm, fgm = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
            cv2.setRNGSeed(cfg.seed)
            feat = np.clip(pix.reshape(s, s, 3) * 400.0, 0, 255).astype(np.uint8)  # GrabCut's colour models on the shading features too
            cv2.grabCut(feat, gc, None, bgm, fgm, cfg.grabcut_iterations, cv2.GC_INIT_WITH_MASK)
            fg |= maybe & ((gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)) & ~wall  # what the border model explains stays wall
        else:
            fg |= maybe & (lf > lb)
    else:
        logger.info("matting: too few sure pixels for a colour model; using the silhouette band")
        fg |= (sil_in | edge_zone) & valid
    fg = ndimage.binary_opening(fg, _disk(1.5)) | core
    lab, n = ndimage.label(fg)
    if n > 1:  # only regions connected to the face
        keep = np.unique(lab[core])
        fg = np.isin(lab, keep[keep > 0])
    fg = ndimage.binary_fill_holes(fg)
    alpha = fg.astype(np.float32)
    if cfg.feather_px > 0:
        alpha = ndimage.gaussian_filter(alpha, cfg.feather_px)
    return np.clip(alpha * valid, 0.0, 1.0).astype(np.float32)
