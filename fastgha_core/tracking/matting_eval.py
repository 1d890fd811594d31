"""Matting against known alpha: synthetic heads on walls with shading and a soft shadow.

``python -m fastgha_core.tracking.matting_eval [--subjects 6] [--first-seed 1000300] [--method auto] [--perturbed] [--json OUT]``
``python -m fastgha_core.tracking.matting_eval --realsets [--method segmentation,mixture,grabcut]``

Each held-out synthetic subject (``data/synthetic.py``: procedural skin, hair shell, lighting) is
rendered at yaws 0, 35 and 70 degrees (pitch 0, 1 m, 40-degree field of view, 384 x 512 portrait)
and composited, with its exact alpha, over a wall (``wall_background``): a plain colour (white,
light grey, studio grey or beige), a brightness ramp in a random direction, a vignette, sensor
noise and the subject's own shadow (its alpha shifted sideways and down by 4-10 % of the width,
blurred 6-16 px, darkening the wall by 25-45 %). The three views of a subject are tracked
jointly (``track_photos``: MediaPipe landmarks, one fit), so the mask is built from a fitted, not
the true, head. The true alpha goes through the same crop, and per view the report gives:

- ``iou``: intersection over union of mask > 0.5 and true alpha > 0.5;
- ``leak``: the fraction of the mask (> 0.5) where the truth is background (wall or shadow kept);
- ``shadow_kept``: the fraction of shadow pixels (darkened by > 10 %, true alpha < 0.5) in the mask;
- ``miss``: the fraction of the true foreground missing from the mask;
- ``mae``: mean absolute alpha error over the crop's pixels inside the photo;
- ``seconds``: time of ``matte_from_head`` for that view.

``--perturbed`` (``evaluate_perturbed``) skips the detector and gives the matting the true head
made 15 % larger and turned 15 degrees, the way real fits miss (skull too long, yaw off).
``--realsets`` (``evaluate_realsets``) has no truth: per real photo the share of the mask whose
colour matches the crop's background edge (``wall_like_fraction``); the sets are read from
``../shared/realsets`` or ``$FASTGHA_REALSETS`` and never shipped.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

__all__ = ["wall_background", "composite_on_wall", "evaluate_matting", "matting_table"]

WALLS = {  # sRGB in [0, 1]
    "white": (0.93, 0.93, 0.92),
    "light grey": (0.78, 0.78, 0.79),
    "studio grey": (0.52, 0.54, 0.55),
    "beige": (0.85, 0.80, 0.72),
}


def wall_background(rng: np.random.Generator, alpha: np.ndarray, kind: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A wall behind a subject of coverage ``alpha [H, W]``: ``(rgb [H, W, 3] float32 in [0, 1],
    shadow [H, W] float32 darkening in [0, 1))`` (module doc)."""
    h, w = alpha.shape
    name = kind or list(WALLS)[rng.integers(len(WALLS))]
    base = np.asarray(WALLS[name], np.float32) * rng.uniform(0.95, 1.03, 3).astype(np.float32)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    a = rng.uniform(0, 2 * math.pi)
    ramp = ((xx - w / 2) * math.cos(a) + (yy - h / 2) * math.sin(a)) / max(h, w)  # [-0.7, 0.7]
    r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / (0.25 * (h * h + w * w))
    light = 1.0 + rng.uniform(0.15, 0.35) * ramp - rng.uniform(0.05, 0.2) * r2
    sign = rng.choice([-1.0, 1.0])
    dx, dy = sign * rng.uniform(0.04, 0.10) * w, rng.uniform(0.0, 0.05) * w
    shadow = ndimage.shift(alpha.astype(np.float32), (dy, dx), order=1, mode="constant")
    shadow = ndimage.gaussian_filter(shadow, rng.uniform(6.0, 16.0)) * rng.uniform(0.25, 0.45)
    rgb = base[None, None] * (light * (1.0 - shadow))[..., None]
    rgb = rgb + rng.normal(0.0, 1.5 / 255.0, rgb.shape).astype(np.float32)
    return np.clip(rgb, 0.0, 1.0).astype(np.float32), shadow.astype(np.float32)


