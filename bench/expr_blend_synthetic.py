"""Expression-aware view blending on synthetic subjects with known truth (``model/viewblend.py``
``ExpressionPenalty``, ``GaussianHeadConfig.view_blend_expr_mm``).

Per held-out synthetic subject and expression kind (``jaw``: jawOpen 0.8; ``smile``: mouthSmile_L/R
0.9 with jawOpen 0.15): four inputs from yaw -25, +25, -65, +65 degrees, ONE of them (+25 for the
1st, 3rd, ... subject, -25 for the others) at that expression and the rest neutral, reconstructed on
the head fitted through them (the tracked-surface path of ``fastgha eval --surface tracked``) with
the inputs' true expressions undone; then frames at the neutral expression and at the input's
expression from yaw 0, +12, -12 and pitch 15 degrees, compared with the truth: mean PSNR over the
image and over a box around the mouth (rows 58-80%, columns 36-64% of the frame) per ``--sigmas``
value (0 = off), per (kind, frame):

    python bench/expr_blend_synthetic.py --sigmas 0,8 --subjects 4
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="tiny", help="preset name or model folder (default: tiny)")
    ap.add_argument("--sigmas", default="0,8", help="comma-separated view_blend_expr_mm values in millimetres, 0 = off (default 0,8)")
    ap.add_argument("--subjects", type=int, default=4, help="held-out synthetic subjects, seeds from 1000000 (default 4)")
    ap.add_argument("--resolution", type=int, default=256, help="input and frame side in pixels (default 256)")
    ap.add_argument("--json", default=None, help="also write the per-subject rows and the means here")
    ap.add_argument("--grid", default=None, help="also write a PNG: per subject, kind and frame the truth then the yaw-0 frame per sigma")
    args = ap.parse_args(argv)
    try:
        sigmas = [float(s) for s in args.sigmas.split(",")]
    except ValueError:
        ap.error(f"--sigmas: expected comma-separated numbers of millimetres (0,8), got {args.sigmas!r}")
    if any(s < 0 for s in sigmas) or args.subjects < 1 or args.resolution < 64:
        ap.error(f"expected --sigmas >= 0, --subjects >= 1 and --resolution >= 64, got {args.sigmas!r}, {args.subjects}, {args.resolution}")
    sys.path.insert(0, str(REPO))
    import fastgha_core  # noqa: F401  (first: its thread settings must precede torch's import, fastgha_core/perf.py)
    import numpy as np
    import torch

    from fastgha_core.cameras import Cameras
    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.data.synthetic import CAMERA_DISTANCE, FOV_DEG, SyntheticSubject
    from fastgha_core.expressions import ICT53_NAMES
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.render import render
    from fastgha_core.tracking.faces import load_face_detector
    from fastgha_core.train.evaluate import fit_input_surface

    r = args.resolution
    model = load_model(args.model)
    gc = model.config.gaussians
    detector = load_face_detector()

    def cams_at(yaw_pitch):
        eye = [[math.cos(math.radians(p)) * math.sin(math.radians(y)), math.sin(math.radians(p)), math.cos(math.radians(p)) * math.cos(math.radians(y))] for y, p in yaw_pitch]
        return Cameras.look_at(torch.tensor(eye) * CAMERA_DISTANCE, fov_deg=FOV_DEG, width=r, height=r)

    def expression(kind):
        z = np.zeros(len(ICT53_NAMES), np.float32)
        if kind == "jaw":
            z[ICT53_NAMES.index("jawOpen")] = 0.8
        else:
            z[ICT53_NAMES.index("mouthSmile_L")] = z[ICT53_NAMES.index("mouthSmile_R")] = 0.9
            z[ICT53_NAMES.index("jawOpen")] = 0.15
        return z

    def psnr(a, b):
        return float(-10 * torch.log10(((a - b) ** 2).mean().clamp_min(1e-10)))

    in_cams = cams_at([(-25, 0), (25, 0), (-65, 0), (65, 0)])
    tg_cams = cams_at([(0, 0), (12, 0), (-12, 0), (0, 15)])
    mouth = (slice(None), slice(int(r * 0.58), int(r * 0.80)), slice(int(r * 0.36), int(r * 0.64)))
    saved = gc.view_blend_expr_mm
    rows, tiles = [], []
    try:
        for si in range(args.subjects):
            seed = 1000000 + si
            subj = SyntheticSubject(seed)
            for kind in ("jaw", "smile"):
                ez, e0 = expression(kind), np.zeros(len(ICT53_NAMES), np.float32)
                which = 1 if si % 2 == 0 else 0
                ins = [ez if i == which else e0 for i in range(4)]
                views = [subj.render(subj.frame(e), in_cams[i : i + 1])[0] for i, e in enumerate(ins)]
                images = torch.stack([v.image for v in views]).float()
                masks = torch.stack([v.mask for v in views]).float()
                surface, fit = fit_input_surface(images, in_cams, detector=detector, masks=masks)
                if surface is None:
                    print(f"{seed} {kind}: no fitted head ({fit}); skipped", flush=True)
                    continue
                imgs, cams = model.prepare(images, in_cams, masks=masks)
                avatar = model.reconstruct(imgs, cams, expressions=torch.from_numpy(np.stack(ins)), surface=surface)
                for frame, e in (("neutral", e0), (kind, ez)):
                    truth = [subj.render(subj.frame(e), tg_cams[j : j + 1])[0].image.float().clamp(0, 1) for j in range(len(tg_cams))]
                    shown = [truth[0]]
                    for sg in sigmas:
                        gc.view_blend_expr_mm = sg
                        whole, box = [], []
                        for j in range(len(tg_cams)):
                            pred = render(model.animate(avatar, torch.from_numpy(e), camera=tg_cams[j : j + 1]), tg_cams[j : j + 1], background=BACKGROUND_RGB).rgb[0].clamp(0, 1)
                            whole.append(psnr(pred, truth[j]))
                            box.append(psnr(pred[mouth], truth[j][mouth]))
                            if j == 0:
                                shown.append(pred)
                        rows.append({"seed": seed, "kind": kind, "expressive_input": which, "frame": frame, "sigma_mm": sg, "psnr": float(np.mean(whole)), "mouth_psnr": float(np.mean(box))})
                    print(seed, kind, frame, " ".join(f"sigma {x['sigma_mm']:g}: {x['psnr']:.2f} / mouth {x['mouth_psnr']:.2f}" for x in rows[-len(sigmas) :]), flush=True)
                    tiles.append(torch.cat(shown, 2))
    finally:
        gc.view_blend_expr_mm = saved
    means = {}
    for x in rows:
        means.setdefault(f"{x['kind']} input, {'neutral' if x['frame'] == 'neutral' else 'its'} frame, sigma {x['sigma_mm']:g}", []).append((x["psnr"], x["mouth_psnr"]))
    summary = {k: {"psnr": float(np.mean([a for a, _ in v])), "mouth_psnr": float(np.mean([b for _, b in v]))} for k, v in means.items()}
    for k, v in summary.items():
        print(f"{k}: PSNR {v['psnr']:.3f}, mouth {v['mouth_psnr']:.3f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "means": summary}, indent=1))
    if args.grid and tiles:
        from PIL import Image

        Image.fromarray((torch.cat(tiles, 1).permute(1, 2, 0).numpy() * 255).astype(np.uint8)).save(args.grid)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
