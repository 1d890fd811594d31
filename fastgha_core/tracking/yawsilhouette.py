"""Yaw read off the head's silhouette relative to the Face Mesh (a measurement, not in the fit).

Beyond ~60 degrees the Face Mesh layout saturates (``yawprior.py``, docs/tracking-log.md), but the
outline of the matted head keeps changing: the back of the head moves away from the nose tip and
the near side of the face covers more of the head's width. This module measures whether that
evidence, learned on synthetic renders as the layout regression is, transfers to real photos.
It did not (docs/tracking-log.md, "Tried for the wide yaws and not kept"), so nothing here is used by
the tracker; ``python -m fastgha_core.tracking.yawsilhouette`` reproduces the figures.

Features (:func:`silhouette_edges`): the face axis of ``yawprior.layout_features`` (forehead point
10 -> chin point 152, length ``L``); at ``HEIGHTS`` (fractions of ``L`` from the segment's
midpoint, + = towards the chin) the person mask is scanned across the axis, and the run of mask
pixels nearest the face's centre (within half a face length) gives a back edge (away from the nose) and a front edge (towards it),
each relative to the nose tip (point 1) and divided by ``L``. ``side`` folds the photo so that
the nose points to +x: the features of a head turned right and of its mirror image are equal.
"""

from __future__ import annotations

import sys

import numpy as np
from scipy import ndimage

from .yawprior import face_axes

__all__ = ["HEIGHTS", "silhouette_edges", "silhouette_features", "near_contour_fraction", "fit_folded_ridge", "predict_folded"]

HEIGHTS = (-0.45, -0.3, -0.15, 0.0, 0.15, 0.3)  # forehead (-0.5) to below the mouth; chin = +0.5
NOSE_TIP = 1
NEAR_CONTOUR = {1: (127, 234, 93, 132), -1: (356, 454, 323, 361)}  # face-oval points on the side away from the nose


def silhouette_edges(mask: np.ndarray, points: np.ndarray, side: float, heights=HEIGHTS) -> np.ndarray:
    """``[len(heights), 2]`` (back, front) edges of the person ``mask [H, W]`` (bool or alpha > 0.5)
    across the face axis of the ``[468, 2]`` Face Mesh ``points`` (pixels), relative to the nose
    tip, in units of the forehead-chin length, folded so that the nose points to +x (``side`` = +1
    for a head turned towards the image's right edge, -1 for the left; module doc). A height
    whose scan line holds no mask pixel within half a face length of the landmarks' centre gives NaN. Raises ValueError on other shapes or when
    forehead and chin coincide.
    """
    m = np.asarray(mask)
    m = m > 0.5 if m.dtype != bool else m
    p = np.asarray(points, dtype=np.float64)
    if m.ndim != 2 or p.shape != (468, 2):
        raise ValueError(f"expected a mask [H, W] and the 468 Face Mesh points [468, 2], got {list(m.shape)} and {list(p.shape)}")
    mid, right, down, L = face_axes(p)
    right = right * (1.0 if side >= 0 else -1.0)
    u_nose = float((p[NOSE_TIP] - mid) @ right) / L
    u_face = float((p.mean(0) - mid) @ right) / L
    u = np.arange(-2.5, 2.5, 0.5 / L)  # half-pixel steps, +-2.5 L around the face's midpoint
    H, W = m.shape
    out = np.full((len(heights), 2), np.nan)
    for i, h in enumerate(heights):
        xy = (mid + h * L * down)[None] + (u[:, None] * L) * right[None]
        x, y = np.floor(xy[:, 0]).astype(int), np.floor(xy[:, 1]).astype(int)  # pixel (x, y) covers [x, x + 1)
        ok = (x >= 0) & (x < W) & (y >= 0) & (y < H)
        row = np.zeros(len(u), bool)
        row[ok] = m[y[ok], x[ok]]
        if not row.any():
            continue
        lab, _ = ndimage.label(row)
        on = np.flatnonzero(row)
        j = on[np.argmin(np.abs(u[on] - u_face))]  # the run nearest the face's centre ...
        if abs(u[j] - u_face) > 0.5:  # ... if it comes within half a face length of it (else: another person)
            continue
        run = np.flatnonzero(lab == lab[j])
        out[i] = (u[run[0]] - u_nose, u[run[-1]] - u_nose)
    return out


