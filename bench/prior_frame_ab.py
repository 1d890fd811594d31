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

``--rev REV`` adds a third path to the same rounds: the prior path of git revision ``REV`` (its
``fastgha_core`` exported into a temporary folder and imported as another package; its model, its
avatar of the same sample and its animate/render code, quantised and encoded by this tree's server
functions), so that a change to the prior's frame path is measured before and after in one process:
reported as ``rev`` (ms, fps), its ratio to the old path, and ``rev / prior`` (> 1: this tree faster).

    python bench/prior_frame_ab.py --rounds 40 --json out/prior_ab.json
    python bench/prior_frame_ab.py --rounds 30 --rev e77b094
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/: _bench_cli, _prior_ab (tests load this file by path)

from _bench_cli import frame_parser, write_json

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = frame_parser(__doc__, rounds=40)
    ap.add_argument("--sizes", default="256,512")
    ap.add_argument("--json", default=None)
    ap.add_argument("--rev", default=None, help="also time the prior path of this git revision (before/after in one process)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    import fastgha_core  # noqa: F401  (sets the OpenMP defaults before torch is imported, as the server does)
    import torch

    import tempfile

    from _prior_ab import prior_on_off, rev_frame, rev_package
    from server.frames import FrameRenderer

    try:
        model_a, model_b, av_a, av_b = prior_on_off(args.model)
    except ValueError as e:
        print(e)
        return 1
    ra, rb = FrameRenderer(model_a, "cpu"), FrameRenderer(model_b, "cpu")
    tmp = tempfile.TemporaryDirectory(prefix="prior_ab_rev_") if args.rev else None
    rev = None
    if args.rev:
        try:
            _, _, rev = rev_frame(rev_package(args.rev, tmp.name), args.model, ra.default_camera)
        except ValueError as e:
            print(e)
            return 1
    g = torch.Generator().manual_seed(0)
    out = {"model": args.model, "gaussians_a": len(av_a), "gaussians_b": len(av_b), "threads": torch.get_num_threads(), "rev": args.rev, "sizes": {}}
    for size in [int(s) for s in args.sizes.split(",")]:
        cam = ra.default_camera.resize(size, size)
        t = {"a": [], "b": [], "rev": []}
        dx = {"da": [], "db": [], "xa": [], "xb": []}
        paths = ["a", "b"] + (["rev"] if rev else [])
        for r in range(args.rounds + 3):
            z = torch.rand(53, generator=g) * 0.6
            order = paths[r % len(paths):] + paths[: r % len(paths)]  # each path first in turn
            for p in order:
                t0 = time.perf_counter()
                if p == "rev":
                    rev(z, size, 85)
                else:
                    fr = (ra if p == "a" else rb).render(av_a if p == "a" else av_b, z, cam, 85)
                if r >= 3:  # warm-up rounds not counted
                    t[p].append(1e3 * (time.perf_counter() - t0))
                    if p != "rev":
                        dx["d" + p].append(fr.deform_ms)
                        dx["x" + p].append(fr.raster_ms)
        ma, mb = statistics.median(t["a"]), statistics.median(t["b"])
        dm = {k: statistics.median(v) for k, v in dx.items()}
        out["sizes"][size] = {
            "prior_ms": ma, "old_ms": mb, "prior_fps": 1e3 / ma, "old_fps": 1e3 / mb, "fps_ratio_prior_over_old": mb / ma,
            "deform_ms_prior": dm["da"], "deform_ms_old": dm["db"], "raster_ms_prior": dm["xa"], "raster_ms_old": dm["xb"],
        }
        line = (
            f"{size}²: prior {ma:.1f} ms ({1e3 / ma:.1f} fps), old path {mb:.1f} ms ({1e3 / mb:.1f} fps), fps ratio {mb / ma:.3f}; "
            f"deform {dm['da']:.1f} vs {dm['db']:.1f} ms, raster {dm['xa']:.1f} vs {dm['xb']:.1f} ms"
        )
        if rev:
            mr = statistics.median(t["rev"])
            out["sizes"][size].update({"rev_ms": mr, "rev_fps": 1e3 / mr, "fps_ratio_rev_over_old": mb / mr, "rev_over_prior": mr / ma})
            line += f"; {args.rev}: {mr:.1f} ms ({1e3 / mr:.1f} fps), fps ratio {mb / mr:.3f}, {args.rev} / prior {mr / ma:.3f}"
        print(line)
    write_json(args.json, out)
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
