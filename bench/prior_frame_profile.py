"""Where the expression prior's per-frame cost goes (issue 16): the server's frame path split into
stages, prior on (A) against the old prior-off path (B), interleaved in one process.

Same avatars and expressions as ``bench/prior_frame_ab.py`` (the shipped sample ``synth_1000001``,
4 views; expressions uniform in [0, 0.6] per blendshape). Stages, each timed on its own per frame:

- ``animate``: ``model.animate`` as the server calls it; ``mlp``: the MLP's per-frame layers alone,
  and ``prior`` = ``animate - mlp`` (with the prior: its displacement, the gate and the assembly of
  the deformed Gaussians; without: the residual's addition);
- ``project``, ``pack`` .. ``composite``, ``finish``: the CPU rasterizer, as
  ``fastgha_core.bench.frame.render_breakdown`` splits it; ``quantise``, ``jpeg``: the server's
  ``frame_to_uint8`` and ``encode_jpeg``.

Reported: the median ms of each stage for A and B, A - B, and the Gaussians handed to the
rasterizer, the splats it composited and the (tile, splat) pairs (medians).

    python bench/prior_frame_profile.py --rounds 40 --size 256
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/: _bench_cli, _prior_ab (tests load this file by path)

from _bench_cli import add_threads_and_clock, frame_parser, set_threads, write_json

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = frame_parser(__doc__, rounds=40)
    ap.add_argument("--size", type=int, default=256)
    add_threads_and_clock(ap)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    import fastgha_core  # noqa: F401  (sets the OpenMP defaults before torch is imported, as the server does)
    import numba
    import torch

    from _prior_ab import prior_on_off
    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.render import _background, _finish
    from fastgha_core.render.cpu_backend import num_threads, project_cpu, rasterize_fast
    from server.frames import FrameRenderer
    from server.imaging import encode_jpeg, frame_to_uint8

    set_threads(args.threads)
    model_a, model_b, av_a, av_b = prior_on_off(args.model)
    cam = FrameRenderer(model_a, "cpu").default_camera.resize(args.size, args.size).flatten()
    w, h = cam.width, cam.height
    bg = _background(BACKGROUND_RGB, 1, torch.float32, torch.device("cpu"))

    def frame(model, av, z, st):
        t = time.thread_time if args.clock == "cpu" else time.perf_counter
        with torch.inference_mode():
            t0 = t()
            g = model.animate(av, z)
            st["animate"] = t() - t0
            t0 = t()
            model.deform.forward_split(av.deform_cache, z)
            st["mlp"] = t() - t0
            st["prior"] = st["animate"] - st["mlp"]
            prev = numba.get_num_threads()
            numba.set_num_threads(num_threads())
            try:
                t0 = t()
                proj, rects = project_cpu(g.means, g.quats, g.scales, cam.K, cam.w2c, w, h)
                values = torch.cat([g.colors.expand(1, -1, 3), proj.depths[..., None]], dim=-1)
                st["project"] = t() - t0
                acc, alpha = rasterize_fast(proj, g.opacities, values, w, h, rects, stages=st)
                t0 = t()
                out = _finish(acc, alpha, bg)
                st["finish"] = t() - t0
            finally:
                numba.set_num_threads(prev)
            t0 = t()
            fr = frame_to_uint8(out.rgb[0])
            st["quantise"] = t() - t0
        t0 = t()
        encode_jpeg(fr, 85)
        st["jpeg"] = t() - t0
        st["gaussians"] = len(g)

    gen = torch.Generator().manual_seed(0)
    runs = {"A": [], "B": []}
    for r in range(args.rounds + 3):
        z = torch.rand(53, generator=gen) * 0.6
        order = [("A", model_a, av_a), ("B", model_b, av_b)]
        if r % 2:
            order.reverse()
        for name, model, av in order:
            st: dict = {}
            frame(model, av, z, st)
            if r >= 3:
                runs[name].append(st)
    names = ["animate", "mlp", "prior", "project", "pack", "sort", "gather", "bin", "composite", "finish", "quantise", "jpeg"]
    counts = ["gaussians", "composited_splats", "intersections"]
    out = {"model": args.model, "size": args.size, "threads": torch.get_num_threads(), "clock": args.clock, "rounds": args.rounds, "stages_ms": {}, "counts": {}}
    print(f"{args.size}², {args.rounds} rounds, torch threads {torch.get_num_threads()}, {args.clock} clock: median ms (A = prior on, B = prior off)")
    print(f"{'stage':>18} {'A':>8} {'B':>8} {'A-B':>8}")
    tot = {"A": 0.0, "B": 0.0}
    for k in names:
        med = {n: 1e3 * statistics.median(s.get(k, 0.0) for s in runs[n]) for n in runs}
        out["stages_ms"][k] = med
        if k not in ("mlp", "prior"):
            tot["A"] += med["A"]
            tot["B"] += med["B"]
        print(f"{k:>18} {med['A']:8.2f} {med['B']:8.2f} {med['A'] - med['B']:8.2f}")
    print(f"{'sum (no sub-parts)':>18} {tot['A']:8.2f} {tot['B']:8.2f} {tot['A'] - tot['B']:8.2f}")
    for k in counts:
        med = {n: statistics.median(s.get(k, 0) for s in runs[n]) for n in runs}
        out["counts"][k] = med
        print(f"{k:>18} {med['A']:8.0f} {med['B']:8.0f} {med['A'] - med['B']:8.0f}")
    write_json(args.json, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