def composite_on_wall(view, rng: np.random.Generator, kind: str | None = None):
    """A rendered ``data.sample.View`` (over ``BACKGROUND_RGB``) put on a wall: ``(photo [H, W, 3]
    uint8, alpha [H, W] float32, shadow [H, W] float32)``."""
    from ..constants import BACKGROUND_RGB

    color = view.image.permute(1, 2, 0).numpy().astype(np.float32)
    alpha = view.mask[0].numpy().astype(np.float32)
    bgc = np.asarray(BACKGROUND_RGB, np.float32)
    wall, shadow = wall_background(rng, alpha, kind)
    photo = color + (wall - bgc[None, None]) * (1.0 - alpha)[..., None]
    return (np.clip(photo, 0, 1) * 255).round().astype(np.uint8), alpha, shadow


def evaluate_matting(subjects: int = 6, first_seed: int = 1_000_300, yaws=(0.0, 35.0, 70.0), method: str = "auto", seed: int = 0,
                     size: int = 256) -> list[dict]:
    """One row per tracked view (module doc). Views MediaPipe finds no face in are skipped."""
    from ..cameras import Cameras
    from ..data.synthetic import SyntheticSubject
    from . import pipeline
    from .crop import crop_array, head_crop_box
    from .faces import MeshDetector
    from .matting import MattingConfig
    from .pipeline import TrackConfig, track_photos

    det = MeshDetector(min_face_px=1.0)
    rng = np.random.default_rng(seed)
    rows = []
    times: list[float] = []
    orig = pipeline.matte_from_head

    def timed(*a, **k):
        t0 = time.perf_counter()
        out = orig(*a, **k)
        times.append(time.perf_counter() - t0)
        return out

    pipeline.matte_from_head = timed
    try:
        for s in range(subjects):
            sub = SyntheticSubject(first_seed + s)
            photos, truths, shadows, used = [], [], [], []
            for yaw in yaws:
                a = -math.radians(yaw)
                cam = Cameras.look_at([math.sin(a), -0.03, math.cos(a)], fov_deg=40.0, width=384, height=512).flatten()
                view = sub.render(sub.frame(np.zeros(53, np.float32)), cam)[0]
                img, alpha, shadow = composite_on_wall(view, rng)
                if not det.detect_all(img):
                    continue
                photos.append(img), truths.append(alpha), shadows.append(shadow), used.append(yaw)
            if not photos:
                continue
            times.clear()
            res = track_photos(photos, TrackConfig(size=size, matting=MattingConfig(method=method)), detector=det,
                               names=[f"seed {first_seed + s} yaw {y:.0f}" for y in used])
            for v, yaw in enumerate(used):
                h, w = truths[v].shape
                box = head_crop_box(res.fit.K[v], res.fit.translations[v])
                sh = crop_array(shadows[v][..., None], box, size, [0.0])[..., 0] > 0.1
                valid = crop_array(np.ones((h, w, 1), np.float32), box, size, [0.0])[..., 0] > 0.5
                ta = crop_array(truths[v][..., None], box, size, [0.0])[..., 0]
                rows.append(_scores(first_seed + s, yaw, res.masks[v], ta, sh, valid, times[v]))
    finally:
        pipeline.matte_from_head = orig
    return rows


def evaluate_perturbed(subjects: int = 6, first_seed: int = 1_000_300, yaws=(0.0, 35.0, 70.0), yaw_error_deg: float = 15.0,
                       scale: float = 1.15, method: str = "auto", seed: int = 0, size: int = 256) -> list[dict]:
    """Like :func:`evaluate_matting`, but the head given to the matting is the true one made
    ``scale`` x larger about its centre and turned by ``yaw_error_deg`` (the sign alternates per
    subject): what a fit whose skull is too large and whose yaw is off gives on real photos
    (the back of the head and the neck over the wall). No landmark detector involved."""
    from ..cameras import Cameras
    from ..data.synthetic import SyntheticSubject
    from .crop import crop_array, crop_cameras, head_crop_box
    from .fit import rodrigues
    from .matting import MattingConfig, head_silhouette, matte_from_head

    rng = np.random.default_rng(seed)
    rows = []
    for s in range(subjects):
        sub = SyntheticSubject(first_seed + s)
        faces = sub.model.visible_faces(eyelashes=False)
        verts = sub.vertices(np.zeros(53, np.float32)).astype(np.float64)
        centre = verts.mean(0)
        sign = 1.0 if s % 2 == 0 else -1.0
        Rerr = rodrigues(np.radians([0.0, sign * yaw_error_deg, 0.0]))
        wrong = (verts - centre) @ Rerr.T * scale + centre
        for yaw in yaws:
            a = -math.radians(yaw)
            cam = Cameras.look_at([math.sin(a), -0.03, math.cos(a)], fov_deg=40.0, width=384, height=512).flatten()
            view = sub.render(sub.frame(np.zeros(53, np.float32)), cam)[0]
            img, alpha, shadow = composite_on_wall(view, rng)
            w2c = cam.w2c[0].double().numpy()
            R, t, K = w2c[:3, :3], w2c[:3, 3], cam.K[0].double().numpy()
            box = head_crop_box(K, t)
            Kc = crop_cameras(cam, box, size).K[0].double().numpy()
            crop = crop_array(img, box, size, [0, 0, 0])
            valid = crop_array(np.ones((*alpha.shape, 1), np.float32), box, size, [0.0])[..., 0] > 0.5
            sil = head_silhouette(wrong, faces, R, t, Kc, size)
            lm = (sub.model.landmarks(wrong) @ R.T + t) @ Kc.T
            lm = lm[:, :2] / lm[:, 2:]
            t0 = time.perf_counter()
            m = matte_from_head(crop, sil, Kc[0, 0] / t[2], lm[57, 1], valid, MattingConfig(method=method), face_points=lm)
            dt = time.perf_counter() - t0
            ta = crop_array(alpha[..., None], box, size, [0.0])[..., 0]
            sh = crop_array(shadow[..., None], box, size, [0.0])[..., 0] > 0.1
            rows.append(_scores(first_seed + s, yaw, m, ta, sh, valid, dt))
    return rows


