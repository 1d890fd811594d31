"""Which blendshapes show the mouth interior, against the prior's mouth gate (issue 16, the smile).

For training subjects (seeds 0..N-1, never the held-out ones), each of the 53 ICT-FaceKit
blendshapes at weight 1 is rendered frontally (1 m, the synthetic rig's field of view) by the
ground-truth mesh rasterizer with a per-vertex flag that is 1 on the teeth, gums/tongue and mouth
socket (``head_regions``). The pixels where the interpolated flag is > 0.5, less the neutral
face's, over those of ``jawOpen``, is how much of the interior the shape shows. Printed per shape,
largest first, with the mouth gate's hand weight (``prior._MOUTH_OPENING``) and the inner-lip
landmark gap change on the generic head (mm; mean of |p61-p67|, |p62-p66|, |p63-p65|).

    python bench/mouth_interior_shown.py --subjects 4 --resolution 512
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def interior_shown(seeds, resolution: int = 512) -> dict[str, np.ndarray]:
    """``{shape name: [S] interior pixels over neutral / jawOpen's}`` for the training ``seeds``.
    Raises ``ValueError`` for a held-out seed."""
    import torch

    from fastgha_core.cameras import Cameras
    from fastgha_core.data.appearance import head_regions
    from fastgha_core.data.meshraster import render_mesh
    from fastgha_core.data.synthetic import FOV_DEG, TRAIN_SEEDS, SyntheticSubject

    seeds = list(seeds)
    if any(not (0 <= s < TRAIN_SEEDS.stop) for s in seeds):
        raise ValueError(
            f"interior_shown: expected training subjects (seeds 0..{TRAIN_SEEDS.stop - 1}), got {seeds}"
        )
    cam = Cameras.look_at(
        torch.tensor([[0.0, 0.0, 1.0]]),
        torch.zeros(1, 3),
        fov_deg=FOV_DEG,
        width=resolution,
        height=resolution,
    )
    w2c, K = cam.w2c[0].double().numpy(), cam.K[0].double().numpy()
    out = None
    for si, seed in enumerate(seeds):
        subj = SyntheticSubject(seed)
        m = subj.model
        reg = head_regions(m)
        flag = ((reg.teeth > 0) | (reg.gums > 0) | (reg.mouth_interior > 0)).astype(
            np.float64
        )[:, None]
        if out is None:
            out = np.zeros((len(seeds), m.num_expression + 1))
        for k in range(m.num_expression + 1):
            z = np.zeros(m.num_expression, np.float32)
            if k < m.num_expression:
                z[k] = 1.0
            v = subj.vertices(z).astype(np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
            r = render_mesh(v, subj.faces, flag, K, resolution, resolution, 1, None)
            out[si, k] = float((r.color[..., 0] > 0.5).sum())
    names = subj.model.expression_names
    base = out[:, -1]
    jaw = out[:, names.index("jawOpen")] - base
    return {n: (out[:, k] - base) / jaw for k, n in enumerate(names)}


def lip_gap_change_mm() -> dict[str, float]:
    """Inner-lip landmark gap change of each shape at weight 1 on the generic ICT-FaceKit head (mm)."""
    from fastgha_core.data.headmodel import HeadModel

    m = HeadModel.load()
    L = m.landmarks68

    def gap(v):
        return np.mean(
            [
                np.linalg.norm(v[L[a]] - v[L[b]])
                for a, b in ((61, 67), (62, 66), (63, 65))
            ]
        )

    g0 = gap(m.neutral)
    return {
        n: 1000.0 * (gap(m.neutral + m.expression_basis[k]) - g0)
        for k, n in enumerate(m.expression_names)
    }


def main() -> None:
    from fastgha_core.model.prior import _MOUTH_OPENING

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--subjects", type=int, default=4)
    ap.add_argument("--resolution", type=int, default=512)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    shown = interior_shown(range(a.subjects), a.resolution)
    gaps = lip_gap_change_mm()
    rows = sorted(shown, key=lambda n: -float(np.mean(shown[n])))
    print(
        f"{'shape':20s} {'shown/jawOpen':>13s} {'min..max':>15s} {'lip gap mm':>10s} {'gate weight':>11s}"
    )
    for n in rows:
        s = shown[n]
        print(
            f"{n:20s} {np.mean(s):13.3f} {s.min():7.3f}..{s.max():6.3f} {gaps[n]:10.2f} {_MOUTH_OPENING.get(n, 0.0):11.2f}"
        )
    if a.json:
        a.json.write_text(
            json.dumps(
                {
                    n: {
                        "shown": shown[n].tolist(),
                        "lip_gap_mm": gaps[n],
                        "gate": _MOUTH_OPENING.get(n, 0.0),
                    }
                    for n in rows
                },
                indent=1,
            )
        )


if __name__ == "__main__":
    main()
