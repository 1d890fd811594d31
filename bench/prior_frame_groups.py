"""Where the expression prior's extra rasterizer time goes, Gaussian group by group (issue 16).

For each frame of the model with the prior (the avatar of ``bench/prior_frame_ab.py``: the shipped
sample ``synth_1000001``, 4 views), ``model.animate`` gives the Gaussians the server rasterizes; they
are rendered (``fastgha_core.render.render``: projection, sort, compositing, as the server does) as
they are and with one group left out at a time:

- ``shell``: the back-of-head shell (ungated);
- ``mouth``: the mouth interior (teeth, gums, socket; gated by how far the lips are open);
- ``lids``: the closed-lid and lash Gaussians of both eyes (gated by the blinks);
- ``eye hiders``: reconstructed Gaussians on the eyeballs that fade as the lids close;
- ``gated out``: every Gaussian whose final opacity is below the rasterizer's ``ALPHA_MIN``, which
  no pixel composites: the image is the same (checked, ``max |diff|``), so this row is what culling
  every gated-out Gaussian before the rasterizer (not only trailing runs, as ``animate`` does) saves;
- ``interior``: the shell, mouth and lids together (what is left is the old path's Gaussian count).

Expressions: ``--mode random`` is the protocol of ``prior_frame_ab.py`` (each blendshape uniform in
[0, 0.6]: the mouth is open in every frame); ``--mode blink`` renders ``eyeBlink_L`` = ``eyeBlink_R``
= 1 with closed lips, the slider frame whose gated-out Gaussians (the whole mouth interior) sit
between drawn ones (the lids), so ``animate`` cannot drop them as a trailing run. (Neutral, smile and
jaw-only frames have every gated-out Gaussian in trailing runs, which ``animate`` already leaves
out.) Reported: median ms of each render, its difference to the
frame as drawn, and the median count left out. ``--threads 1 --clock cpu`` as in
``prior_frame_profile.py`` (steadier on a loaded machine).

    python bench/prior_frame_groups.py --rounds 20 --size 256 --threads 1 --clock cpu
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
    ap = frame_parser(__doc__, rounds=20)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--mode", choices=("random", "blink"), default="random")
    add_threads_and_clock(ap)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    import fastgha_core  # noqa: F401  (the OpenMP defaults before torch, as the server does)
    import torch

    from _prior_ab import prior_on_off
    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.render import render
    from fastgha_core.render.projection import ALPHA_MIN
    from server.frames import FrameRenderer

    set_threads(args.threads)
    try:
        model, _, av, _ = prior_on_off(args.model)
    except ValueError as e:
        print(e)
        return 1
    cam = FrameRenderer(model, "cpu").default_camera.resize(args.size, args.size)
    clock = time.thread_time if args.clock == "cpu" else time.perf_counter
    grp = av.prior.groups()  # -1 ungated, 0 mouth, 1-2 lids, 3.. eye hiders
    n_rec = av.num_reconstructed
    idx = torch.arange(len(av))
    groups = {
        "shell": (grp == -1) & (idx >= n_rec),
        "mouth": grp == 0,
        "lids": (grp == 1) | (grp == 2),
        "eye hiders": grp >= 3,
    }
    groups["interior"] = idx >= n_rec
    space = model.expression_space
    blink = torch.as_tensor(space.parse({"eyeBlink_L": 1.0, "eyeBlink_R": 1.0}), dtype=torch.float32)
    gen = torch.Generator().manual_seed(0)
    rows = ["as drawn", *groups, "gated out"]
    ms: dict[str, list[float]] = {k: [] for k in rows}
    left: dict[str, list[int]] = {k: [] for k in rows}
    worst = 0.0
    with torch.inference_mode():
        for r in range(args.rounds + 2):
            z = torch.rand(53, generator=gen) * 0.6 if args.mode == "random" else blink
            g = model.animate(av, z)
            n = len(g)
            sets = {"as drawn": None, **{k: ~m[:n] for k, m in groups.items()}, "gated out": g.opacities >= ALPHA_MIN}
            order = rows if r % 2 == 0 else rows[::-1]
            for k in order:
                gg = g if sets[k] is None else g[sets[k]]
                t0 = clock()
                render(gg, cam, background=BACKGROUND_RGB)
                dt = clock() - t0
                if r >= 2:  # warm-up rounds not counted
                    ms[k].append(1e3 * dt)
                    left[k].append(n - len(gg))
            culled = g[sets["gated out"]]
            worst = max(worst, float((render(culled, cam, background=BACKGROUND_RGB).rgb - render(g, cam, background=BACKGROUND_RGB).rgb).abs().max()))
    base = statistics.median(ms["as drawn"])
    report = {"model": args.model, "size": args.size, "mode": args.mode, "rounds": args.rounds, "threads": torch.get_num_threads(),
              "clock": args.clock, "ms": {}, "left_out": {}, "gated_out_max_abs_diff": worst}
    print(f"{args.size}², {args.mode} expressions, {args.rounds} rounds, threads {torch.get_num_threads()}, {args.clock} clock; render median ms")
    print(f"{'left out':>12} {'ms':>8} {'saves':>8} {'Gaussians':>10}")
    for k in rows:
        m, c = statistics.median(ms[k]), int(statistics.median(left[k]))
        report["ms"][k], report["left_out"][k] = m, c
        print(f"{k:>12} {m:8.2f} {base - m:8.2f} {c:10d}")
    print(f"gated-out cull: max |image difference| {worst:.3g}")
    write_json(args.json, report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
