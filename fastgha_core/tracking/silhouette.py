"""The head's outline as a constraint for side views (where the Face Mesh squeezes the far side).

In a turned head the outline of the face against the background (forehead, brow ridge, nose,
lips, chin; or the far cheek at 40-60 degrees) is where the model's surface grazes the line of
sight. Its position in the image pins the yaw much better than landmarks guessed on the hidden
half. Per photo:

1. **Person mask**: MediaPipe's selfie segmentation (``mediapipe.solutions.selfie_segmentation``,
   the general model shipped in the wheel), thresholded at 0.5 - or the user's mask. From it a
   signed distance field in pixels (+ outside) and its gradient (``SilhouetteTarget``).
2. **Model outline points** (``outline_vertices``): ICT face vertices of the front half of the
   head between the chin and the brows (``FRONT_BAND``: hair, ears, neck and the back of the
   head do not make a reliable outline) whose normal is within ``grazing`` of perpendicular to the
   line of sight, and that lie on the rendered head's outer edge (the rendered head is empty a few
   pixels outward along the projected normal).
3. **Residual**: the signed distance at each outline point's projection, clipped at
   ``clip_frac`` x the face size (a mask error, a hand or a strand of hair cannot pull without
   bound), weighted so all outline points of a photo weigh ``silhouette_weight`` x the photo's
   landmarks (``fit.FitConfig``).

Used by ``fit.fit_landmarks(..., silhouettes=...)`` for photos turned by at least
``FitConfig.silhouette_min_yaw`` degrees after the landmark-only fit.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

__all__ = ["SilhouetteTarget", "person_mask", "outline_vertices", "FRONT_BAND"]

# head-space band (metres, axes of docs/conventions.md) of candidate outline vertices: z > z_min (front half),
# y from chin + 1.2 cm to eye level + 4 cm (below the hairline)
FRONT_BAND = {"z_min": 0.0, "below_chin": 0.012, "above_eyes": 0.04}


@dataclass
class SilhouetteTarget:
    """Signed distance to a photo's person-mask outline: ``sdf [H, W]`` px (+ outside),
    ``grad [2, H, W]`` (d/dx, d/dy) of it, and the face size in pixels (for the clip)."""

    sdf: np.ndarray
    grad: np.ndarray
    face_px: float

    @staticmethod
    def from_mask(mask: np.ndarray, face_px: float) -> "SilhouetteTarget":
        m = np.asarray(mask) > 0.5
        if not m.any() or m.all():
            raise ValueError("the person mask is empty or covers the whole photo; no outline to fit")
        sdf = (ndimage.distance_transform_edt(~m) - ndimage.distance_transform_edt(m)).astype(np.float32)
        gy, gx = np.gradient(sdf)
        return SilhouetteTarget(sdf, np.stack([gx, gy]).astype(np.float32), float(face_px))

    def sample(self, uv: np.ndarray, clip: float) -> tuple[np.ndarray, np.ndarray]:
        """``(value [N], gradient [N, 2])`` at pixel positions ``uv [N, 2]`` (corner convention),
        bilinear; values clipped at +-``clip`` px with zero gradient there."""
        h, w = self.sdf.shape
        x = np.clip(uv[:, 0] - 0.5, 0, w - 1.001)
        y = np.clip(uv[:, 1] - 0.5, 0, h - 1.001)
        x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
        fx, fy = x - x0, y - y0

        def bil(a):
            return (a[y0, x0] * (1 - fx) * (1 - fy) + a[y0, x0 + 1] * fx * (1 - fy)
                    + a[y0 + 1, x0] * (1 - fx) * fy + a[y0 + 1, x0 + 1] * fx * fy)  # fmt: skip

        val = bil(self.sdf)
        g = np.stack([bil(self.grad[0]), bil(self.grad[1])], axis=1)
        out = np.abs(val) > clip
        g[out] = 0.0
        return np.clip(val, -clip, clip), g


_SEG = {}


def person_mask(img: np.ndarray) -> np.ndarray:
    """``[H, W]`` float32 in [0, 1]: MediaPipe selfie segmentation of ``img [H, W, 3]`` uint8 RGB."""
    import os

    os.environ.setdefault("GLOG_minloglevel", "2")
    import mediapipe as mp  # type: ignore

    if "general" not in _SEG:
        from .faces import QuietGraph  # its C++ start-up lines off stderr

        _SEG["general"] = QuietGraph(lambda: mp.solutions.selfie_segmentation.SelfieSegmentation(model_selection=0))
    return np.asarray(_SEG["general"].process(np.ascontiguousarray(img)).segmentation_mask, dtype=np.float32)


@functools.lru_cache(maxsize=2)
def _candidates(head_id: int, step: int = 3) -> np.ndarray:
    from ..data.headmodel import HeadModel

    head = HeadModel.load()
    v = head.neutral
    lm = head.landmarks68
    chin_y, eye_y = float(v[lm[8], 1]), float(v[lm[36:48], 1].mean())
    ids = np.arange(0, 9409)
    keep = (v[ids, 2] > FRONT_BAND["z_min"]) & (v[ids, 1] > chin_y + FRONT_BAND["below_chin"]) & (v[ids, 1] < eye_y + FRONT_BAND["above_eyes"])
    return ids[keep][::step]


def outline_vertices(head, verts: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray, width: int, height: int,
                     grazing: float = 0.15, probe_px: float = 3.0) -> np.ndarray:
    """ICT vertex ids ``[M]`` on the outer outline of the face band (module doc) for head vertices
    ``verts [Nv, 3]`` seen by ``(R, t, K)`` in a ``width x height`` photo."""
    ids = _candidates(id(head))
    normals = head.vertex_normals(verts)[ids] @ R.T
    P = verts[ids] @ R.T + t
    c = -(normals * P).sum(1) / np.linalg.norm(P, axis=1)
    g = np.abs(c) < grazing
    if not g.any():
        return ids[:0]
    ids, P, normals = ids[g], P[g], normals[g]
    uv = (P @ K.T)[:, :2] / (P @ K.T)[:, 2:]
    # outward direction in the image: the projected normal
    tip = P + 0.005 * normals
    uv_tip = (tip @ K.T)[:, :2] / (tip @ K.T)[:, 2:]
    d = uv_tip - uv
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    from ..data.meshraster import render_mesh

    pts = (verts @ R.T + t).astype(np.float32)
    alpha = render_mesh(pts, head.visible_faces(eyelashes=False), np.ones((pts.shape[0], 1), np.float32), K, width, height, supersample=1).alpha
    probe = uv + probe_px * d
    x = np.clip(np.round(probe[:, 0] - 0.5).astype(int), 0, width - 1)
    y = np.clip(np.round(probe[:, 1] - 0.5).astype(int), 0, height - 1)
    inside_img = (probe[:, 0] >= 0) & (probe[:, 0] < width) & (probe[:, 1] >= 0) & (probe[:, 1] < height)
    outer = inside_img & (alpha[y, x] < 0.5)
    return ids[outer]
