"""How much of the real-set leave-one-out error is input resolution (issue 17), side by side.

For every set of ``$FASTGHA_REALSETS`` or ``../shared/realsets`` (not part of the repository: without
it the script says so and exits 0), tracked once at 256², every photo is left out in turn and the
avatar of the others is rendered at its camera (as ``python -m fastgha_core.refine.realsets``), once
per variant:

- ``photo_via_128``: no avatar: the left-out photo itself shrunk to the model's 128² input and
  enlarged back to 256² (the bound of what a 128² input alone loses);
- ``shipped``: ``model.reconstruct`` as the server does (Gaussians on a 128² grid per view);
- ``g128_photo``: the same Gaussians, each coloured by its source photo at 256² where it projects
  (``model.surface.sample_photo_colours``) instead of the 128² input plus the network's residual;
- ``g256_photo``: Gaussians on a 256² grid per view: the decoder's 128² maps enlarged bilinearly,
  centres on the tracked surface along the 256² pixel rays, colours from the 256² photo;
- ``g256face_photo``: the 256² grid on the bare face only (``SurfaceDepth.face_hit`` at 128²), the
  128² grid elsewhere, colours from the 256² photo;
- ``viewTAU`` (e.g. ``view20``, not a resolution variant): the shipped avatar, each input view's
  Gaussians' opacity multiplied by ``exp(-(a_i - min_j a_j) / TAU)`` at render time, ``a_i`` the
  angle (degrees) between input camera ``i``'s and the render camera's direction from the head;
- ``blendTAU`` (e.g. ``blend20``): the shipped feature (``model/viewblend.py``,
  ``GaussianHeadConfig.view_blend_tau_deg = TAU``): as ``viewTAU`` but the minimum runs over the
  views that see each Gaussian's point (its coverage mask), so regions only far views cover keep
  their best view opaque;

and reports masked PSNR, SSIM, dlib identity distance, HOG/CNN face counts and Gaussian counts.
``--reproduce`` adds the input-view check: the avatar of all of a set's photos, and each photo's own
single-view avatar, rendered at that photo's own camera (does the avatar blur even the views it saw?).
``--frame`` times one served frame (``model.animate`` + ``render`` at 256², medians) of the first
left-out avatar of the first set for each variant, interleaved.

    python bench/realset_resolution.py --grid /tmp/res.png --json /tmp/res.json --reproduce --frame

The grid (per left-out photo: the photo, then each variant) must stay outside the repository.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
VARIANTS = ("shipped", "g128_photo", "g256_photo", "g256face_photo")
# not resolution: the shipped avatar drawn with each input view's Gaussians' opacity times
# exp(-(angle to the render camera - smallest such angle) / tau), tau in degrees ("view20" = 20)
VIEW_WEIGHT_PREFIX = "view"
BLEND_PREFIX = "blend"  # the shipped per-Gaussian normalised weighting, tau in degrees ("blend20")


def _maps(model, imgs, cams):
    """The decoder's raw maps ``[1, V, C, S, S]`` (``FastGHA.forward_gaussians`` up to the head)."""
    import torch

    from fastgha_core.cameras import plucker_rays

    v, _, h, w = imgs.shape
    f_dino, f_enc = model.semantic(imgs), model.colour(imgs)
    p_cam = plucker_rays(cams[None].to(dtype=torch.float32), h // 8, w // 8)
    tokens = torch.cat([f_dino[None], f_enc[None].to(f_dino.dtype), p_cam.to(f_dino.dtype)], dim=2)
    return model.decoder(model.transformer(tokens))


def _grid_gaussians(model, maps, cams_g, imgs_g, surface, hair, margin, photo, photo_cams):
    """Pixel-aligned Gaussians of ``cams_g``' grid, on the tracked surface, coloured from ``photo``,
    with ``reconstruct``'s outline colours, air drop and matte fill (before pruning)."""
    import torch
    import torch.nn.functional as F

    from fastgha_core.model.coverage import fill_coverage
    from fastgha_core.model.gaussian_head import edge_source_index, foreground_weight
    from fastgha_core.model.surface import sample_photo_colours, surface_ray_depth

    v, s = imgs_g.shape[0], imgs_g.shape[-1]
    m = maps if maps.shape[-1] == s else F.interpolate(maps[0], size=(s, s), mode="bilinear", align_corners=False)[None]
    sd = surface_ray_depth(surface, cams_g, hair)
    g = model.head(m, cams_g[None], imgs_g[None], sd.t[None])[0]
    vi = torch.arange(v).repeat_interleave(s * s)
    g = g.replace(colors=sample_photo_colours(g.means, photo_cams, photo, vi))
    src = (edge_source_index(imgs_g, margin).reshape(v, -1) + torch.arange(v)[:, None] * s * s).reshape(-1)
    g = g.replace(colors=g.colors[src], opacities=g.opacities * (~sd.beyond_face).reshape(-1).float())
    g, _ = fill_coverage(g, cams_g, foreground_weight(imgs_g), model.config.gaussians.coverage_target, sd.beyond_face)
    return g, vi, sd


def reconstruct_variant(model, name, imgs128, cams128, photos, photo_cams, expr, surface):
    """The avatar of ``name`` (module doc) from the 128² inputs and their 256² photos."""
    import torch

    from fastgha_core.model.avatar import CanonicalAvatar
    from fastgha_core.model.gaussian_head import foreground_weight
    from fastgha_core.model.surface import fit_hair_thickness

    if name == "shipped" or name.startswith(VIEW_WEIGHT_PREFIX) or name.startswith(BLEND_PREFIX):
        return model.reconstruct(imgs128, cams128, expressions=expr, surface=surface)
    with torch.no_grad():
        gc = model.config.gaussians
        hair = fit_hair_thickness(surface, cams128, foreground_weight(imgs128)) if gc.hair_fit else 0.0
        maps = _maps(model, imgs128, cams128)
        scale = photos.shape[-1] // imgs128.shape[-1]
        if name == "g128_photo":
            g, vi, _ = _grid_gaussians(model, maps, cams128, imgs128, surface, hair, gc.edge_margin_px, photos, photo_cams)
        elif name in ("g256_photo", "g256face_photo"):
            g, vi, _ = _grid_gaussians(model, maps, photo_cams, photos, surface, hair, gc.edge_margin_px * scale, photos, photo_cams)
            if name == "g256face_photo":
                g1, vi1, sd1 = _grid_gaussians(model, maps, cams128, imgs128, surface, hair, gc.edge_margin_px, photos, photo_cams)
                face = sd1.face_hit
                fine = face.repeat_interleave(scale, 1).repeat_interleave(scale, 2).reshape(-1)
                g, vi = type(g).concat([g1[(~face).reshape(-1)], g[fine]]), torch.cat([vi1[(~face).reshape(-1)], vi[fine]])
        else:
            raise ValueError(f"unknown variant {name!r}; expected one of {VARIANTS}")
        keep = g.opacities >= gc.prune_opacity
        g, vi = g[keep], vi[keep]
        prior, n_int = None, 0
        if model.config.deform.prior:
            g, prior, n_int = model.build_prior(g, vi, expr, head_fit=surface.head_fit(model.head_basis()))
        avatar = CanonicalAvatar(g, model.config.name, model.config.expression_space, prior, n_int)
        model._deform_partial(avatar)
        return avatar


def _valid_variant(name: str) -> bool:
    """A name ``--variants`` accepts: one of ``VARIANTS``, or ``view``/``blend`` + a non-negative TAU."""
    for prefix in (VIEW_WEIGHT_PREFIX, BLEND_PREFIX):
        if name.startswith(prefix):
            try:
                return float(name[len(prefix) :]) >= 0
            except ValueError:
                return False
    return name in VARIANTS


def _shipped_like(name: str) -> bool:
    """Variants drawing the shipped avatar (one reconstruction serves them all)."""
    return name == "shipped" or name.startswith(VIEW_WEIGHT_PREFIX) or name.startswith(BLEND_PREFIX)


def _view_index(model):
    """Wrap ``model.build_prior`` so that each reconstruction leaves the source view of its
    reconstructed Gaussians (in order, ``[N_rec]``) in ``model._last_view_index``."""
    orig = model.build_prior

    def build_prior(g, view_index=None, *args, **kwargs):
        model._last_view_index = view_index
        return orig(g, view_index, *args, **kwargs)

    model.build_prior = build_prior


def _view_weighted(g, view_index, in_cams, camera, tau_deg):
    """``g`` with each input view's reconstructed Gaussians' opacity weighted by its camera's angle
    to ``camera`` (module doc, ``viewTAU``)."""
    import torch

    dirs = in_cams.centers.reshape(-1, 3)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    c = camera.centers.reshape(3)
    ang = torch.rad2deg(torch.arccos((dirs @ (c / c.norm())).clamp(-1, 1)))
    w = torch.exp(-(ang - ang.min()) / tau_deg)
    op = g.opacities.clone()
    n = len(view_index)
    op[:n] = op[:n] * w[view_index.long()].to(op)
    return g.replace(opacities=op)


def _score(faces, pred, target, mask, box=None):
    import numpy as np
    import torch

    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.refine.realsets import _count_cnn, _identity
    from fastgha_core.train.faces import to_uint8_hwc
    from fastgha_core.train.metrics import ssim

    bg = torch.tensor(BACKGROUND_RGB).view(1, 3, 1, 1)
    pm, tm = pred * mask + bg * (1 - mask), target * mask + bg * (1 - mask)
    mse = ((pred - target) ** 2 * mask).sum() / (3 * mask.sum())
    t_desc, _, t_box = _identity(faces, to_uint8_hwc(target[0]))
    img = to_uint8_hwc(pred[0])
    p_desc, n, _ = _identity(faces, img, t_box)
    return {
        "psnr": float(-10 * torch.log10(mse)),
        "ssim": float(ssim(pm, tm)[0]),
        "identity": None if p_desc is None or t_desc is None else float(np.linalg.norm(p_desc - t_desc)),
        "hog": n,
        "cnn": _count_cnn(faces, img),
    }


def _table(rows, key):
    import numpy as np

    out = "| set | variant | photos | masked PSNR ↑ | masked SSIM ↑ | identity ↓ (scored) | 1 face HOG | 1 face CNN | Gaussians |\n|---|---|---:|---:|---:|---:|---:|---:|---:|\n"
    for s in sorted({r["set"] for r in rows}):
        for name in dict.fromkeys(r[key] for r in rows):
            rs = [r for r in rows if r["set"] == s and r[key] == name]
            if not rs:
                continue
            ids = [r["identity"] for r in rs if r["identity"] is not None]
            ng = [r["gaussians"] for r in rs if r.get("gaussians")]
            out += (
                f"| {s} | {name} | {len(rs)} | {np.mean([r['psnr'] for r in rs]):.2f} | {np.mean([r['ssim'] for r in rs]):.3f} | "
                f"{np.mean(ids) if ids else float('nan'):.3f} ({len(ids)}) | {sum(r['hog'] == 1 for r in rs)}/{len(rs)} | "
                f"{sum(r['cnn'] == 1 for r in rs)}/{len(rs)} | {int(np.mean(ng)) if ng else '-'} |\n"
            )
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="tiny", help="preset name or model folder (default: tiny)")
    ap.add_argument("--sets", default=None, help="comma-separated set names (default: all)")
    ap.add_argument(
        "--variants",
        default=",".join(VARIANTS),
        help=f"comma-separated: {', '.join(VARIANTS)}, viewTAU or blendTAU (TAU in degrees, e.g. view20, blend20: the shipped "
        f"view blending); default {','.join(VARIANTS)}",
    )
    ap.add_argument("--reproduce", action="store_true", help="also render each set's avatars at their own input cameras")
    ap.add_argument("--frame", action="store_true", help="also time a served frame (animate + render at 256²) per variant")
    ap.add_argument("--json", default=None, help="also write the rows and tables here")
    ap.add_argument("--grid", default=None, help="grid picture (NOT inside the repository)")
    args = ap.parse_args(argv)
    bad = [n for n in args.variants.split(",") if not _valid_variant(n)]
    if bad:
        ap.error(f"--variants: unknown {bad}; expected {', '.join(VARIANTS)}, viewTAU or blendTAU with TAU in degrees (view20, blend20)")
    sys.path.insert(0, str(REPO))
    import fastgha_core  # noqa: F401  (OpenMP defaults before torch)
    import torch
    import torch.nn.functional as F

    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.model.surface import HeadSurface
    from fastgha_core.refine import realsets as rs
    from fastgha_core.render import render
    from fastgha_core.train.faces import load_face_metrics
    from fastgha_core.tracking import track_photos
    from fastgha_core.tracking.pipeline import TrackConfig

    sets = rs.list_sets(rs.realsets_root())
    if args.sets:
        sets = [s for s in sets if s.name in args.sets.split(",")]
    if not sets:
        print(f"no real photo sets under {rs.realsets_root()}: skipped")
        return 0
    model = load_model(args.model)
    faces = load_face_metrics()
    if faces is None:
        print("dlib face models missing (the faces extra): identity is not measured")
        return 1
    faces = rs._load_cnn(faces)
    variants = args.variants.split(",")
    _view_index(model)
    tau0 = model.config.gaussians.view_blend_tau_deg
    model.config.gaussians.view_blend_tau_deg = 0.0  # only the blendTAU variants weight
    bg = torch.tensor(BACKGROUND_RGB).view(1, 3, 1, 1)
    rows, rep_rows, grid, timing = [], [], [], None
    for folder in sets:
        photos, names = rs._load_photos(folder)
        tr = track_photos(photos, TrackConfig(size=256), names=names)
        crops = torch.from_numpy(tr.crops).permute(0, 3, 1, 2).float() / 255.0
        masks = torch.from_numpy(tr.masks)[:, None].float()
        matted = crops * masks + bg * (1 - masks)
        cams, expr, v = tr.cameras, torch.from_numpy(tr.expressions).float(), len(names)
        head = HeadSurface.from_tracking(tr)
        for k in range(v):
            keep = [i for i in range(v) if i != k][: model.config.max_views]
            imgs128, cams128 = model.prepare(matted[keep], cams[keep])
            target, mask = matted[k : k + 1], (masks[k : k + 1] > 0.5).float()
            s = model.config.input_size
            via = F.interpolate(F.interpolate(target, size=(s, s), mode="bilinear", antialias=True, align_corners=False), size=target.shape[-2:], mode="bilinear", align_corners=False)
            row = dict(set=folder.name, left_out=names[k], variant="photo_via_128", gaussians=None, **_score(faces, via, target, mask))
            rows.append(row)
            print(json.dumps(row), flush=True)
            pics = [target[0], via[0]]
            avatars = {}
            for name in variants:
                same = [n for n in avatars if _shipped_like(n)] if _shipped_like(name) else []
                av = avatars[same[0]] if same else reconstruct_variant(model, name, imgs128, cams128, matted[keep], cams[keep], expr[keep], head.subset(keep))
                avatars[name] = av
                if name.startswith(BLEND_PREFIX):
                    model.config.gaussians.view_blend_tau_deg = float(name[len(BLEND_PREFIX) :])
                    g = model.animate(av, expr[k], camera=cams[k : k + 1])
                    model.config.gaussians.view_blend_tau_deg = tau0
                else:
                    g = model.animate(av, expr[k])
                if name.startswith(VIEW_WEIGHT_PREFIX):
                    g = _view_weighted(g, av.view_blend.source_view, cams[keep], cams[k], float(name[len(VIEW_WEIGHT_PREFIX) :]))
                pred = render(g, cams[k : k + 1], background=BACKGROUND_RGB).rgb.clamp(0, 1)
                row = dict(set=folder.name, left_out=names[k], variant=name, gaussians=len(av.gaussians), **_score(faces, pred, target, mask))
                rows.append(row)
                print(json.dumps(row), flush=True)
                pics.append(pred[0])
            grid.append(pics)
            if args.frame and timing is None:
                timing = _frame_times(model, avatars, expr[k], cams[k : k + 1])
                print(json.dumps({"frame_ms": timing}), flush=True)
        if args.reproduce:
            imgs128, cams128 = model.prepare(matted, cams)
            whole = reconstruct_variant(model, "shipped", imgs128, cams128, matted, cams, expr, head)
            for j in range(v):
                single = model.reconstruct(imgs128[j : j + 1], cams128[j : j + 1], expressions=expr[j : j + 1], surface=head.subset([j]))
                for name, av in (("all photos, at an input camera", whole), ("that photo alone, at its camera", single)):
                    pred = render(model.animate(av, expr[j]), cams[j : j + 1], background=BACKGROUND_RGB).rgb.clamp(0, 1)
                    row = dict(set=folder.name, view=names[j], avatar=name, **_score(faces, pred, matted[j : j + 1], (masks[j : j + 1] > 0.5).float()))
                    rep_rows.append(row)
                    print(json.dumps(row), flush=True)
    print(_table(rows, "variant"))
    if rep_rows:
        print(_table(rep_rows, "avatar"))
    if timing:
        print("served frame (animate + render 256², ms, median): " + ", ".join(f"{k} {v:.1f}" for k, v in timing.items()))
    if args.json:
        Path(args.json).write_text(json.dumps({"leave_one_out": rows, "reproduce": rep_rows, "frame_ms": timing}, indent=1))
    if args.grid and grid:
        from fastgha_core.train.visualize import save_grid

        save_grid(Path(args.grid), grid)
    return 0


def _frame_times(model, avatars, expression, camera, rounds: int = 15) -> dict:
    """Median ms of ``animate`` + ``render`` per avatar, interleaved (the first round is a warm-up)."""
    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.render import render

    times = {k: [] for k in avatars}
    for r in range(rounds + 1):
        for name, av in avatars.items():
            t0 = time.perf_counter()
            render(model.animate(av, expression), camera, background=BACKGROUND_RGB)
            if r:
                times[name].append(1000 * (time.perf_counter() - t0))
    return {k: statistics.median(v) for k, v in times.items()}


if __name__ == "__main__":
    raise SystemExit(main())
