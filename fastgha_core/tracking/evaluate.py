"""Accuracy of the landmark fitter on synthetic observations where the truth is known.

``python -m fastgha_core.tracking.evaluate [--renders 48] [--views 4] [--noise-px 1.5] [--seed 0]``

Each synthetic subject has a random identity (all 100 ICT modes ~ N(0, 1), while the fitter only
estimates the first ``num_identity``: a deliberate model mismatch), ``--views`` photos with random
sparse expressions (3-5 active ict53 shapes, weights U(0.2, 0.9)) and random head poses (yaw
+-35, pitch +-15, roll +-10 degrees, distance 0.6-1.2 m, offsets +-5 cm) seen by a 512 x 512
camera with a 25-degree field of view (known to the fitter). The observations are the projected
68 landmark vertices plus Gaussian pixel noise (``--noise-px``): this measures the fitter alone,
not dlib (the detector is exercised on a real photo in the tests).

Reported per render: rotation error (geodesic angle, degrees), translation error (mm; split into
the lateral x/y part and the relative depth error in %: from one photo, head size and distance are
ambiguous, and the identity prior picks an average-sized head, so depth errors of a few percent
are the expected floor), expression
MAE over the 53 weights, and the expression geometry error: RMS over the face vertices of the
displacement ``B_e (e_fit - e_true)`` in mm (blendshapes are redundant, so this is the error that
matters for driving); the same for the neutral guess ``e = 0`` is the baseline.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np

from .fit import FRONTAL_R, FitConfig, LandmarkModel, default_intrinsics, fit_landmarks, rodrigues

__all__ = ["evaluate", "random_subject", "rotation_error_deg"]

FACE_VERTICES = (0, 9409)  # ICT face region (vertex ids), for the expression geometry error
# the known expressions of ``evaluate_renders(expressions=...)`` / ``--known-expressions``
KNOWN_EXPRESSIONS = {"neutral": {}, "smile": {"mouthSmile_L": 0.6, "mouthSmile_R": 0.6}, "jawOpen": {"jawOpen": 0.4}}


def rotation_error_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra @ Rb.T) - 1.0) / 2.0
    return math.degrees(math.acos(float(np.clip(c, -1.0, 1.0))))


def random_subject(rng: np.random.Generator, views: int, size: int = 512, fov_deg: float = 25.0,
                   max_yaw: float = 35.0, max_pitch: float = 15.0, yaws: tuple[float, ...] | None = None):
    """Truth for one subject: identity [100], expressions [V, 53], R [V, 3, 3], t [V, 3], K [3, 3].

    Yaw uniform in +-``max_yaw`` (or ``yaws[v]`` when given), pitch in +-``max_pitch``, roll +-10 degrees.
    """
    beta = rng.normal(size=100)
    E = np.zeros((views, 53))
    for v in range(views):
        k = rng.integers(3, 6)
        E[v, rng.choice(53, k, replace=False)] = rng.uniform(0.2, 0.9, k)
    R = np.stack([
        FRONTAL_R @ rodrigues(np.radians([rng.uniform(-max_pitch, max_pitch), rng.uniform(-max_yaw, max_yaw) if yaws is None else yaws[v], 0.0]))
        @ rodrigues(np.radians([0.0, 0.0, rng.uniform(-10, 10)]))
        for v in range(views)
    ])
    t = np.stack([np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(0.6, 1.2)]) for _ in range(views)])
    return beta, E, R, t, default_intrinsics(size, size, fov_deg)


def evaluate(renders: int = 48, views: int = 4, noise_px: float = 1.5, seed: int = 0, config: FitConfig | None = None,
             layout: str = "dlib68", max_yaw: float = 35.0, max_pitch: float = 15.0, yaws: tuple[float, ...] | None = None) -> dict:
    """Fit ``renders`` synthetic photos (``views`` per subject); per-render error arrays (module doc).

    ``layout``: the landmark points observed ("dlib68" or "mediapipe", see ``fit.LandmarkModel``);
    points whose normal faces away from the camera are observed too (as the Face Mesh does) but with
    the same noise. Also returns ``rel_rot_deg`` (error of the rotation between every pair of photos of
    one subject) and ``expr_abs [renders, 53]`` (absolute error per ict53 shape).
    """
    from ..data.headmodel import HeadModel

    # the observations are the map's own vertices, so the detector models (the yaw-dependent map, the yaw prior) are off
    cfg = config or FitConfig(yaw_map=False, yaw_prior=False)
    head = HeadModel.load()
    truth_model = LandmarkModel.from_head_model(head, num_identity=head.num_identity, layout=layout)
    fit_model = LandmarkModel.from_head_model(head, num_identity=cfg.num_identity, layout=layout)
    Bf = head.expression_basis[:, FACE_VERTICES[0] : FACE_VERTICES[1]].reshape(53, -1).astype(np.float64).T  # [3Nf, 53]
    nf = Bf.shape[0] // 3
    rng = np.random.default_rng(seed)
    out = {k: [] for k in ("rot_deg", "trans_mm", "lateral_mm", "depth_pct", "expr_mae", "expr_geom_mm", "expr_geom_neutral_mm", "rms_px", "expr_abs")}
    rel = []
    n_subjects = math.ceil(renders / views)
    t0 = time.perf_counter()
    for _ in range(n_subjects):
        beta, E, R, t, K = random_subject(rng, views, max_yaw=max_yaw, max_pitch=max_pitch, yaws=yaws)
        obs = []
        for v in range(views):
            P = truth_model.points(beta, E[v]) @ R[v].T + t[v]
            uv = P @ K.T
            obs.append(uv[:, :2] / uv[:, 2:] + rng.normal(scale=noise_px, size=(truth_model.num_points, 2)))
        res = fit_landmarks(np.stack(obs), K, cfg, fit_model)
        for v in range(views):
            d = res.expressions[v] - E[v]
            out["rot_deg"].append(rotation_error_deg(res.rotations[v], R[v]))
            out["trans_mm"].append(1000.0 * float(np.linalg.norm(res.translations[v] - t[v])))
            out["lateral_mm"].append(1000.0 * float(np.linalg.norm(res.translations[v, :2] - t[v, :2])))
            out["depth_pct"].append(100.0 * abs(float(res.translations[v, 2] / t[v, 2] - 1.0)))
            out["expr_mae"].append(float(np.abs(d).mean()))
            out["expr_geom_mm"].append(1000.0 * float(np.sqrt(((Bf @ d) ** 2).sum() / nf)))
            out["expr_geom_neutral_mm"].append(1000.0 * float(np.sqrt(((Bf @ E[v]) ** 2).sum() / nf)))
            out["rms_px"].append(float(res.rms_px[v]))
            out["expr_abs"].append(np.abs(d))
            for w in range(v + 1, views):
                rel.append(rotation_error_deg(res.rotations[w] @ res.rotations[v].T, R[w] @ R[v].T))
    res = {k: np.asarray(v[:renders]) for k, v in out.items()}
    res["rel_rot_deg"] = np.asarray(rel)
    res["seconds_per_subject"] = (time.perf_counter() - t0) / n_subjects
    return res


def summary_table(r: dict) -> str:
    rows = ["| metric | median | mean | p90 | max |", "|---|---|---|---|---|"]
    rows[0] = "| metric | median | mean | p90 | p95 | max |"
    rows[1] = "|---|---|---|---|---|---|"
    for k in ("rot_deg", "rel_rot_deg", "trans_mm", "lateral_mm", "depth_pct", "expr_mae", "expr_geom_mm", "expr_geom_neutral_mm", "rms_px"):
        a = r[k]
        rows.append(f"| {k} | {np.median(a):.3f} | {a.mean():.3f} | {np.percentile(a, 90):.3f} | {np.percentile(a, 95):.3f} | {a.max():.3f} |")
    return "\n".join(rows)


def expression_table(r: dict, top: int = 53) -> str:
    """Mean absolute error per ict53 shape (largest first)."""
    from ..expressions import ICT53_NAMES

    m = r["expr_abs"].mean(0)
    order = np.argsort(-m)[:top]
    return "\n".join(["| shape | mean abs error |", "|---|---|"] + [f"| {ICT53_NAMES[k]} | {m[k]:.3f} |" for k in order])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m fastgha_core.tracking.evaluate", description=__doc__.split("\n")[0])
    p.add_argument("--renders", type=int, default=48)
    p.add_argument("--views", type=int, default=4)
    p.add_argument("--noise-px", type=float, default=1.5)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--layout", default="mediapipe", choices=("mediapipe", "dlib68"), help="landmark points observed")
    p.add_argument("--max-yaw", type=float, default=75.0, help="yaw uniform in +-this (degrees)")
    p.add_argument("--max-pitch", type=float, default=30.0, help="pitch uniform in +-this (degrees)")
    p.add_argument("--yaws", default=None, help="comma-separated fixed yaw per view instead (e.g. 0,30,60)")
    p.add_argument("--per-shape", action="store_true", help="also print the expression error per ict53 shape")
    p.add_argument("--through-detector", type=int, default=0, metavar="SUBJECTS",
                   help="instead: render this many synthetic heads at --yaws (default 0,30,60) and track them with MediaPipe")
    p.add_argument("--json", default=None, help="also write the per-render errors here")
    p.add_argument("--photo-align", action="store_true", help="with --through-detector: also register the poses photometrically (photoalign.py)")
    p.add_argument("--pitches", default=None, help="with --through-detector: also render every yaw at these pitches (comma-separated degrees, + = nose up)")
    p.add_argument("--known-expressions", action="store_true",
                   help="with --through-detector: neutral, smile (mouthSmile_L/R 0.6) and jawOpen 0.4 instead of random codes, one joint fit per expression and yaw over the pitches")
    p.add_argument("--no-pitch-map", action="store_true", help="fit with the pitch-0 row of the pose map only (FitConfig.pitch_map=False)")
    p.add_argument("--pitch-map-min", type=float, default=None, help="FitConfig.pitch_map_min_deg (default 0: the pitched-down rows unused)")
    a = p.parse_args(argv)
    if a.through_detector:
        yaws = tuple(float(x) for x in (a.yaws or "0,30,60").split(","))
        align = None
        if a.photo_align:
            from .photoalign import PhotoAlignConfig

            align = PhotoAlignConfig()
        try:
            pitches = tuple(float(x) for x in a.pitches.split(",")) if a.pitches else (0.0,)
        except ValueError:
            p.error(f"--pitches: expected comma-separated degrees (e.g. --pitches=-30,0,30), got {a.pitches!r}")
        cfg = FitConfig(pitch_map=not a.no_pitch_map)
        if a.pitch_map_min is not None:
            if a.pitch_map_min > cfg.pitch_map_max_deg:
                p.error(f"--pitch-map-min must not exceed FitConfig.pitch_map_max_deg ({cfg.pitch_map_max_deg:g}), got {a.pitch_map_min:g}")
            cfg.pitch_map_min_deg = a.pitch_map_min
        r = evaluate_renders(a.through_detector, yaws, a.seed, align=align, pitches=pitches, config=cfg,
                             expressions=KNOWN_EXPRESSIONS if a.known_expressions else None)  # fmt: skip
        print(f"{a.through_detector} synthetic subjects rendered at yaw {yaws}, pitch {pitches}, MediaPipe landmarks, one joint fit per subject"
              + (" and expression" if a.known_expressions else "") + (", poses registered photometrically" if align else ""))  # fmt: skip
        print(renders_table(r))
        if len(pitches) > 1 or a.known_expressions:
            print(pitch_table(r))
            print(f"all views: |pitch err| mean {np.abs(r['pitch_err_deg']).mean():.2f}, |yaw err| mean {np.abs(r['yaw_err_deg']).mean():.2f}, "
                  f"expr geometry {r['expr_geom_mm'].mean():.2f} mm, MAE {r['expr_abs'].mean():.3f}, largest code error mean {r['expr_abs'].max(1).mean():.2f}")
        if align is not None:
            print(alignment_table(r))
        if a.per_shape:
            print(expression_table(r))
        return 0
    yaws = tuple(float(x) for x in a.yaws.split(",")) if a.yaws else None
    views = len(yaws) if yaws else a.views
    r = evaluate(a.renders, views, a.noise_px, a.seed, layout=a.layout, max_yaw=a.max_yaw, max_pitch=a.max_pitch, yaws=yaws)
    print(f"{a.renders} renders ({a.layout}), {views} views per subject, yaw {yaws or f'+-{a.max_yaw}'}, pitch +-{a.max_pitch}, "
          f"noise {a.noise_px} px, {r['seconds_per_subject']:.2f} s per subject fit")  # fmt: skip
    print(summary_table(r))
    if a.per_shape:
        print(expression_table(r))
    if a.json:
        with open(a.json, "w") as f:
            json.dump({k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in r.items()}, f)
    return 0




def evaluate_renders(subjects: int = 6, yaws: tuple[float, ...] = (0.0, 30.0, 60.0), seed: int = 0, size: int = 512,
                     fov_deg: float = 25.0, first_seed: int = 1_000_200, config: FitConfig | None = None, align=None,
                     pitches: tuple[float, ...] = (0.0,), expressions: dict | None = None) -> dict:
    """Detector + fitter on rendered synthetic heads with known cameras and expression codes.

    Subjects ``first_seed ..`` (held-out synthetic seeds, not the yaw-map calibration ones) are
    rendered (``data/synthetic.py``: procedural skin, hair and lighting) at each yaw of ``yaws``
    (pitch 0, 1 m, ``fov_deg``), each view with its own random sparse expression (3-5 shapes,
    U(0.2, 0.9)); MediaPipe finds the landmarks and one joint fit per subject recovers identity,
    poses and codes with the true ``K``. Returns per view: ``yaw`` (truth), ``rot_deg``,
    ``yaw_err_deg`` (signed, estimate - truth), ``expr_abs [53]``, ``expr_geom_mm`` and the
    neutral baseline ``expr_geom_neutral_mm``; also ``pitch`` (truth, degrees, + = nose up),
    ``pitch_err_deg`` (signed), ``expr_err [53]`` (signed, estimate - truth) and ``expr_name``.

    ``pitches``: every yaw is rendered at each of these pitches too (the camera at elevation
    ``-pitch``, 1 m from the head origin). ``expressions``: ``{name: {ict53 shape: weight}}``
    instead of the random codes: each subject is rendered with each of them at every (yaw, pitch),
    and fitted once per (expression, yaw), jointly over the pitches (a pitched photo set).

    ``align``: a ``photoalign.PhotoAlignConfig``: the landmark fit's poses are then registered
    photometrically (``photoalign.register_photos``, as ``track_photos`` does) and the rotation
    figures are of the registered poses; ``rot_deg_fit`` / ``yaw_err_deg_fit`` keep the landmark
    fit's, ``rel_rot_deg`` / ``rel_rot_deg_fit`` the error of the rotation between every pair of
    views of a subject (both always filled), ``align_s`` the registration's seconds per subject.
    """
    from ..data.headmodel import HeadModel
    from ..data.synthetic import SyntheticSubject
    from ..expressions import ICT53_NAMES
    from .faces import MeshDetector

    head = HeadModel.load()
    det = MeshDetector(min_face_px=1.0)
    model = LandmarkModel.from_head_model(head, num_identity=50, layout="mediapipe")
    Bf = head.expression_basis[:, FACE_VERTICES[0] : FACE_VERTICES[1]].reshape(53, -1).astype(np.float64).T
    nf = Bf.shape[0] // 3
    rng = np.random.default_rng(seed)
    out = {k: [] for k in ("yaw", "rot_deg", "yaw_err_deg", "expr_abs", "expr_geom_mm", "expr_geom_neutral_mm", "rot_deg_fit",
                           "yaw_err_deg_fit", "rel_rot_deg", "rel_rot_deg_fit", "align_s", "pitch", "pitch_err_deg", "expr_err",
                           "expr_name")}  # fmt: skip
    groups = [(None, tuple(yaws))] if expressions is None else [(n, (y,)) for n in expressions for y in yaws]
    for s in range(subjects):
        sub = SyntheticSubject(first_seed + s)
        for name, group_yaws in groups:
            _renders_group(sub, name, None if name is None else expressions[name], group_yaws, pitches, rng, det, size, fov_deg,
                           model, config, align, Bf, nf, out, ICT53_NAMES)  # fmt: skip
    return {k: np.asarray(v) for k, v in out.items()}


def _renders_group(sub, name, codes, yaws, pitches, rng, det, size, fov_deg, model, config, align, Bf, nf, out, names) -> None:
    """One joint fit of ``sub`` rendered at every (yaw, pitch) (``evaluate_renders``); appends to ``out``."""
    from ..cameras import Cameras
    from .realsets import head_angles_deg

    lms, Ks, Rt, Et, ims = [], [], [], [], []
    frame = None
    if codes is not None:
        e_fixed = np.zeros(53)
        for k, v in codes.items():
            e_fixed[names.index(k)] = v
        frame = sub.frame(e_fixed.astype(np.float32))
    for yaw in yaws:
        for pitch in pitches:
            if codes is None:
                e = np.zeros(53)
                k = rng.integers(3, 6)
                e[rng.choice(53, k, replace=False)] = rng.uniform(0.2, 0.9, k)
            else:
                e = e_fixed
            cam = Cameras.facing_head(yaw, pitch, fov_deg=fov_deg, size=size)  # + pitch: the camera below the head, nose up
            fr = frame if frame is not None else sub.frame(e.astype(np.float32))
            img = (sub.render(fr, cam)[0].image.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
            faces = det.detect_all(img)
            if not faces:
                continue
            lms.append(faces[0][1][det.index])
            ims.append(img)
            Ks.append(cam.K[0].double().numpy())
            Rt.append(cam.w2c[0, :3, :3].double().numpy())
            Et.append((yaw, e))
    if not lms:
        return
    res = fit_landmarks(np.stack(lms), np.stack(Ks), config or FitConfig(), model)
    Rfit = res.rotations.copy()
    if align is not None and len(lms) > 1:
        from .fit import landmark_models
        from .photoalign import register_photos

        al = register_photos(ims, res.identity, res.expressions, res.rotations, res.translations, res.K, align, landmarks=lms,
                             landmark_model=landmark_models(model, res.rotations, config or FitConfig()))  # fmt: skip
        res.rotations, res.translations = al.rotations, al.translations
        out["align_s"].append(al.seconds)
    for a in range(len(Et)):
        for b in range(a + 1, len(Et)):
            truth = Rt[b] @ Rt[a].T
            out["rel_rot_deg"].append(rotation_error_deg(res.rotations[b] @ res.rotations[a].T, truth))
            out["rel_rot_deg_fit"].append(rotation_error_deg(Rfit[b] @ Rfit[a].T, truth))
    for v, (yaw, e) in enumerate(Et):
        d = res.expressions[v] - e
        out["yaw"].append(yaw)
        out["pitch"].append(head_angles_deg(Rt[v])[1])
        out["pitch_err_deg"].append(head_angles_deg(res.rotations[v])[1] - head_angles_deg(Rt[v])[1])
        out["expr_err"].append(d)
        out["expr_name"].append(name or "random")
        out["rot_deg"].append(rotation_error_deg(res.rotations[v], Rt[v]))
        out["yaw_err_deg"].append(head_angles_deg(res.rotations[v])[0] - head_angles_deg(Rt[v])[0])
        out["rot_deg_fit"].append(rotation_error_deg(Rfit[v], Rt[v]))
        out["yaw_err_deg_fit"].append(head_angles_deg(Rfit[v])[0] - head_angles_deg(Rt[v])[0])
        out["expr_abs"].append(np.abs(d))
        out["expr_geom_mm"].append(1000.0 * float(np.sqrt(((Bf @ d) ** 2).sum() / nf)))
        out["expr_geom_neutral_mm"].append(1000.0 * float(np.sqrt(((Bf @ e) ** 2).sum() / nf)))


def renders_table(r: dict) -> str:
    """Per yaw: rotation and yaw error, expression geometry vs neutral, and the 5 worst shapes."""
    from ..expressions import ICT53_NAMES

    rows = ["| yaw (deg) | views | rotation err median (deg) | yaw err mean (deg) | expr geometry mm (neutral) | expr MAE | worst shapes (mean abs err) |",
            "|---|---|---|---|---|---|---|"]  # fmt: skip
    for y in np.unique(r["yaw"]):
        k = r["yaw"] == y
        ea = r["expr_abs"][k].mean(0)
        worst = ", ".join(f"{ICT53_NAMES[i]} {ea[i]:.2f}" for i in np.argsort(-ea)[:5])
        rows.append(f"| {y:.0f} | {k.sum()} | {np.median(r['rot_deg'][k]):.2f} | {r['yaw_err_deg'][k].mean():+.2f} | "
                    f"{r['expr_geom_mm'][k].mean():.2f} ({r['expr_geom_neutral_mm'][k].mean():.2f}) | {r['expr_abs'][k].mean():.3f} | {worst} |")  # fmt: skip
    return "\n".join(rows)


def pitch_table(r: dict) -> str:
    """Per expression, yaw and pitch (``evaluate_renders(pitches=...)``): the signed pitch error, the
    expression geometry error and the 4 shapes with the largest mean signed code error."""
    from ..expressions import ICT53_NAMES

    rows = ["| expression | yaw | pitch | views | pitch err mean (min .. max) | expr geometry mm | largest code error, mean of views | shapes (mean signed error) |",
            "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for n in dict.fromkeys(r["expr_name"].tolist()):
        for y in np.unique(r["yaw"]):
            for p in np.unique(np.round(r["pitch"])):
                k = (r["expr_name"] == n) & (r["yaw"] == y) & (np.round(r["pitch"]) == p)
                if not k.any():
                    continue
                pe, E = r["pitch_err_deg"][k], r["expr_err"][k]
                top = np.argsort(-np.abs(E).mean(0))[:4]
                rows.append(f"| {n} | {y:.0f} | {p:+.0f} | {k.sum()} | {pe.mean():+.1f} ({pe.min():+.1f} .. {pe.max():+.1f}) | "
                            f"{r['expr_geom_mm'][k].mean():.2f} | {np.abs(E).max(1).mean():.2f} | "
                            + ", ".join(f"{ICT53_NAMES[i]} {E[:, i].mean():+.2f}" for i in top) + " |")  # fmt: skip
    return "\n".join(rows)


def alignment_table(r: dict) -> str:
    """Rotation errors of the landmark fit against the photometrically registered poses (``evaluate_renders(align=...)``)."""
    rows = ["| yaw (deg) | rotation err median, fit -> registered (deg) | p95 | yaw err mean | ",
            "|---|---|---|---|"]  # fmt: skip
    for y in np.unique(r["yaw"]):
        k = r["yaw"] == y
        rows.append(f"| {y:.0f} | {np.median(r['rot_deg_fit'][k]):.2f} -> {np.median(r['rot_deg'][k]):.2f} | "
                    f"{np.percentile(r['rot_deg_fit'][k], 95):.2f} -> {np.percentile(r['rot_deg'][k], 95):.2f} | "
                    f"{r['yaw_err_deg_fit'][k].mean():+.2f} -> {r['yaw_err_deg'][k].mean():+.2f} |")  # fmt: skip
    a, b = r["rel_rot_deg_fit"], r["rel_rot_deg"]
    rows.append(f"| all pairs, relative rotation | {np.median(a):.2f} -> {np.median(b):.2f} | {np.percentile(a, 95):.2f} -> {np.percentile(b, 95):.2f} | |")
    if len(r["align_s"]):
        rows.append(f"registration: {np.median(r['align_s']):.1f} s per subject (median)")
    return "\n".join(rows)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