def _scores(seed, yaw, m, ta, sh, valid, dt) -> dict:
    p, t = m > 0.5, ta > 0.5
    return {
        "seed": seed, "yaw": yaw,
        "iou": float((p & t).sum() / max((p | t).sum(), 1)),
        "leak": float((p & ~t).sum() / max(p.sum(), 1)),
        "shadow_kept": float((p & sh & ~t).sum() / max((sh & ~t & valid).sum(), 1)),
        "miss": float((t & ~p).sum() / max(t.sum(), 1)),
        "mae": float(np.abs(m - ta)[valid].mean()),
        "seconds": float(dt),
    }  # fmt: skip


def wall_like_fraction(img: np.ndarray, mask: np.ndarray, valid: np.ndarray, silhouette: np.ndarray, face: np.ndarray,
                       px_per_m: float, delta_e: float = 6.0) -> float:
    """Leak score of a mask on a real crop (no true alpha): the fraction of the mask (> 0.5) outside
    the fitted face region whose CIELAB colour is within ``delta_e`` of some background sample.
    Background samples: photo pixels (``valid``) within 6 px of the photo's edge in the crop or of
    the crop's top and side edges, in the upper 55 % of the crop, and more than 5 cm from the
    fitted ``silhouette`` (so hair touching the edge is not a sample). Uses neither the mask's
    classifier nor its trimap. ``img [S, S, 3]`` uint8, others ``[S, S]``."""
    import cv2
    from scipy.spatial import cKDTree

    s = img.shape[0]
    lab = cv2.cvtColor(img.astype(np.float32) / 255.0, cv2.COLOR_RGB2LAB)
    edge = np.zeros((s, s), bool)
    edge[:6], edge[:, :6], edge[:, -6:] = True, True, True
    edge |= valid & ~ndimage.binary_erosion(valid, iterations=6)
    far = ndimage.distance_transform_edt(silhouette <= 0.5) > 0.05 * px_per_m
    ref = edge & valid & far
    ref[int(0.55 * s):] = False
    m = mask > 0.5
    test = m & ~face
    if not ref.any() or not test.any():
        return 0.0
    d, _ = cKDTree(lab[ref][::2]).query(lab[test], k=1)
    return float((d < delta_e).sum() / max(m.sum(), 1))


