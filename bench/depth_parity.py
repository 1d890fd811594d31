"""The shipped sample's per-view depth maps: row alternation and cross-view disagreement (issue 17).

For each model (a preset name or a model folder), reconstructs the demo's subject
(``synth_1000000``, its 4 request photos and cameras, as ``fastgha demo`` does) and reports, per
input view, over the view's foreground (``foreground_weight > 0.5``):

- the mean amplitude (mm) of the row-alternating part of the depth along each pixel's ray
  (``model.gaussian_head.row_parity``, sigma 2 px) and of the column-alternating part;
- the mean absolute depth step (mm) between neighbouring rows and between neighbouring columns;

and the cross-view disagreement: each view's foreground points (opacity > 0.3) projected into each
other view, the median |distance from that camera - that view's own depth at the pixel| (mm) over
the points within 3 cm of it (farther ones are taken as occluded), per ordered pair.
With ``--truth N`` also, on ``N`` training samples drawn from the held-out subjects 1000000–1000003
(``SyntheticTrainingDataset`` stream 7, one sample per subject block), each input view's depth against
its true depth (``TrainingSample.input_depths``): mean |depth - truth| and the signed mean (mm,
positive = behind the surface) over the foreground, and the one-sided cross-view term
``train.losses.cross_view_depth_loss`` as L1 (mm).
With ``--picture PNG``: the neutral avatar of every model at yaw -30/0/+30 degrees and 30 degrees
above/below (256², 18 degree field of view, one row per model), and ``PNG`` with ``_crop`` before
``.png``: forehead and eyes at yaw -30 degrees, 30 degrees above and below, enlarged 2x.

    python bench/depth_parity.py --model tiny --model RUN/model --picture out/parity.png --json out/parity.json
    python bench/depth_parity.py --model tiny --truth 3
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
VIEWS = (("yaw -30", -30.0, 0.0), ("front", 0.0, 0.0), ("yaw +30", 30.0, 0.0), ("above 30", 0.0, 30.0), ("below 30", 0.0, -30.0))
CROP_VIEWS = ("yaw -30", "above 30", "below 30")


def depth_stats(model, sample) -> dict:
    import numpy as np
    import torch

    from fastgha_core.model.gaussian_head import foreground_weight, row_parity

    images, cams = model.prepare(sample.request_images, sample.request_cameras, sample.request_masks)
    with torch.no_grad():
        (g,) = model.forward_gaussians(images[None].to(model.device), cams[None].to(model.device))
    g = g.to("cpu")
    v, s = len(images), images.shape[-1]
    pts = g.means.view(v, s, s, 3)
    t = (pts - cams.centers[:, None, None]).norm(dim=-1)  # [V, S, S] metres along the rays
    fg = foreground_weight(images) > 0.5
    op = g.opacities.view(v, s, s)
    rows = row_parity(t, fg, 2.0).abs() * 1e3
    cols = row_parity(t.transpose(1, 2), fg.transpose(1, 2), 2.0).abs().transpose(1, 2) * 1e3
    per_view = []
    for i in range(v):
        m = fg[i]
        tm = t[i] * 1e3
        my, mx = m[1:] & m[:-1], m[:, 1:] & m[:, :-1]
        per_view.append(
            {
                "row_alternation_mm": float(rows[i][m].mean()),
                "column_alternation_mm": float(cols[i][m].mean()),
                "row_step_mm": float((tm[1:] - tm[:-1]).abs()[my].mean()),
                "column_step_mm": float((tm[:, 1:] - tm[:, :-1]).abs()[mx].mean()),
            }
        )
    pairs = {}
    for a in range(v):
        for b in range(v):
            if a == b:
                continue
            p = pts[a][fg[a] & (op[a] > 0.3)]
            uv, _ = cams[b : b + 1].project(p[None])
            u, w = uv[0, :, 0].floor().long(), uv[0, :, 1].floor().long()
            ok = (u >= 0) & (u < s) & (w >= 0) & (w < s)
            u, w, p = u[ok], w[ok], p[ok]
            seen = fg[b][w, u] & (op[b][w, u] > 0.3)
            d = (p[seen] - cams.centers[b]).norm(dim=-1) - t[b][w[seen], u[seen]]
            near = d.abs() < 0.03
            pairs[f"{a}->{b}"] = float(d[near].abs().median() * 1e3) if bool(near.any()) else None
    vals = [x for x in pairs.values() if x is not None]
    return {"per_view": per_view, "cross_view_median_mm": pairs, "cross_view_mean_mm": float(np.mean(vals)) if vals else None}


def truth_batches(n: int) -> list:
    """``n`` collated training samples of the held-out subjects 1000000-1000003 (see the module doc)."""
    from fastgha_core.data.sampling import SyntheticTrainingDataset, collate_samples
    from fastgha_core.data.synthetic import HELDOUT_SEEDS

    ds = SyntheticTrainingDataset(HELDOUT_SEEDS[:4], resolution=128, timesteps=16, num_cameras=16, seed=7, samples_per_subject=1)
    return [collate_samples([ds[i]]) for i in range(n)]


def truth_stats(model, batches: list) -> dict:
    """Per sample: mean |depth - truth|, signed mean (mm, > 0 = behind the surface) over the input
    views' foreground, and the one-sided cross-view term as L1 (mm)."""
    import torch

    from fastgha_core.model.gaussian_head import foreground_weight
    from fastgha_core.train.losses import cross_view_depth_loss, input_depth_loss, ray_depth_from_z

    out = {"abs_error_mm": [], "signed_error_mm": [], "cross_view_one_sided_mm": []}
    for b in batches:
        truth = ray_depth_from_z(b.input_depths[:, :, 0], b.input_K)  # [1, V, H, W]
        fg = foreground_weight(b.input_images)
        with torch.no_grad():
            depth = model(b.input_images, b.input_K, b.input_w2c, b.expression, b.input_expressions).view_depth
        m = (fg > 0.5) & (truth > 0)
        out["abs_error_mm"].append(float(input_depth_loss(depth.flatten(0, 1), truth.flatten(0, 1), fg.flatten(0, 1), 0.0)) * 1e3)
        out["signed_error_mm"].append(float((depth - truth)[m].mean()) * 1e3)
        out["cross_view_one_sided_mm"].append(float(cross_view_depth_loss(depth, b.input_K, b.input_w2c, fg, 0.03, 0.0)) * 1e3)
    return out


