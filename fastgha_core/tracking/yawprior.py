"""Yaw of a wide-turned head read off the Face Mesh's 2D layout (a regression learned on synthetic renders).

Beyond ~60 degrees the Face Mesh squeezes the far half of the face onto the visible half, and a
landmark fit of the head model saturates at 55-60 degrees (docs/tracking-log.md). The 2D layout of
the 468 points still changes with the yaw (the nose tip moves against the face outline, the
visible half widens), so a linear regression from the layout to the yaw, learned on synthetic
renders with known cameras, reads wide yaws better than the fit. The fitter uses it as a prior on
the yaw of photos that it finds turned by at least ``FitConfig.yaw_prior_min_fit_deg`` and that
the regression finds turned further than the fit and by at least ``yaw_prior_min_deg``
(``fit._fit_landmarks``).

Features (:func:`layout_features`): the 468 points relative to the midpoint of the forehead
(point 10) - chin (point 152) segment, in axes along / across that segment, divided by its length
(so translation, scale and roll drop out); ``[936]``. The regression (ridge, ``RIDGE``) maps
them to the yaw in degrees (+ = nose towards the image's right edge) and is trained on views
turned by at least ``MIN_TRAIN_YAW`` degrees only.

Training data (:func:`render_training_views`): synthetic subjects (``data/synthetic.py``, seeds
``TRAINING_BATCHES``: the yaw-map calibration seeds 1000100-1000107 and 1000300-1000315; the
evaluation seeds 1000200+ are held out) rendered at yaw 0, 20, 40, 50, ..., 90 (+-2.5 jitter),
pitch +-15 degrees, mild random expressions, 512 x 512, 25-degree camera at 1 m; each render
also mirrored (negative yaw). Rebuild the shipped coefficients
(``assets/headmodel/mediapipe_yaw_regression.npz``) with
``python -m fastgha_core.tracking.yawprior`` (~1 min).
"""

from __future__ import annotations

import functools
import math
import sys
from pathlib import Path

import numpy as np

__all__ = ["layout_features", "predict_yaw", "load_regression", "render_training_views", "train_regression", "calibration_table",
           "REGRESSION_ASSET", "HELD_OUT_BATCHES"]

REGRESSION_ASSET = Path(__file__).resolve().parent.parent / "assets" / "headmodel" / "mediapipe_yaw_regression.npz"
TRAINING_BATCHES = ((1_000_100, 8), (1_000_300, 16))  # (first seed, subjects); rng seeded by the first seed
TRAINING_YAWS = (0, 20, 40, 50, 55, 60, 65, 70, 75, 80, 85, 90)
MIN_TRAIN_YAW = 35.0
RIDGE = 1.0
HELD_OUT_BATCHES = ((1_000_200, 12),)  # the evaluation subjects (never trained on): ``--check``


def layout_features(points: np.ndarray) -> np.ndarray:
    """``[468, 2]`` Face Mesh points (pixels, MediaPipe's order) -> ``[936]`` normalised layout (module doc).

    Raises ValueError when the shape is not ``[468, 2]`` or forehead and chin coincide.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.shape != (468, 2):
        raise ValueError(f"expected the 468 Face Mesh points [468, 2], got {list(p.shape)}")
    mid, right, down, length = face_axes(p)
    d = p - mid
    return (np.stack([d @ right, d @ down], axis=1) / length).reshape(-1)


def face_axes(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The face's own frame in the image from ``[468, 2]`` Face Mesh points (pixels): ``(mid [2],
    right [2], down [2], length)``, where ``down`` is the unit vector from the forehead point (10) to
    the chin (152), ``right`` is ``down`` turned to image +x for an upright face, ``mid`` is their
    midpoint and ``length`` their distance in pixels. Raises ValueError when they coincide."""
    top, chin = p[10], p[152]
    length = float(np.linalg.norm(chin - top))
    if not length > 1e-6:
        raise ValueError("forehead and chin points coincide: not a face layout")
    down = (chin - top) / length
    return 0.5 * (top + chin), np.array([down[1], -down[0]]), down, length


@functools.lru_cache(maxsize=1)
def load_regression(path: str | None = None) -> np.ndarray | None:
    """Shipped coefficients ``[937]`` (936 features + intercept), or None when the asset is absent."""
    p = Path(path) if path else REGRESSION_ASSET
    if not p.is_file():
        return None
    return np.load(p)["coef"].astype(np.float64)


def predict_yaw(points: np.ndarray, coef: np.ndarray | None = None) -> float | None:
    """Regressed yaw in degrees of one face's ``[468, 2]`` Face Mesh points, or None without coefficients.

    Only meaningful for heads turned by >= ``MIN_TRAIN_YAW`` degrees (trained there)."""
    coef = load_regression() if coef is None else coef
    if coef is None:
        return None
    return float(layout_features(points) @ coef[:-1] + coef[-1])


