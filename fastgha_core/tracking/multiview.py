"""Relative head poses between photos of one person from image features (a measurement, not in the fit).

Landmarks alone saturate beyond ~60 degrees of yaw (docs/tracking-log.md); features matched between
two photos of the same head are independent multi-view evidence. This module measures how much
of it real photo sets hold:

1. :func:`head_features`: SIFT keypoints (``cv2.SIFT_create``) inside the fitted head's coverage
   in one photo (the ICT mesh rasterized at the fitted pose), each lifted onto the fitted surface
   (the rasterized depth) and expressed in head axes. Points that do not move rigidly with the
   skull are dropped: within ``mouth_radius_m`` of the mouth centre (ICT landmarks 48-67) and
   below the chin (neck, collar).
2. :func:`relative_pose`: ratio-test matches (``cv2.BFMatcher``, Lowe's 0.8) between photo ``a``'s
   head-space points and photo ``b``'s keypoints, then the head pose in ``b`` by PnP with RANSAC
   (``cv2.solvePnPRansac``, threshold ``threshold_frac`` of ``b``'s face size). Returns None when
   fewer than ``min_inliers`` agree.

The pose in ``b`` inherits ``a``'s pose and head shape (the 3D points come from ``a``'s fit), so
it measures the rotation *between* the photos: ``R_b R_a^T``.

On synthetic renders with known cameras (true geometry for ``a``) 20-25 degrees apart, the pose in
``b`` comes out within 1.4-2.1 degrees with 32-48 inliers; 45 degrees apart, 10 inliers remain
(tests/test_tracking_multiview.py). On the real sets (``python -m fastgha_core.tracking.multiview``)
neighbouring frames of the white-background video give 22-69 inliers, but the wide pairs (55-85
degrees apart: the photos the landmark fit gets wrong) give 0-8 inliers among 14-46 putative
matches, and the poses they imply scatter over +-150 degrees: too little evidence to correct the
wide yaws, so it is not a residual of the fit (docs/tracking-log.md).
"""

from __future__ import annotations

import argparse
import itertools
import sys
from dataclasses import dataclass

import numpy as np

__all__ = ["HeadFeatures", "head_features", "match_features", "relative_pose", "main"]


@dataclass
class HeadFeatures:
    """Keypoints of one photo on the fitted head."""

    uv: np.ndarray  # [M, 2] float32 pixels (corner convention, OpenCV's keypoint positions)
    descriptors: np.ndarray  # [M, 128] float32 SIFT descriptors
    head_points: np.ndarray  # [M, 3] float64 metres, head axes: the keypoints lifted onto the fitted surface
    face_px: float  # the fitted face's size in this photo (pixels; landmark-box diagonal of the 68 ICT landmarks)


