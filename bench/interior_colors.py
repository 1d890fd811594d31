"""How bright the synthetic renderer shows the inside of an open mouth, against the prior's interior colours (issue 16).

For training subjects (seeds 0..N-1, never the held-out ones): the ground-truth mesh's shaded vertex
colours at ``jawOpen`` = 1 (``SyntheticSubject.frame``: its albedo under that subject's lights) at the
vertices the mouth interior puts Gaussians on, per class (teeth, gums/tongue, socket), and the colours
``model.prior`` gives those Gaussians. Prints, per class, the mean Rec. 601 luma of both, the ratio
truth / ours, and the ratio truth / bare colours (ours without ``INTERIOR_SHADE``): the latter is
what ``INTERIOR_SHADE`` is set from.

Then the teeth as the renderer *shows* them once the lips part off them (``jawOpen`` +
``mouthUpperUp_L/R`` + ``mouthLowerDown_L/R`` = 1, frontal 512², the mesh rasterizer's teeth pixels less
a 1-pixel rim): the mean luma of the brightest 30% of those pixels and their hue (RGB over luma),
against ``model.prior``'s front-teeth colour (``TEETH_FRONT_LUMA`` is set from the former).

    python bench/interior_colors.py --subjects 30
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/, for _bench_cli

from _bench_cli import training_subjects_args, write_json


def interior_luma(seeds) -> dict[str, dict[str, float]]:
    """``{class: {"truth": luma, "ours": luma, "bare": luma}}`` averaged over the subjects of ``seeds``."""
    from fastgha_core.data.appearance import head_regions
    from fastgha_core.data.headmodel import HeadModel
    from fastgha_core.data.synthetic import TRAIN_SEEDS, SyntheticSubject
    from fastgha_core.model import prior as P

    hm = HeadModel.load()
    b = P.load_basis("ict53")
    reg = head_regions(hm)
    m0 = b.interior_group == 0
    ids = b.interior_vertices[m0]
    ours = b.interior_colors[m0].astype(np.float64)
    teeth = b.interior_scale[m0] == P.TEETH_SCALE
    gums = ~teeth & (reg.gums[ids] > 0)
    classes = {"teeth": (teeth, 0), "gums+tongue": (gums, 1), "socket": (~teeth & ~gums, 2)}
    luma = np.array([0.299, 0.587, 0.114])
    z = np.zeros(hm.num_expression, np.float32)
    z[hm.expression_names.index("jawOpen")] = 1.0
    acc = {k: [] for k in classes}
    for seed in seeds:
        if int(seed) not in TRAIN_SEEDS:
            raise ValueError(f"interior colours are measured on training subjects only, got seed {seed}")
        c = SyntheticSubject(int(seed), hm).frame(z).colors[ids].astype(np.float64)
        for k, (m, _) in classes.items():
            acc[k].append((c[m] @ luma).mean())
    out = {}
    for k, (m, j) in classes.items():
        o = float((ours[m] @ luma).mean())
        out[k] = {"truth": float(np.mean(acc[k])), "ours": o, "bare": o / P.INTERIOR_SHADE[j]}
    return out


def visible_teeth(seeds, resolution: int = 512) -> dict[str, float | list[float]]:
    """``{"luma": mean over subjects of the brightest 30% teeth pixels' mean luma, "chroma": [3] their hue
    (RGB over luma), "subjects": how many showed >= 20 teeth pixels, "ours_luma", "ours_chroma"}``
    for the training ``seeds`` (see the module doc). Raises ``ValueError`` for a held-out seed."""
    import torch
    from scipy.ndimage import binary_erosion

    from fastgha_core.cameras import Cameras
    from fastgha_core.data.appearance import head_regions
    from fastgha_core.data.headmodel import HeadModel
    from fastgha_core.data.meshraster import render_mesh
    from fastgha_core.data.synthetic import FOV_DEG, TRAIN_SEEDS, SyntheticSubject
    from fastgha_core.model import prior as P

    hm = HeadModel.load()
    reg = head_regions(hm)
    luma = np.array([0.299, 0.587, 0.114])
    z = np.zeros(hm.num_expression, np.float32)
    for n in ("jawOpen", "mouthUpperUp_L", "mouthUpperUp_R", "mouthLowerDown_L", "mouthLowerDown_R"):
        z[hm.expression_names.index(n)] = 1.0
    cam = Cameras.look_at(torch.tensor([[0.0, 0.0, 1.0]]), torch.zeros(1, 3), fov_deg=FOV_DEG, width=resolution, height=resolution)
    w2c, K = cam.w2c.reshape(4, 4).double().numpy(), cam.K.reshape(3, 3).double().numpy()
    flag = (reg.teeth > 0).astype(np.float64)[:, None]
    lum, chroma = [], []
    for seed in seeds:
        if int(seed) not in TRAIN_SEEDS:
            raise ValueError(f"interior colours are measured on training subjects only, got seed {seed}")
        subj = SyntheticSubject(int(seed), hm)
        img = subj.render(subj.frame(z), cam)[0].image.float().clamp(0, 1).permute(1, 2, 0).numpy().astype(np.float64)
        v = subj.vertices(z).astype(np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
        teeth = binary_erosion(render_mesh(v, subj.faces, flag, K, resolution, resolution, 1, None).color[..., 0] > 0.5, iterations=1)
        if teeth.sum() < 20:
            continue
        px = img[teeth]
        bright = px[px @ luma >= np.percentile(px @ luma, 70)].mean(0)
        lum.append(float(bright @ luma))
        chroma.append(bright / float(bright @ luma))
    ours = P.teeth_front_color().astype(np.float64)
    return {
        "luma": float(np.mean(lum)) if lum else float("nan"),
        "chroma": np.mean(chroma, 0).tolist() if chroma else [],
        "subjects": len(lum),
        "ours_luma": float(ours @ luma),
        "ours_chroma": (ours / float(ours @ luma)).tolist(),
    }


def main(argv=None) -> int:
    a = training_subjects_args(__doc__, argv)
    res = interior_luma(range(a.subjects))
    print("| class | truth luma | ours | truth / ours | truth / bare colours |\n|---|---:|---:|---:|---:|")
    for k, r in res.items():
        print(f"| {k} | {r['truth']:.3f} | {r['ours']:.3f} | {r['truth'] / r['ours']:.2f} | {r['truth'] / r['bare']:.2f} |")
    vis = visible_teeth(range(a.subjects))
    print(
        f"\nteeth shown with the lips parted ({vis['subjects']} subjects): brightest 30% luma {vis['luma']:.3f} "
        f"(ours at the front: {vis['ours_luma']:.3f}), hue {np.round(vis['chroma'], 3).tolist()} (ours: {np.round(vis['ours_chroma'], 3).tolist()})"
    )
    write_json(a.json, {**res, "teeth_shown": vis})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
