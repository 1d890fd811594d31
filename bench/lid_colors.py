"""How dark the synthetic renderer shows a closed upper lid, against the skin the prior colours it from (issue 16).

For training subjects (seeds 0..N-1, never the held-out ones): the ground-truth mesh's shaded vertex
colours (``SyntheticSubject.frame``: its albedo under that subject's lights) at the closed-lid points
of ``model.prior`` (``eyeBlink_L`` = ``eyeBlink_R`` = 1), and the colour ``_lid_skin_colors`` takes for
them from the same mesh at the neutral expression (the brighter half of the skin at the crease and
under the eye, which is what a reconstruction of neutral photos holds there). Prints the Rec. 601
luma ratio truth lid / sampled skin: over all lid points, and per band of how far the blink moves
a point (``BANDS``: the crease, <= 6 mm; 6-8 mm; the lower part over the eye), and the head
model's own Lambert ratio (``prior._brightness`` at the closed lid over that at the sampled skin,
``SHADE_LIGHT``) for the same points. A closed-lid colour factor from these figures (with the lashes
lifted 1.5 mm) was tried and not kept: docs/model-card-log.md, "The closed lid's shade and the lash band".

    python bench/lid_colors.py --subjects 30
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/, for _bench_cli

from _bench_cli import training_subjects_args, write_json


# Bands of how far the blink moves a lid point (metres): the crease (<= 6 mm, where the lid sits
# above the open eye), 6-8 mm, and the lower part that closes over the eye (its open position is the
# lash line).
BANDS = (0.006, 0.008)


def lid_ratios(seeds) -> dict[str, float]:
    """``{"all": r, "bands": [r per band of BANDS], "lambert": r, ...}``: median over the lid
    points (of a band) of the mean over ``seeds`` of truth lid luma / sampled skin luma (``lambert``:
    the head model's Lambert ratio, same points). Raises ``ValueError`` for a held-out seed."""
    from scipy.spatial import cKDTree

    from fastgha_core.data.headmodel import HeadModel
    from fastgha_core.data.synthetic import TRAIN_SEEDS, SyntheticSubject
    from fastgha_core.model import prior as P

    hm = HeadModel.load()
    b = P.load_basis("ict53")
    lash = np.zeros(len(b.interior_vertices), bool) if b.lash is None else b.lash
    lid = b.sample_color & ~lash & (b.interior_group > 0)
    ids = b.interior_vertices[lid]
    blink = [hm.expression_names.index(n) for n in ("eyeBlink_L", "eyeBlink_R")]
    travel = np.linalg.norm(b.expression_basis[blink][:, ids], axis=-1).max(0)
    z0 = np.zeros(hm.num_expression, np.float32)
    zb = z0.copy()
    zb[blink] = 1.0
    M = np.eye(3)
    luma = P._LUMA.astype(np.float64)
    ratios, lam = [], []
    for seed in seeds:
        if int(seed) not in TRAIN_SEEDS:
            raise ValueError(f"lid colours are measured on training subjects only, got seed {seed}")
        s = SyntheticSubject(int(seed), hm)
        f0, fb = s.frame(z0), s.frame(zb)
        nv = len(s.base)
        skin = f0.points[:nv]
        tree = cKDTree(skin)
        ref = P._lid_skin_colors(skin[ids], M, tree, f0.colors[:nv]).astype(np.float64)
        ratios.append((fb.colors[ids].astype(np.float64) @ luma) / (ref @ luma))
        v0, vb = s.vertices(z0).astype(np.float64), s.vertices(zb).astype(np.float64)
        up, fwd = np.array([0, 1.0, 0]), np.array([0, 0, 1.0])
        _, below = tree.query(v0[ids] - 0.014 * up + 0.004 * fwd)
        lam.append(P._brightness(vb, s.faces)[ids] / P._brightness(v0, s.faces)[below])
    r = np.mean(ratios, 0)
    la = np.mean(lam, 0)
    band = np.searchsorted(np.asarray(BANDS), travel, side="left")
    out = {
        "all": float(np.median(r)),
        "subject_spread": float(np.std([np.median(x) for x in ratios])),
        "lambert": float(np.median(la)),
        "bands": [float(np.median(r[band == i])) for i in range(len(BANDS) + 1)],
        "bands_lambert": [float(np.median(la[band == i])) for i in range(len(BANDS) + 1)],
        "band_points": [int((band == i).sum()) for i in range(len(BANDS) + 1)],
    }
    return out


def main(argv=None) -> int:
    a = training_subjects_args(__doc__, argv)
    res = lid_ratios(range(a.subjects))
    for k, v in res.items():
        print(f"{k}: {v:.3f}" if isinstance(v, float) else f"{k}: {np.round(v, 3).tolist()}")
    write_json(a.json, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