def render_training_views(batches=TRAINING_BATCHES, yaws=TRAINING_YAWS, size: int = 512, fov_deg: float = 25.0,
                          with_masks: bool = False) -> dict:
    """Synthetic renders through MediaPipe (module doc): ``{"seed", "yaw", "pitch" [M], "points" [M, 468, 2]}``;
    with ``with_masks`` also ``"mask" [M, ceil(size^2 / 8)]``: the photo pipeline's person mask of each
    render (``silhouette.person_mask`` > 0.5, ``np.packbits`` of the ``[size, size]`` bool array)."""
    from ..cameras import Cameras
    from ..data.synthetic import SyntheticSubject
    from .faces import MeshDetector

    det = MeshDetector(min_face_px=1.0)
    rec: dict[str, list] = {k: [] for k in ("seed", "yaw", "pitch", "points") + (("mask",) if with_masks else ())}
    for first, n in batches:
        rng = np.random.default_rng(first)
        for s in range(first, first + n):
            sub = SyntheticSubject(s)
            for yaw in yaws:
                e = np.zeros(53, np.float32)
                k = rng.integers(2, 5)
                e[rng.choice(53, k, replace=False)] = rng.uniform(0.1, 0.6, k)
                pitch = rng.uniform(-15, 15)
                y = yaw + rng.uniform(-2.5, 2.5)
                a, p = -math.radians(y), math.radians(pitch)  # a camera at azimuth -y sees the head turned by +y
                eye = [math.sin(a) * math.cos(p), math.sin(p), math.cos(a) * math.cos(p)]
                cam = Cameras.look_at(eye, fov_deg=fov_deg, width=size, height=size).flatten()
                img = (sub.render(sub.frame(e), cam)[0].image.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
                for flip in (False, True):
                    im = img[:, ::-1].copy() if flip else img
                    faces = det.detect_all(im)
                    if faces:
                        if with_masks:
                            from .silhouette import person_mask

                            rec["mask"].append(np.packbits(person_mask(im) > 0.5))
                        rec["seed"].append(s)
                        rec["yaw"].append(-y if flip else y)
                        rec["pitch"].append(pitch)
                        rec["points"].append(faces[0][1])
    return {k: np.asarray(v) for k, v in rec.items()}


def train_regression(points: np.ndarray, yaw: np.ndarray, min_yaw: float = MIN_TRAIN_YAW, ridge: float = RIDGE) -> np.ndarray:
    """Ridge regression ``[937]`` from layouts ``[M, 468, 2]`` to yaws ``[M]`` (degrees), on ``|yaw| >= min_yaw``."""
    keep = np.abs(yaw) >= min_yaw
    if keep.sum() < 10:
        raise ValueError(f"need at least 10 training views turned by >= {min_yaw} degrees, got {int(keep.sum())}")
    A = np.stack([layout_features(p) for p in points[keep]])
    A = np.c_[A, np.ones(len(A))]
    return np.linalg.solve(A.T @ A + ridge * np.eye(A.shape[1]), A.T @ yaw[keep].astype(np.float64))


def calibration_table(true_yaw: np.ndarray, read_yaw: np.ndarray, width: float = 5.0) -> dict[str, list[tuple]]:
    """How the regression reads held-out views, both ways (views are folded to one side: |true yaw|,
    readings signed by the true side, so a reading on the wrong side counts as negative).

    Returns ``{"by_true": [(bin centre, n, mean reading, mean |error|)], "by_reading": [(bin start, n,
    mean true)]}``: ``by_true`` bins the true yaw to the nearest multiple of ``width`` degrees;
    ``by_reading`` bins the folded reading in ``[k width, (k + 1) width)``; empty bins are left out.
    ``by_reading`` is what a calibration of the output (E[true | reading]) would map a reading to.
    Raises ValueError on different lengths.
    """
    y, r = np.asarray(true_yaw, np.float64).reshape(-1), np.asarray(read_yaw, np.float64).reshape(-1)
    if y.shape != r.shape:
        raise ValueError(f"true and read yaws must have the same length, got {y.size} and {r.size}")
    side = np.where(y < 0, -1.0, 1.0)
    a, rf = np.abs(y), r * side
    by_true, by_read = [], []
    centre = np.round(a / width) * width
    for c in np.unique(centre):
        k = centre == c
        by_true.append((float(c), int(k.sum()), float(rf[k].mean()), float(np.abs(rf[k] - a[k]).mean())))
    lo = np.floor(rf / width) * width
    for c in np.unique(lo):
        k = lo == c
        by_read.append((float(c), int(k.sum()), float(a[k].mean())))
    return {"by_true": by_true, "by_reading": by_read}


def main(argv: list[str] | None = None) -> int:  # pragma: no cover - rebuilds the shipped asset
    import argparse

    p = argparse.ArgumentParser(prog="python -m fastgha_core.tracking.yawprior", description="rebuild the yaw regression (or check it)")
    p.add_argument("--check", action="store_true", help="instead: read renders of the held-out subjects with the shipped regression")
    if p.parse_args(argv).check:
        d = render_training_views(HELD_OUT_BATCHES)
        coef = load_regression()
        read = np.array([predict_yaw(q, coef) for q in d["points"]])
        t = calibration_table(d["yaw"], read)
        print(f"{len(read)} detected views of {HELD_OUT_BATCHES[0][1]} held-out subjects")
        print("| true yaw | views | mean reading | mean abs error |\n|---|---|---|---|")
        for c, n, m, e in t["by_true"]:
            print(f"| {c:.0f} | {n} | {m:.1f} | {e:.1f} |")
        print("| reading | views | mean true yaw |\n|---|---|---|")
        for c, n, m in t["by_reading"]:
            print(f"| {c:.0f}-{c + 5:.0f} | {n} | {m:.1f} |")
        return 0
    d = render_training_views()
    coef = train_regression(d["points"], d["yaw"])
    np.savez_compressed(REGRESSION_ASSET, coef=coef.astype(np.float32))
    print(f"wrote {REGRESSION_ASSET}: {len(d['yaw'])} views, {int((np.abs(d['yaw']) >= MIN_TRAIN_YAW).sum())} used")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
