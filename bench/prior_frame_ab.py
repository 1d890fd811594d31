"""Per-frame cost of the expression prior (issue 16): the server's frame path with and without it,
interleaved in one process so that machine load hits both alike.

A = the model as shipped (prior on: head-surface displacement + MLP residual, mouth-interior
Gaussians with their opacity gate); B = the same weights on the old path (prior off, an avatar
without the binding and the interior). Both avatars come from the same 4 input views of the shipped
sample ``synth_1000001``. Each round renders one frame with A then one with B (or B then A on odd
rounds) through ``server.frames.FrameRenderer.render`` (deform, rasterize, JPEG) with changing
expressions (uniform in [0, 0.6] per blendshape, so the mouth and lids are often partly open);
reported: median ms per frame, frames per second, the ratio B/A of medians, and the deform and
raster medians of each.

``fastgha_core`` is imported before torch, as the server does, so that its OpenMP default
(``GOMP_SPINCOUNT``, ``fastgha_core.perf``) reaches torch's runtime; until 2026-11-29 the script
imported torch first, and idle OpenMP threads then spun for longer after each parallel region.
``bench/prior_frame_profile.py`` splits the same frames into stages.

    python bench/prior_frame_ab.py --rounds 40 --json out/prior_ab.json
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="tiny")
    ap.add_argument("--rounds", type=int, default=40)
    ap.add_argument("--sizes", default="256,512")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    import fastgha_core  # noqa: F401  (sets the OpenMP defaults before torch is imported, as the server does)
    import torch

    from _prior_ab import prior_on_off, write_json
    from server.frames import FrameRenderer

    try:
        model_a, model_b, av_a, av_b = prior_on_off(args.model)
    except ValueError as e:
        print(e)
        return 1
    ra, rb = FrameRenderer(model_a, "cpu"), FrameRenderer(model_b, "cpu")
    g = torch.Generator().manual_seed(0)
    out = {"model": args.model, "gaussians_a": len(av_a), "gaussians_b": len(av_b), "threads": torch.get_num_threads(), "sizes": {}}
    for size in [int(s) for s in args.sizes.split(",")]:
        cam = ra.default_camera.resize(size, size)
        ta, tb, da, db, xa, xb = [], [], [], [], [], []
        for r in range(args.rounds + 3):
            z = torch.rand(53, generator=g) * 0.6
            order = [(ra, av_a, ta, da, xa), (rb, av_b, tb, db, xb)] if r % 2 == 0 else [(rb, av_b, tb, db, xb), (ra, av_a, ta, da, xa)]
            for rend, av, acc, dacc, xacc in order:
                t0 = time.perf_counter()
                fr = rend.render(av, z, cam, 85)
                if r >= 3:  # warm-up rounds not counted
                    acc.append(1e3 * (time.perf_counter() - t0))
                    dacc.append(fr.deform_ms)
                    xacc.append(fr.raster_ms)
        ma, mb = statistics.median(ta), statistics.median(tb)
        out["sizes"][size] = {
            "prior_ms": ma, "old_ms": mb, "prior_fps": 1e3 / ma, "old_fps": 1e3 / mb, "fps_ratio_prior_over_old": mb / ma,
            "deform_ms_prior": statistics.median(da), "deform_ms_old": statistics.median(db),
            "raster_ms_prior": statistics.median(xa), "raster_ms_old": statistics.median(xb),
        }
        print(
            f"{size}²: prior {ma:.1f} ms ({1e3 / ma:.1f} fps), old path {mb:.1f} ms ({1e3 / mb:.1f} fps), fps ratio {mb / ma:.3f}; "
            f"deform {statistics.median(da):.1f} vs {statistics.median(db):.1f} ms, raster {statistics.median(xa):.1f} vs {statistics.median(xb):.1f} ms"
        )
    write_json(args.json, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