def head_features(
    image: np.ndarray,  # [H, W, 3] uint8 RGB
    vertices: np.ndarray,  # [Nv, 3] fitted head vertices (metres, head axes; HeadModel.vertices)
    faces: np.ndarray,  # [F, 3] visible triangles (HeadModel.visible_faces(eyelashes=False))
    R: np.ndarray,  # [3, 3] head -> camera rotation
    t: np.ndarray,  # [3] head origin in the camera (metres)
    K: np.ndarray,  # [3, 3] intrinsics of the photo
    landmarks68: np.ndarray,  # [68] int vertex ids (HeadModel.landmarks68)
    max_features: int = 4000,
    mouth_radius_m: float = 0.03,
    edge_frac: float = 0.02,
) -> HeadFeatures:
    """SIFT keypoints on the rigid part of the fitted head (module doc). Raises ValueError on bad shapes."""
    import cv2

    from ..data.meshraster import render_mesh

    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"image must be [H, W, 3] uint8, got {list(img.shape)} {img.dtype}")
    V = np.asarray(vertices, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 3:
        raise ValueError(f"vertices must be [Nv, 3], got {list(V.shape)}")
    R, t, K = np.asarray(R, np.float64), np.asarray(t, np.float64).reshape(3), np.asarray(K, np.float64)
    h, w = img.shape[:2]
    pc = V @ R.T + t
    r = render_mesh(pc.astype(np.float32), faces, np.ones((len(pc), 1), np.float32), K, w, h, supersample=1)
    mask = (r.alpha > 0.5).astype(np.uint8) * 255
    lm = V[np.asarray(landmarks68)]
    lmp = lm @ R.T + t
    lmp = (lmp @ K.T)[:, :2] / (lmp @ K.T)[:, 2:]
    face_px = float(np.linalg.norm(lmp.max(0) - lmp.min(0)))
    k = 2 * int(round(edge_frac * face_px)) + 1  # off the outline, where the rasterized depth jumps
    mask = cv2.erode(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    kp, des = cv2.SIFT_create(nfeatures=max_features, contrastThreshold=0.01).detectAndCompute(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), mask)
    uv = np.array([k.pt for k in kp], dtype=np.float32).reshape(-1, 2)
    des = np.zeros((0, 128), np.float32) if des is None else des.astype(np.float32)
    if len(uv) == 0:
        return HeadFeatures(uv, des, np.zeros((0, 3)), face_px)
    ix = np.clip(uv[:, 0].astype(int), 0, w - 1)
    iy = np.clip(uv[:, 1].astype(int), 0, h - 1)
    z = r.depth[iy, ix].astype(np.float64)
    ray = np.c_[uv.astype(np.float64), np.ones(len(uv))] @ np.linalg.inv(K).T
    X = (ray * z[:, None] - t) @ R  # camera -> head axes
    mouth = lm[48:68].mean(0)
    chin_y = float(lm[8, 1])
    keep = (z > 0) & (np.linalg.norm(X - mouth, axis=1) > mouth_radius_m) & (X[:, 1] > chin_y)
    return HeadFeatures(uv[keep], des[keep], X[keep], face_px)


def relative_pose(
    a: HeadFeatures,
    b: HeadFeatures,
    K_b: np.ndarray,  # [3, 3] intrinsics of photo b
    ratio: float = 0.8,
    threshold_frac: float = 0.02,
    min_inliers: int = 12,
) -> tuple[np.ndarray, np.ndarray, int, int] | None:
    """Head pose in photo ``b`` from ``a``'s lifted keypoints: ``(R [3, 3], t [3], inliers, putative)``, or None.

    None when there are fewer than 6 putative matches or fewer than ``min_inliers`` RANSAC inliers.
    """
    import cv2

    ia, ib = match_features(a, b, ratio)
    if len(ia) < 6:
        return None
    X = a.head_points[ia].astype(np.float64)
    x = b.uv[ib].astype(np.float64)
    cv2.setRNGSeed(0)  # RANSAC's samples: the same answer for the same photos
    ok, rv, tv, inl = cv2.solvePnPRansac(X, x, np.asarray(K_b, np.float64), None, reprojectionError=threshold_frac * b.face_px,
                                         iterationsCount=2000, confidence=0.999, flags=cv2.SOLVEPNP_ITERATIVE)  # fmt: skip
    n = 0 if inl is None else len(inl)
    if not ok or n < max(min_inliers, 4):
        return None
    idx = inl.reshape(-1)  # refine on the inliers
    ok, rv, tv = cv2.solvePnP(X[idx], x[idx], np.asarray(K_b, np.float64), None, rv, tv, useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    return cv2.Rodrigues(rv)[0], tv.reshape(3), n, len(ia)


def match_features(a: HeadFeatures, b: HeadFeatures, ratio: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """Putative matches ``(indices into a [P], indices into b [P])``: nearest SIFT descriptor of
    ``b`` for each of ``a`` (L2), kept when closer than ``ratio`` x the second nearest (Lowe's test)."""
    import cv2

    if len(a.uv) < 2 or len(b.uv) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a.descriptors, b.descriptors, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < ratio * p[1].distance]
    return np.array([g.queryIdx for g in good], np.int64), np.array([g.trainIdx for g in good], np.int64)


def main(argv: list[str] | None = None) -> int:  # pragma: no cover - evaluation on the real sets (not shipped)
    """Every ordered pair of photos of every real set: putative matches, inliers, and the yaw of
    ``b`` implied by ``a``'s fit against ``b``'s own fitted yaw."""
    from ..data.headmodel import HeadModel
    from .pipeline import TrackConfig, track_photos
    from .realsets import _read, annotated_yaw, head_angles_deg, realsets_root

    p = argparse.ArgumentParser(prog="python -m fastgha_core.tracking.multiview", description=__doc__.split("\n")[0])
    p.add_argument("--root", default=None, help="folder of photo sets (default: ../shared/realsets or $FASTGHA_REALSETS)")
    a = p.parse_args(argv)
    from pathlib import Path

    root = Path(a.root) if a.root else realsets_root()
    head = HeadModel.load()
    faces = head.visible_faces(eyelashes=False)
    print("| set | a | b | b annotated | b fitted | putative | inliers | b from a |")
    print("|---|---|---|---|---|---|---|---|")
    for d in sorted(q for q in root.iterdir() if q.is_dir()):
        paths = sorted(q for q in d.iterdir() if q.suffix.lower() in (".jpg", ".jpeg", ".png"))
        imgs = [_read(q) for q in paths]
        res = track_photos(imgs, TrackConfig(), names=[q.name for q in paths])
        fit = res.fit
        feats = []
        for v, img in enumerate(imgs):
            verts = head.vertices(fit.identity.astype(np.float32), fit.expressions[v].astype(np.float32))
            feats.append(head_features(img, verts, faces, fit.rotations[v], fit.translations[v], fit.K[v], head.landmarks68))
        for i, j in itertools.permutations(range(len(imgs)), 2):
            out = relative_pose(feats[i], feats[j], fit.K[j], min_inliers=1)
            got = "-" if out is None else f"{head_angles_deg(out[0])[0]:.1f}"
            m = len(match_features(feats[i], feats[j])[0])
            n = 0 if out is None else out[2]
            print(f"| {d.name} | {paths[i].name[:2]} | {paths[j].name[:2]} | {annotated_yaw(paths[j].name)} | "
                  f"{head_angles_deg(fit.rotations[j])[0]:.1f} | {m} | {n} | {got} |")  # fmt: skip
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
