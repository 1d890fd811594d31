"""Input-view reproduction of a request folder: reconstruct, optionally refine, render every input view
at its own camera with its own expression, and compare inside its mask.

``python -m fastgha_core.refine.measure [--input FOLDER] [--steps N]`` prints one JSON line per run.
The request folder is the layout ``fastgha reconstruct --input`` reads (images sorted by name,
``<name>_mask.png``, ``cameras.json``) plus ``info.json`` with the inputs' ``expressions`` (the
shipped synthetic sample has it); without ``info.json`` the canonical avatar is rendered undeformed.
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path

import torch

from ..cameras import Cameras, load_request_folder
from . import RefineConfig, masked_psnr, prepare_targets, refine_avatar

SAMPLE_REQUEST = Path(__file__).resolve().parent.parent / "assets" / "samples" / "synth_1000000" / "request"


def read_request(folder: str | Path):
    """``(images [V, 3, H, W] uint8, masks [V, H, W] uint8 | None, cameras [V], expressions [V, E] | None)``."""
    import numpy as np
    from PIL import Image

    paths, cams = load_request_folder(folder)
    imgs, masks = [], []
    for p in paths:
        with Image.open(p) as im:
            imgs.append(torch.from_numpy(np.asarray(im.convert("RGB")).copy()).permute(2, 0, 1))
        mp = p.with_name(p.stem + "_mask.png")
        if mp.exists():
            with Image.open(mp) as im:
                masks.append(torch.from_numpy(np.asarray(im.convert("L")).copy()))
    info = Path(folder) / "info.json"
    expr = None
    if info.exists():
        data = json.loads(info.read_text())
        if "expressions" in data:
            expr = torch.tensor(data["expressions"], dtype=torch.float32)
    return torch.stack(imgs), (torch.stack(masks) if len(masks) == len(imgs) else None), Cameras.stack([c.flatten()[0] for c in cams]), expr


def render_inputs(model, avatar, cams: Cameras, expressions, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Render ``avatar`` at ``cams [V]`` (resized to ``size``) with each view's expression: rgb, alpha.
    Each view is drawn as a frame at that camera (``animate(..., camera=)``: the view-dependent blending
    of avatars on a tracked head; network-depth avatars ignore the camera)."""
    from ..constants import BACKGROUND_RGB
    from ..render import render

    rgbs, alphas = [], []
    cams = cams.resize(size, size) if (cams.width, cams.height) != (size, size) else cams
    for i in range(len(cams.K)):
        g = model.animate(avatar, expressions[i], camera=cams[i : i + 1]) if expressions is not None else avatar.gaussians
        out = render(g, cams[i : i + 1], background=BACKGROUND_RGB)
        rgbs.append(out.rgb[0].clamp(0, 1))
        alphas.append(out.alpha[0])
    return torch.stack(rgbs), torch.stack(alphas)


def reproduce(model, folder: str | Path, steps: int, resolution: int = 256, config: RefineConfig | None = None, surface: str = "none") -> dict:
    """Masked PSNR of every input view rendered at its own camera; refinement with ``steps`` steps.

    ``masked_psnr`` renders at the corrected cameras (the ones the refined avatar was fitted to),
    ``masked_psnr_given_cameras`` at the cameras of the request. ``surface``: ``"tracked"`` puts
    the Gaussians on the head fitted to the photos through the request's cameras
    (``tracking.pipeline.track_known_cameras``; the network's depth when that fails, and
    ``"surface"`` in the result says so), ``"none"`` keeps the network's depth.
    """
    images, masks, cams, expr = read_request(folder)
    imgs, in_cams = model.prepare(list(images), [cams[i : i + 1] for i in range(len(cams.K))], None if masks is None else list(masks))
    t0 = time.perf_counter()
    head, used = None, "none"
    if surface != "none":
        from ..train.evaluate import fit_input_surface

        head, fit = fit_input_surface(images, cams, masks=masks)
        used = surface if head is not None else f"none ({fit})"
    t_fit = time.perf_counter() - t0
    avatar = model.reconstruct(imgs, in_cams, expressions=expr if expr is not None and expr.shape[-1] == model.config.expression_dim else None, surface=head, surface_mode="blend" if surface == "blend" else "replace")
    t_rec = time.perf_counter() - t0 - t_fit
    cfg = copy.deepcopy(config) if config is not None else RefineConfig()
    cfg.steps = steps
    res = refine_avatar(model, avatar, images, cams, masks, config=cfg, expressions=expr)
    targets, tmasks, tcams = prepare_targets(images, cams, masks, resolution)
    _, _, ecams = prepare_targets(images, res.cameras, masks, resolution)
    pred, _ = render_inputs(model, res.avatar, ecams, expr, resolution)
    ps = masked_psnr(pred, targets, tmasks)
    pred_given, _ = render_inputs(model, res.avatar, tcams, expr, resolution)
    ps_given = masked_psnr(pred_given, targets, tmasks)
    return {
        "folder": str(folder),
        "steps": steps,
        "surface": used,
        "resolution": resolution,
        "masked_psnr": float(ps.mean()),
        "per_view": [round(float(x), 2) for x in ps],
        "masked_psnr_given_cameras": float(ps_given.mean()),
        "surface_fit_s": round(t_fit, 3),
        "reconstruct_s": round(t_rec, 3),
        "refine_s": round(res.timings["total"], 3),
        "refine_opt_s": round(res.timings["optimize"], 3),
        "gaussians": len(res.avatar),
        "rot_deg": [round(float(r.norm()) * 57.2958, 2) for r in res.rotations],
        "trans_mm": [round(float(t.norm()) * 1000, 1) for t in res.translations],
        "_pred": pred,
        "_targets": targets,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--input", default=str(SAMPLE_REQUEST))
    ap.add_argument("--model", default="tiny")
    ap.add_argument("--steps", default="0,40", help="comma-separated step counts")
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--refine-resolution", type=int, default=None, help="RefineConfig.resolution (default: the preset's)")
    ap.add_argument("--coarse-resolution", type=int, default=None)
    ap.add_argument("--coarse-fraction", type=float, default=None)
    ap.add_argument("--set", action="append", default=[], help="RefineConfig field=value (repeatable)")
    ap.add_argument("--surface", default="none", choices=["tracked", "blend", "none"], help="none (default): the network's depth; tracked: Gaussians on the head fitted through the request's photos, masks and cameras; blend: that head on the face only")
    ap.add_argument("--picture", default=None, help="write a grid picture (targets, then one row per step count) here")
    args = ap.parse_args(argv)
    from ..model.fastgha import load_model

    torch.manual_seed(0)
    model = load_model(args.model)
    cfg = RefineConfig()
    for name, val in (("resolution", args.refine_resolution), ("coarse_resolution", args.coarse_resolution), ("coarse_fraction", args.coarse_fraction)):
        if val is not None:
            setattr(cfg, name, val)
    for kv in args.set:
        k, v = kv.split("=", 1)
        setattr(cfg, k, type(getattr(cfg, k))(v) if not isinstance(getattr(cfg, k), bool) else v.lower() in ("1", "true"))
    rows = []
    for s in [int(x) for x in args.steps.split(",")]:
        r = reproduce(model, args.input, s, args.resolution, config=cfg, surface=args.surface)
        if not rows:
            rows.append(list(r["_targets"]))
        rows.append(list(r["_pred"]))
        print(json.dumps({k: v for k, v in r.items() if not k.startswith("_")}), flush=True)
    if args.picture:
        from ..train.visualize import save_grid

        save_grid(Path(args.picture), rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
