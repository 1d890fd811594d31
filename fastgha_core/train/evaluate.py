"""Held-out evaluation (paper §4.4): novel views and novel expressions from 4 inputs per subject
taken at different expressions.

Protocol per subject (one ``SequenceSource``), deterministic given ``EvalConfig.seed``:

1. input cameras: ``num_inputs`` cameras by farthest-viewpoint sampling over the camera centres;
2. input timesteps: ``num_inputs`` timesteps by farthest-point sampling in expression space (so the
   4 inputs show different expressions), input ``i`` = (timestep ``i``, camera ``i``);
3. target timesteps (novel expressions): ``num_target_timesteps`` of the remaining timesteps,
   evenly spaced in the order of expression strength ``||z||`` (from the mildest to the strongest);
4. target cameras (novel views): ``num_target_views`` of the remaining cameras by farthest-viewpoint
   sampling (when there are no cameras left, the input cameras are reused and the report says so).

Every (target timestep, target camera) pair is one evaluated image: the avatar reconstructed once
from the inputs is animated with the target expression and rendered over ``BACKGROUND_RGB`` at the
model's render size; the ground truth (already over the same background) is centre-cropped and
resized to that size. Metrics: PSNR, SSIM, LPIPS (when weights are given), CSIM and AKD (when dlib is
installed); unavailable metrics are null, never approximated. The "strong expression" subset is the
target timesteps whose ``||z||`` lies at or above the ``strong_quantile`` of the subject's sequence.

Input depth (``EvalConfig.surface``): ``none`` (the network's per-pixel depth), ``tracked`` (every input
pixel's Gaussian on the head fitted to the input photos and masks through their known cameras,
``tracking.pipeline.track_known_cameras``; never the ground-truth mesh) or ``blend`` (that head on
the face only, ``model.surface.blend_network_depth``). The report gives per subject the fit's
landmark RMS and, for synthetic sources, its distance to the true mesh (``surface_error_mm``).

Ablations (``EvalConfig.ablation``):

- ``none``: the model as trained;
- ``static``: the canonical Gaussians rendered without deformation (no animation at all);
- ``no-features``: the deformation MLP runs with every per-Gaussian feature set to zero. For a model
  trained *with* features this is an inference-time knock-out, not the paper's retrained
  "w/o per-Gaussian features" ablation: it measures how much the trained deformation relies on the
  features (a large drop means animation uses them), and it is expected to be worse than a model
  retrained without features.
- ``no-prior``: for a model with the expression prior, the deformation MLP's residual alone (the
  prior's head-surface displacement left out; the same avatar otherwise).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Sequence

import torch
from torch import Tensor

from ..cameras import Cameras, farthest_viewpoint_sampling
from ..constants import BACKGROUND_RGB

__all__ = ["EvalConfig", "ABLATIONS", "SURFACES", "fit_input_surface", "METRICS", "select_protocol", "evaluate", "fit_square", "write_report", "markdown_table"]

log = logging.getLogger(__name__)

ABLATIONS = ("none", "static", "no-features", "no-prior")
SURFACES = ("tracked", "blend", "none")
METRICS = ("psnr", "ssim", "lpips", "csim", "akd")


@dataclass
class EvalConfig:
    num_inputs: int = 4  # input images per subject (paper: 4)
    num_target_timesteps: int = 4  # novel expressions per subject
    num_target_views: int = 4  # novel cameras per expression
    strong_quantile: float = 0.75  # ||z|| quantile (within the sequence) of the strong-expression subset
    ablation: str = "none"  # "none" | "static" | "no-features"
    seed: int = 0  # the protocol's random choices (first camera)
    backend: str = "auto"  # render backend
    grid_subjects: int = 4  # subjects shown in the comparison grid
    resolution: int = 0  # side of the rendered/ground-truth target images (0 = the model's render_size)
    refine_steps: int = 0  # test-time refinement (fastgha_core.refine) against the inputs; 0 = off
    refine_cameras: bool = False  # let the refinement correct the (exact) input cameras
    # "tracked": every input pixel's Gaussian goes on the head fitted to the input photos through
    # their known cameras (tracking.pipeline.track_known_cameras; model/surface.py); "blend": that
    # head on the face only; "none" (default): the network's per-pixel depth. "blend" is within
    # 0.2 dB of "none" on held-out subjects (+0.11 on one draw, -0.16 on another) and "tracked" 1.5 dB
    # below it (docs/model-card-log.md, "Known cameras: one fitted head instead of the network's depth"). The fitted modes fall back to "none" per subject when no input photo gives
    # landmarks (or the faces extra is missing) and the report counts it.
    surface: str = "none"
    surface_outline: bool = True  # the input masks' outlines join the known-camera fit (profiles without landmarks too)

    def __post_init__(self) -> None:
        if self.ablation not in ABLATIONS:
            raise ValueError(f"ablation must be one of {list(ABLATIONS)}, got {self.ablation!r}")
        if self.surface not in SURFACES:
            raise ValueError(f"surface must be one of {list(SURFACES)}, got {self.surface!r}")
        if self.num_inputs < 1 or self.num_target_timesteps < 1 or self.num_target_views < 1:
            raise ValueError(f"num_inputs, num_target_timesteps and num_target_views must be >= 1, got {self.num_inputs}, {self.num_target_timesteps}, {self.num_target_views}")


@dataclass
class Protocol:
    input_timesteps: list[int]
    input_cameras: list[int]
    target_timesteps: list[int]
    target_cameras: list[int]
    strong_timesteps: list[int]
    reused_input_cameras: bool


def _farthest(points: Tensor, k: int, start: int) -> list[int]:  # points [N, D] -> k indices
    k = min(k, points.shape[0])
    chosen = [start]
    d = (points - points[start]).norm(dim=-1)
    while len(chosen) < k:
        nxt = int(torch.argmax(d))
        if d[nxt] <= 0 and len(set(chosen)) == points.shape[0]:
            break
        chosen.append(nxt)
        d = torch.minimum(d, (points - points[nxt]).norm(dim=-1))
    return chosen


def select_protocol(source, cfg: EvalConfig) -> Protocol:
    """The input and target (timestep, camera) choice for one subject (see module docstring)."""
    T, C = int(source.num_timesteps), int(source.num_cameras)
    if T < 2:
        raise ValueError(f"{source.subject}/{source.sequence}: evaluation needs >= 2 timesteps (inputs and novel expressions), got {T}")
    g = torch.Generator().manual_seed(cfg.seed)
    centers = source.cameras(0).centers.reshape(-1, 3).float()  # [C, 3]
    n_in = min(cfg.num_inputs, C)
    in_cams = farthest_viewpoint_sampling(centers, n_in, start=None, generator=g)
    exprs = torch.stack([source.expression(t).float() for t in range(T)])  # [T, E]
    norms = exprs.norm(dim=-1)  # [T]
    n_in_t = min(cfg.num_inputs, T - 1)
    in_ts = _farthest(exprs, n_in_t, start=int(torch.argmin(norms)))
    while len(in_ts) < len(in_cams):  # fewer timesteps than inputs: repeat expressions
        in_ts.append(in_ts[len(in_ts) % max(1, n_in_t)])
    in_cams = in_cams[: len(in_ts)]
    rest_t = [t for t in range(T) if t not in set(in_ts)]
    rest_t.sort(key=lambda t: (float(norms[t]), t))
    n_t = min(cfg.num_target_timesteps, len(rest_t))
    pick = sorted({round(i * (len(rest_t) - 1) / max(1, n_t - 1)) for i in range(n_t)}) if n_t > 1 else [len(rest_t) - 1]
    tgt_ts = [rest_t[i] for i in pick]
    rest_c = [c for c in range(C) if c not in set(in_cams)]
    reused = not rest_c
    if reused:
        rest_c = list(range(C))
    sub = centers[rest_c]
    idx = farthest_viewpoint_sampling(sub, min(cfg.num_target_views, len(rest_c)), start=0)
    tgt_cams = [rest_c[i] for i in idx]
    if len(tgt_ts) < cfg.num_target_timesteps or len(tgt_cams) < cfg.num_target_views:
        log.warning("%s/%s: %d of %d target expressions and %d of %d target views (the sequence has %d timesteps and %d cameras, "
                    "%d of each taken by the inputs)", source.subject, source.sequence, len(tgt_ts), cfg.num_target_timesteps,
                    len(tgt_cams), cfg.num_target_views, T, C, len(in_cams))
    thr = float(torch.quantile(norms, cfg.strong_quantile))
    strong = [t for t in tgt_ts if float(norms[t]) >= thr]
    return Protocol(in_ts, in_cams, tgt_ts, tgt_cams, strong, reused)


def fit_square(image: Tensor, cams: Cameras, size: int) -> tuple[Tensor, Cameras]:
    """Centre-crop ``image [N, C, H, W]`` to a square and resize it to ``size``; the cameras follow."""
    H, W = image.shape[-2:]
    s = min(H, W)
    left, top = (W - s) // 2, (H - s) // 2
    if (H, W) != (s, s):
        image = image[..., top : top + s, left : left + s]
        cams = cams.crop(left, top, s, s)
    if s != size:
        image = torch.nn.functional.interpolate(image, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
        cams = cams.resize(size, size)
    return image, cams


def _cameras_at(source, pairs: Sequence[tuple[int, int]]) -> Cameras:
    Ks, w2cs = [], []
    for t, c in pairs:
        cam = source.cameras(t)
        Ks.append(cam.K.reshape(-1, 3, 3)[c])
        w2cs.append(cam.w2c.reshape(-1, 4, 4)[c])
    first = source.cameras(pairs[0][0])
    return Cameras(torch.stack(Ks).float(), torch.stack(w2cs).float(), first.width, first.height)


def fit_input_surface(images: Tensor, cameras: Cameras, detector=None, masks: Tensor | None = None):
    """The head fitted to a subject's input photos through their known cameras, or None.

    ``images [V, 3, H, W]`` in [0, 1] with ``cameras [V]`` of that size, optional ``masks [V, 1, H, W]``
    (their outlines join the fit for turned views). Returns
    ``(model.surface.HeadSurface, tracking.fit.KnownCameraFit)``, or ``(None, reason)`` when the
    ``faces`` extra is missing or no photo gives usable landmarks (the caller then keeps the
    network's depth)."""
    from ..tracking.faces import FacesUnavailableError
    from ..tracking.pipeline import track_known_cameras

    try:
        return track_known_cameras(images, cameras, detector=detector, masks=masks)
    except FacesUnavailableError as e:
        return None, f"faces extra missing: {e}"
    except ValueError as e:
        return None, str(e)


def surface_error_mm(source, timesteps: Sequence[int], surface) -> dict[str, float] | None:
    """Mean distance (mm) between the fitted head and a synthetic subject's true mesh at each input's
    timestep (world frame; all vertices and the face mesh's), or None for a source without truth."""
    import numpy as np

    subj = getattr(source, "synthetic_subject", None)
    if subj is None or surface is None:
        return None
    allv, face = [], []
    for i, t in enumerate(timesteps):
        d = np.linalg.norm(surface.vertices(i, subj.model) - subj.vertices(source.expressions[t]), axis=1) * 1000.0
        allv.append(float(d.mean()))
        face.append(float(d[:9409].mean()))  # the face mesh (data/headmodel.py: face 0-9408)
    return {"all_mm": float(np.mean(allv)), "face_mm": float(np.mean(face))}


def _mean(values: list[float | None]) -> float | None:
    vals = [v for v in values if v is not None and math.isfinite(v)]
    return float(sum(vals) / len(vals)) if vals else None


def _summarise(rows: list[dict[str, Any]], available: dict[str, bool]) -> dict[str, Any]:
    out: dict[str, Any] = {m: (_mean([r[m] for r in rows]) if available[m] else None) for m in METRICS}
    out["num_images"] = len(rows)
    return out


@torch.no_grad()
def evaluate(
    model,
    sources: Sequence,
    config: EvalConfig | None = None,
    lpips=None,
    faces=None,
    out_dir: str | Path | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Evaluate ``model`` (a ``FastGHA``) on held-out ``sources``; returns the report dict (see
    :func:`write_report`). ``lpips``: an ``LPIPS`` module or None; ``faces``: ``FaceMetrics`` or None.
    With ``out_dir`` the comparison grid is written to ``out_dir/comparison.png``."""
    from tqdm.auto import tqdm

    from ..render import render
    from .metrics import psnr, ssim
    from .visualize import error_map, save_grid

    cfg = config or EvalConfig()
    device = next(model.parameters()).device
    size = int(cfg.resolution or model.config.render_size)
    available = {"psnr": True, "ssim": True, "lpips": lpips is not None, "csim": faces is not None, "akd": faces is not None}
    all_rows: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    grid_rows: list[list[Tensor | None]] = []
    face_skipped = 0
    surface_fallbacks = 0
    detector = None
    if cfg.surface != "none":
        try:
            from ..tracking.faces import load_face_detector

            detector = load_face_detector()
        except ImportError as e:  # FacesUnavailableError: every subject falls back (counted below)
            log.warning("no face detector (%s): every subject uses the network's depth", e)
    for source in tqdm(list(sources), desc="eval", disable=not progress):
        proto = select_protocol(source, cfg)
        pairs = list(zip(proto.input_timesteps, proto.input_cameras))
        views = [source.view(t, c) for t, c in pairs]
        images = torch.stack([v.image for v in views]).float()  # [V, 3, H, W]
        masks = torch.stack([v.mask for v in views]).float()  # [V, 1, H, W]
        in_imgs, in_cams = model.prepare(images, _cameras_at(source, pairs), masks=masks)
        # the inputs' known expressions (synthetic / tracked): a model with the expression prior undoes them
        in_expr = torch.stack([source.expression(t).float() for t, _ in pairs])
        in_expr = in_expr if in_expr.shape[-1] == model.config.expression_dim else None
        surface, surface_info = None, None
        if cfg.surface != "none":
            surface, fit = fit_input_surface(images, _cameras_at(source, pairs), detector=detector, masks=masks if cfg.surface_outline else None)
            if surface is None:
                surface_fallbacks += 1
                log.warning("%s: no fitted head (%s); using the network's depth", source.subject, fit)
                surface_info = {"fitted": False, "reason": fit}
            else:
                surface_info = {
                    "fitted": True,
                    "views_with_landmarks": int(fit.detected.sum()),
                    "landmark_rms_px": [None if not math.isfinite(x) else round(float(x), 2) for x in fit.rms_px],
                    "error": surface_error_mm(source, proto.input_timesteps, surface),
                }
        mode = "blend" if cfg.surface == "blend" else "replace"
        avatar = model.reconstruct(in_imgs.to(device), in_cams.to(device), expressions=in_expr, surface=surface, surface_mode=mode)
        if cfg.refine_steps > 0:
            from ..refine import RefineConfig, refine_avatar

            rcfg = RefineConfig(steps=cfg.refine_steps, optimize_cameras=cfg.refine_cameras)
            avatar = refine_avatar(model, avatar, images, _cameras_at(source, pairs), masks, config=rcfg, expressions=in_expr).avatar
        if cfg.ablation == "no-features":
            from ..model.avatar import CanonicalAvatar

            g = avatar.gaussians
            avatar = CanonicalAvatar(g.replace(features=torch.zeros_like(g.features)), avatar.model_name, avatar.expression_space, avatar.prior, avatar.num_interior)
        rows: list[dict[str, Any]] = []
        shown = False
        for t in proto.target_timesteps:
            expr = source.expression(t).float().to(device)
            if cfg.ablation == "static":
                gauss = model.static_gaussians(avatar)
            else:
                gauss = model.animate(avatar, expr, prior=cfg.ablation != "no-prior")
            tpairs = [(t, c) for c in proto.target_cameras]
            gt = torch.stack([source.view(t, c).image for c in proto.target_cameras]).float()  # [S, 3, H, W]
            gt, cams = fit_square(gt, _cameras_at(source, tpairs), size)
            if cfg.ablation != "static" and model.config.gaussians.view_blend_tau_deg > 0 and avatar.view_blend is not None:
                # view blending weights opacities per render camera (model/viewblend.py): one render each,
                # of the same deformed Gaussians
                cams_d = cams.to(device)
                pred = torch.cat([
                    render(model.blend_views(avatar, gauss, cams_d[i : i + 1], expr), cams_d[i : i + 1], background=BACKGROUND_RGB, backend=cfg.backend).rgb
                    for i in range(len(cams))
                ]).float().cpu().clamp(0, 1)
            else:
                pred = render(gauss, cams.to(device), background=BACKGROUND_RGB, backend=cfg.backend).rgb.float().cpu().clamp(0, 1)
            gt = gt.clamp(0, 1)
            p_vals, s_vals = psnr(pred, gt).tolist(), ssim(pred, gt).tolist()
            l_vals = lpips(pred.to(device), gt.to(device)).cpu().tolist() if lpips is not None else [None] * len(gt)
            for j, c in enumerate(proto.target_cameras):
                csim = akd = None
                if faces is not None:
                    csim, akd = faces.compare(pred[j], gt[j])
                    face_skipped += csim is None
                rows.append(
                    {
                        "timestep": t,
                        "camera": c,
                        "strong": t in proto.strong_timesteps,
                        "expression_norm": float(source.expression(t).float().norm()),
                        "psnr": p_vals[j],
                        "ssim": s_vals[j],
                        "lpips": l_vals[j],
                        "csim": csim,
                        "akd": akd,
                    }
                )
            if not shown and (t == proto.target_timesteps[-1]) and len(grid_rows) < cfg.grid_subjects:
                ins = [fit_square(images[i : i + 1], _cameras_at(source, [pairs[i]]), size)[0][0] for i in range(len(pairs))]
                grid_rows.append([*ins, gt[0], pred[0], error_map(pred[0], gt[0])])
                shown = True
        subj = {
            "subject": source.subject,
            "sequence": source.sequence,
            "protocol": asdict(proto),
            "surface": surface_info,
            **_summarise(rows, available),
            "strong": _summarise([r for r in rows if r["strong"]], available),
            "images": rows,
        }
        subjects.append(subj)
        all_rows += rows
    if out_dir is not None and grid_rows:
        n_in = max(len(r) for r in grid_rows) - 3
        titles = [f"input {i + 1}" for i in range(n_in)] + ["ground truth", "FastGHA", "|error| 0-0.25"]
        save_grid(Path(out_dir) / "comparison.png", grid_rows, titles=titles)
    return {
        "summary": {m: _summarise(all_rows, available)[m] for m in METRICS},
        "strong_expression": _summarise([r for r in all_rows if r["strong"]], available),
        "num_images": len(all_rows),
        "num_subjects": len(subjects),
        "ablation": cfg.ablation,
        "config": asdict(cfg),
        "available": available,
        "face_images_skipped": face_skipped if faces is not None else None,
        "surface_fallbacks": surface_fallbacks if cfg.surface != "none" else None,
        "grid_columns": [f"input {i}" for i in range(cfg.num_inputs)] + ["ground truth", "ours", "error"],
        "subjects": subjects,
    }


def _fmt(v: float | None, digits: int = 3) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


def markdown_table(report: dict[str, Any]) -> str:
    """Summary, strong-expression subset and per-subject rows as a markdown table."""
    head = "| subset | images | PSNR ↑ | SSIM ↑ | LPIPS ↓ | CSIM ↑ | AKD ↓ |\n|---|---:|---:|---:|---:|---:|---:|\n"

    def line(name: str, s: dict[str, Any], n: int) -> str:
        return f"| {name} | {n} | {_fmt(s['psnr'], 2)} | {_fmt(s['ssim'])} | {_fmt(s['lpips'])} | {_fmt(s['csim'])} | {_fmt(s['akd'], 2)} |\n"

    body = line("all", report["summary"], report["num_images"])
    body += line("strong expressions", report["strong_expression"], report["strong_expression"]["num_images"])
    for s in report["subjects"]:
        body += line(f"{s['subject']}/{s['sequence']}", s, s["num_images"])
    surf = report.get("config", {}).get("surface", "none")
    note = f", input depth: `{surf}`" + (f" ({report['surface_fallbacks']} subject(s) fell back to the network's)" if report.get("surface_fallbacks") else "")
    return f"Ablation: `{report['ablation']}`{note}\n\n" + head + body


def write_report(report: dict[str, Any], json_path: str | Path | None = None, out_dir: str | Path | None = None) -> str:
    """Write the JSON (``json_path``) and ``out_dir/eval.md``; return the markdown table."""
    md = markdown_table(report)
    if json_path is not None:
        p = Path(json_path)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(json.dumps(report, indent=2))
    if out_dir is not None:
        d = Path(out_dir)
        d.mkdir(parents=True, exist_ok=True)
        (d / "eval.md").write_text(md)
        if json_path is None:
            (d / "eval.json").write_text(json.dumps(report, indent=2))
    return md