def evaluate_realsets(methods=("auto",), root: Path | None = None) -> list[dict]:
    """Per real photo (``tracking.realsets.realsets_root()``; tracked set by set): for each matting
    method the wall-like fraction (:func:`wall_like_fraction`), the mask's share of the crop and the
    matting time."""
    from . import matting, pipeline
    from .realsets import _read, realsets_root
    from .pipeline import TrackConfig, track_photos

    root = Path(root) if root is not None else realsets_root()
    rows = []
    calls = []
    orig = pipeline.matte_from_head

    def spy(img, sil, ppm, mouth, valid=None, config=None, face_points=None):
        calls.append((img, sil, ppm, mouth, valid, face_points))
        return orig(img, sil, ppm, mouth, valid, config, face_points=face_points)

    pipeline.matte_from_head = spy
    try:
        for d in sorted(p for p in root.iterdir() if p.is_dir()):
            paths = sorted(p for p in d.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
            calls.clear()
            track_photos([_read(p) for p in paths], TrackConfig(), names=[f"{d.name}/{p.name}" for p in paths])
            for p, (img, sil, ppm, mouth, valid, fp) in zip(paths, calls):
                face = matting.face_region(fp, img.shape[0])
                row = {"set": d.name, "photo": p.name}
                for mth in methods:
                    t0 = time.perf_counter()
                    m = matting.matte_from_head(img, sil, ppm, mouth, valid, matting.MattingConfig(method=mth), face_points=fp)
                    row[f"{mth}_s"] = time.perf_counter() - t0
                    row[f"{mth}_wall"] = wall_like_fraction(img, m, valid, sil, face, ppm)
                    row[f"{mth}_area"] = float((m > 0.5).mean())
                rows.append(row)
    finally:
        pipeline.matte_from_head = orig
    return rows


def matting_table(rows: list[dict]) -> str:
    """Markdown: per yaw the means (and the worst view's IoU / leak), then all views."""
    out = ["| yaw | views | IoU mean (min) | leak mean (max) | shadow kept mean (max) | miss mean | alpha MAE | matting s (median) |",
           "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for y in sorted({r["yaw"] for r in rows}) + [None]:
        rs = [r for r in rows if y is None or r["yaw"] == y]
        if not rs:
            continue
        g = lambda k: np.array([r[k] for r in rs])  # noqa: E731
        out.append(f"| {'all' if y is None else f'{y:.0f}'} | {len(rs)} | {g('iou').mean():.3f} ({g('iou').min():.3f}) | "
                   f"{g('leak').mean():.3f} ({g('leak').max():.3f}) | {g('shadow_kept').mean():.3f} ({g('shadow_kept').max():.3f}) | "
                   f"{g('miss').mean():.3f} | {g('mae').mean():.3f} | {np.median(g('seconds')):.2f} |")  # fmt: skip
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m fastgha_core.tracking.matting_eval", description=__doc__.split("\n")[0])
    p.add_argument("--subjects", type=int, default=6)
    p.add_argument("--first-seed", type=int, default=1_000_300, help="first held-out synthetic seed")
    p.add_argument("--method", default="auto", help="MattingConfig.method")
    p.add_argument("--seed", type=int, default=0, help="walls and shadows")
    p.add_argument("--perturbed", action="store_true",
                   help="instead of tracking: the true head made 15%% larger and turned 15 degrees (evaluate_perturbed)")
    p.add_argument("--json", default=None, help="also write the rows here")
    p.add_argument("--realsets", action="store_true",
                   help="instead: the real photo sets (../shared/realsets), per photo the wall-like fraction of each --method (comma-separated)")
    a = p.parse_args(argv)
    if a.realsets:
        from .realsets import realsets_root

        if not realsets_root().is_dir():
            print(f"no real photo sets under {realsets_root()}: nothing to evaluate")
            return 0
        methods = a.method.split(",")
        rows = evaluate_realsets(methods)
        print("| set | photo | " + " | ".join(f"{m} wall-like / area / s" for m in methods) + " |")
        print("|---|---|" + "---|" * len(methods))
        for r in rows:
            print(f"| {r['set']} | {r['photo']} | " + " | ".join(f"{r[m + '_wall']:.3f} / {r[m + '_area']:.2f} / {r[m + '_s']:.2f}" for m in methods) + " |")
        for m in methods:
            w = np.array([r[m + "_wall"] for r in rows])
            print(f"{m}: wall-like mean {w.mean():.3f}, max {w.max():.3f}; matting s median {np.median([r[m + '_s'] for r in rows]):.3f}")
        if a.json:
            Path(a.json).write_text(json.dumps(rows, indent=1))
        return 0
    if a.perturbed:
        rows = evaluate_perturbed(a.subjects, a.first_seed, method=a.method, seed=a.seed)
        how = "true head x1.15, turned 15 degrees"
    else:
        rows = evaluate_matting(a.subjects, a.first_seed, method=a.method, seed=a.seed)
        how = "tracked with MediaPipe landmarks"
    print(f"{a.subjects} held-out synthetic subjects from seed {a.first_seed} ({how}), method {a.method!r}")
    print(matting_table(rows))
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
