"""How bright the synthetic renderer shows the inside of an open mouth, against the prior's interior colours (issue 16).

For training subjects (seeds 0..N-1, never the held-out ones): the ground-truth mesh's shaded vertex
colours at ``jawOpen`` = 1 (``SyntheticSubject.frame``: its albedo under that subject's lights) at the
vertices the mouth interior puts Gaussians on, per class (teeth, gums/tongue, socket), and the colours
``model.prior`` gives those Gaussians. Prints, per class, the mean Rec. 601 luma of both, the ratio
truth / ours, and the ratio truth / bare colours (ours without ``INTERIOR_SHADE``): the latter is
what ``INTERIOR_SHADE`` is set from.

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


def main(argv=None) -> int:
    a = training_subjects_args(__doc__, argv)
    res = interior_luma(range(a.subjects))
    print("| class | truth luma | ours | truth / ours | truth / bare colours |\n|---|---:|---:|---:|---:|")
    for k, r in res.items():
        print(f"| {k} | {r['truth']:.3f} | {r['ours']:.3f} | {r['truth'] / r['ours']:.2f} | {r['truth'] / r['bare']:.2f} |")
    write_json(a.json, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