def near_contour_fraction(mask: np.ndarray, points: np.ndarray, side: float) -> float:
    """Where the Face Mesh's face outline on the side away from the nose (``NEAR_CONTOUR``, the
    cheek towards the ear) lies between the back edge of the head (0) and the nose tip (1), on the
    scan lines through those points, averaged: the visible share of the head that is face. NaN
    when no scan line finds the head. Raises like :func:`silhouette_edges`."""
    p = np.asarray(points, dtype=np.float64)
    if p.shape != (468, 2):
        raise ValueError(f"expected the 468 Face Mesh points [468, 2], got {list(p.shape)}")
    s = 1.0 if side >= 0 else -1.0
    mid, right, down, L = face_axes(p)
    right = right * s
    ids = NEAR_CONTOUR[int(s)]
    e = silhouette_edges(mask, p, s, heights=tuple(float((p[j] - mid) @ down) / L for j in ids))
    u = np.array([float((p[j] - p[NOSE_TIP]) @ right) / L for j in ids])  # relative to the nose tip, like the edges
    f = (u - e[:, 0]) / (-e[:, 0])
    return float(np.nanmean(f)) if np.isfinite(f).any() else float("nan")


def silhouette_features(mask: np.ndarray, points: np.ndarray, side: float) -> np.ndarray:
    """``[2 len(HEIGHTS)]``: :func:`silhouette_edges` flattened (back, front per height); NaN -> 0."""
    return np.nan_to_num(silhouette_edges(mask, points, side).reshape(-1))


def fit_folded_ridge(features: np.ndarray, abs_yaw: np.ndarray, ridge: float) -> np.ndarray:
    """Ridge regression ``[F + 1]`` (unpenalised intercept last) from ``[M, F]`` to ``|yaw| [M]``."""
    A = np.c_[np.asarray(features, np.float64), np.ones(len(features))]
    reg = ridge * np.eye(A.shape[1])
    reg[-1, -1] = 0.0
    return np.linalg.solve(A.T @ A + reg, A.T @ np.asarray(abs_yaw, np.float64))


def predict_folded(coef: np.ndarray, features: np.ndarray) -> np.ndarray:
    """``[M]`` |yaw| readings of :func:`fit_folded_ridge` coefficients."""
    return np.c_[np.asarray(features, np.float64), np.ones(len(features))] @ coef


def _views(batches) -> dict:
    from .yawprior import layout_features, load_regression, render_training_views

    d = render_training_views(batches, with_masks=True)
    coef = load_regression()
    lay = np.stack([layout_features(q) for q in d["points"]])
    side = np.where(lay @ coef[:-1] + coef[-1] < 0, -1.0, 1.0)  # the shipped regression's side, as on photos
    n = d["points"].shape[0]
    masks = [np.unpackbits(d["mask"][i])[: 512 * 512].reshape(512, 512).astype(bool) for i in range(n)]
    sil = np.stack([silhouette_features(masks[i], d["points"][i], side[i]) for i in range(n)])
    near = np.array([near_contour_fraction(masks[i], d["points"][i], side[i]) for i in range(n)])
    return {"yaw": d["yaw"], "layout": lay, "sil": sil, "side": side, "near": near}


