"""Held-out synthetic PSNR/SSIM when the INPUT cameras carry tracking-shaped pose noise (issue 17).

The protocol of ``fastgha eval`` (``train/evaluate.py``: 4 held-out subjects, 4 inputs, 4 novel
expressions x 4 novel views), except that the cameras handed to ``prepare``/``reconstruct`` are
perturbed by ``data/augment.py``'s :class:`InputCameraNoise` scaled by each ``--levels`` factor
(0 = exact cameras, 1 = the option's defaults); the target cameras stay exact. The noise of input
view ``i`` of subject ``k`` is drawn from a generator seeded by ``(--seed, k)``, the same for every
model, so models are compared on identical perturbations.

    python bench/robust_heldout.py --model tiny --model RUN/model --levels 0,1,2 --subjects 4
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import fields, replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


class _NoisyInputs:
    """A FastGHA whose ``prepare`` perturbs the input cameras (everything else is forwarded)."""

    def __init__(self, model, noise, seed: int):
        self._model, self._noise, self._seed, self._calls = model, noise, seed, 0

    def __getattr__(self, name):
        return getattr(self._model, name)

    def prepare(self, images, cams, masks=None):
        import torch

        from fastgha_core.cameras import Cameras
        from fastgha_core.data.augment import perturb_w2c

        gen = torch.Generator().manual_seed(self._seed * 1000 + self._calls)
        self._calls += 1
        noisy = Cameras(cams.K, perturb_w2c(cams.w2c, self._noise, gen), cams.width, cams.height)
        return self._model.prepare(images, noisy, masks=masks)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", action="append", required=True, help="model name or folder (repeatable)")
    ap.add_argument("--levels", default="0,1,2", help="comma-separated multiples of the default noise")
    ap.add_argument("--subjects", type=int, default=4)
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="write all rows here")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    import fastgha_core  # noqa: F401  (OpenMP defaults before torch)
    import torch

    from fastgha_core.data.augment import InputCameraNoise
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.train.builders import build_eval_sources
    from fastgha_core.train.evaluate import EvalConfig, evaluate

    torch.set_grad_enabled(False)
    levels = [float(x) for x in args.levels.split(",")]
    base = InputCameraNoise(enabled=True)
    sources = build_eval_sources("synthetic-heldout", args.subjects, args.resolution)
    rows = []
    print("| model | noise level | PSNR | SSIM | per subject PSNR |")
    print("|---|---:|---:|---:|---|")
    for spec in args.model:
        model = load_model(spec).eval()
        for lv in levels:
            scaled = replace(base, **{f.name: getattr(base, f.name) * lv for f in fields(base) if f.name not in ("enabled", "yaw_gain")})
            m = _NoisyInputs(model, scaled, args.seed) if lv > 0 else model
            rep = evaluate(m, sources, EvalConfig(resolution=args.resolution), progress=False)
            per = [s["psnr"] for s in rep["subjects"]]
            row = {"model": spec, "level": lv, "psnr": rep["summary"]["psnr"], "ssim": rep["summary"]["ssim"], "subjects_psnr": per}
            rows.append(row)
            print(f"| {spec} | {lv:g} | {row['psnr']:.2f} | {row['ssim']:.3f} | {' / '.join(f'{p:.2f}' for p in per)} |", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