def render_row(model, sample, label: str):
    import numpy as np
    import torch
    from PIL import Image, ImageDraw

    from fastgha_core.cameras import Cameras
    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.render import render

    images, cams = model.prepare(sample.request_images, sample.request_cameras, sample.request_masks)
    tiles = []
    with torch.no_grad():
        avatar = model.reconstruct(images, cams)
        z = torch.as_tensor(model.expression_space.neutral(), dtype=torch.float32)
        for _, yaw, pitch in VIEWS:
            y, p = math.radians(yaw), math.radians(pitch)
            eye = [math.sin(y) * math.cos(p), math.sin(p), math.cos(y) * math.cos(p)]
            cam = Cameras.look_at(torch.tensor([eye]), fov_deg=18.0, width=256, height=256)
            rgb = render(model.animate(avatar, z, camera=cam), cam, background=torch.tensor(BACKGROUND_RGB)).rgb[0]
            tiles.append((rgb.clamp(0, 1).permute(1, 2, 0).numpy() * 255).astype(np.uint8))
    im = Image.fromarray(np.concatenate(tiles, 1))
    ImageDraw.Draw(im).text((4, 4), label, fill=(0, 0, 0))
    return np.asarray(im)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", action="append", default=None, help="preset name or model folder (repeatable; default tiny)")
    ap.add_argument("--sample", default="synth_1000000", help="shipped sample subject (default: the demo's)")
    ap.add_argument("--picture", default=None, help="write the renders here (PNG) and the crops next to it")
    ap.add_argument("--json", default=None, help="write the figures as JSON here")
    ap.add_argument("--truth", type=int, default=0, help="also compare the input views' depth with the truth on N held-out training samples")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    import numpy as np
    import torch
    from PIL import Image

    from fastgha_core.data.samples import load_sample
    from fastgha_core.model.fastgha import load_model

    torch.manual_seed(0)
    sample = load_sample(args.sample)
    report, rows = {}, []
    batches = truth_batches(args.truth) if args.truth > 0 else []
    for spec in args.model or ["tiny"]:
        model = load_model(spec).eval()
        st = depth_stats(model, sample)
        report[spec] = st
        pv = st["per_view"]
        print(f"{spec}: row alternation " + " / ".join(f"{x['row_alternation_mm']:.2f}" for x in pv) + " mm, columns "
              + " / ".join(f"{x['column_alternation_mm']:.2f}" for x in pv) + " mm; row steps "
              + " / ".join(f"{x['row_step_mm']:.2f}" for x in pv) + " mm, column steps "
              + " / ".join(f"{x['column_step_mm']:.2f}" for x in pv) + f" mm; cross-view {st['cross_view_mean_mm']:.2f} mm")
        if batches:
            tr = truth_stats(model, batches)
            st["truth"] = tr
            f = lambda xs: " / ".join(f"{x:.2f}" for x in xs)  # noqa: E731
            print(f"{spec}: depth - truth {f(tr['abs_error_mm'])} mm, signed {f(tr['signed_error_mm'])} mm; "
                  f"cross-view one-sided {f(tr['cross_view_one_sided_mm'])} mm")
        if args.picture:
            rows.append(render_row(model, sample, Path(spec).name if "/" in spec else spec))
    if args.picture:
        grid = np.concatenate(rows, 0)
        Path(args.picture).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(grid).save(args.picture)
        cols = [i for i, (name, _, _) in enumerate(VIEWS) if name in CROP_VIEWS]
        crops = Image.fromarray(np.concatenate([np.concatenate([r[40:150, i * 256 + 58 : i * 256 + 198] for i in cols], 1) for r in rows], 0))
        crops.resize((crops.width * 2, crops.height * 2), Image.LANCZOS).save(args.picture.replace(".png", "_crop.png"))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