def main(argv: list[str] | None = None) -> int:  # pragma: no cover - a measurement (renders + the real sets)
    import argparse
    from unittest import mock

    from . import yawprior
    from .faces import load_face_detector
    from .realsets import _read, annotated_yaw, evaluate_realsets, realsets_root
    from .silhouette import person_mask

    ap = argparse.ArgumentParser(prog="python -m fastgha_core.tracking.yawsilhouette", description=__doc__.split("\n")[0])
    ap.add_argument("--no-realsets", action="store_true", help="only the synthetic figures")
    a = ap.parse_args(argv)
    tr, te = _views(yawprior.TRAINING_BATCHES), _views(yawprior.HELD_OUT_BATCHES)
    k = np.abs(tr["yaw"]) >= yawprior.MIN_TRAIN_YAW
    coef_l = yawprior.load_regression()

    def combined(d):  # the layout and the signed silhouette features, one signed ridge (x3: the features' scale)
        return np.c_[d["layout"], 3.0 * d["sil"] * d["side"][:, None], np.ones(len(d["yaw"]))]

    A, ay = combined(tr)[k], np.abs(tr["yaw"][k])
    coef_c = np.linalg.solve(A.T @ A + np.eye(A.shape[1]), A.T @ tr["yaw"][k])
    coef_s = fit_folded_ridge(tr["sil"][k], ay, 0.1)  # all 12 edges
    coef_b = fit_folded_ridge(tr["sil"][k][:, 0::2], ay, 1.0)  # the 6 back edges
    models = {  # name -> signed readings [M] of a set of views
        "layout (shipped)": lambda d: d["layout"] @ coef_l[:-1] + coef_l[-1],
        "silhouette, folded": lambda d: predict_folded(coef_s, d["sil"]) * d["side"],
        "back edges, folded": lambda d: predict_folded(coef_b, d["sil"][:, 0::2]) * d["side"],
        "layout + silhouette": lambda d: combined(d) @ coef_c,
    }
    kt = np.abs(te["yaw"]) >= yawprior.MIN_TRAIN_YAW
    print(f"held-out renders ({int(kt.sum())} detected views turned >= {yawprior.MIN_TRAIN_YAW:.0f}): mean reading / mean abs error by true yaw")
    bins = np.round(np.abs(te["yaw"]) / 5) * 5
    print("| regression | MAE | " + " | ".join(f"{c:.0f}" for c in np.unique(bins[kt])) + " |")
    for name, f in models.items():
        r = f(te)
        cells = []
        for c in np.unique(bins[kt]):
            s = kt & (bins == c)
            cells.append(f"{np.mean(r[s] * np.sign(te['yaw'][s])):.0f} / {np.mean(np.abs(r[s] - te['yaw'][s])):.1f}")
        print(f"| {name} | {np.mean(np.abs(r - te['yaw'])[kt]):.1f} | " + " | ".join(cells) + " |")
    fr = te["near"]
    print("| near-side contour fraction (mean, sd) | | " + " | ".join(f"{np.nanmean(fr[kt & (bins == c)]):.2f}, {np.nanstd(fr[kt & (bins == c)]):.2f}" for c in np.unique(bins[kt])) + " |")
    print("front edges (mean per height, lowest to highest): " + ", ".join(
        f"{c:.0f}: {te['sil'][kt & (bins == c)][:, 1::2].mean(0).min():+.2f} to {te['sil'][kt & (bins == c)][:, 1::2].mean(0).max():+.2f}" for c in np.unique(bins[kt])))  # fmt: skip
    print("back edge at eye height (-0.3), mean and sd in face lengths: " + ", ".join(
        f"{c:.0f}: {np.mean(te['sil'][kt & (bins == c), 2]):.2f} ({np.std(te['sil'][kt & (bins == c), 2]):.2f})" for c in np.unique(bins[kt])))  # fmt: skip
    if a.no_realsets:
        return 0
    root = realsets_root()
    if not root.is_dir():
        print(f"no real sets at {root}; skipped")
        return 0
    det = load_face_detector()
    real = {"yaw": [], "layout": [], "sil": [], "side": [], "points": [], "name": [], "near": []}
    for d in sorted(q for q in root.iterdir() if q.is_dir()):
        for p in sorted(q for q in d.iterdir() if q.suffix.lower() in (".jpg", ".jpeg", ".png")):
            img = _read(p)
            pts = det.detect_one(img, p.name)[1]
            lay = yawprior.layout_features(pts)
            side = -1.0 if lay @ coef_l[:-1] + coef_l[-1] < 0 else 1.0
            real["name"].append(f"{d.name}/{p.name}")
            real["yaw"].append(annotated_yaw(p.name))
            real["points"].append(pts)
            real["layout"].append(lay)
            real["side"].append(side)
            pm = person_mask(img) > 0.5
            real["sil"].append(silhouette_features(pm, pts, side))
            real["near"].append(near_contour_fraction(pm, pts, side))
    real = {n: np.asarray(v) if n != "name" else v for n, v in real.items()}
    reads = {name: f(real) for name, f in models.items()}
    print("\nreal photos: readings (every photo; only those the fit finds turned >= 30 degrees can take the prior)")
    print("| photo | annotated | " + " | ".join(reads) + " | back edge at eye height | front edges | near-side contour fraction |")
    for i, n in enumerate(real["name"]):
        print(f"| {n} | {real['yaw'][i]:+.0f} | " + " | ".join(f"{reads[m][i]:+.1f}" for m in reads)
              + f" | {real['sil'][i][2]:.2f} | {', '.join(f'{x:.2f}' for x in real['sil'][i][1::2])} | {real['near'][i]:.2f} |")  # fmt: skip
    print("\nreal sets tracked with each reading as the yaw prior's (same rule: >= 55, further than the fit, same side)")
    for name, r in reads.items():
        def read(points, coef=None, r=r):
            i = int(np.argmin(np.abs(real["points"] - np.asarray(points)[None]).sum((1, 2))))
            return float(r[i])

        with mock.patch.object(yawprior, "predict_yaw", read):
            rows = evaluate_realsets(root, detector=det)
        errs = [x["yaw_error"] for x in rows]
        print(f"{name}: median {np.median(errs):.1f}, max {max(errs):.1f}, within 15: {sum(e <= 15 for e in errs)}/{len(errs)}; "
              + ", ".join(f"{x['set']}/{x['photo'][:2]} {x['yaw']:+.1f}" for x in rows))  # fmt: skip
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
