"""Served-frame cost of view blending (``model/viewblend.py``, issue 17), side by side.

The server's ``FrameRenderer.render`` (animate + render + JPEG) of one 4-view avatar
(``fastgha_core.bench._common.bench_avatar``) at 256², with ``view_blend_tau_deg`` 0 (off) and
``--tau`` interleaved frame by frame (same expressions, same camera), plus the blending step
alone (``ViewBlend.factors`` + the opacity product), and ``FastGHA.blend_views`` without and with
Gaussians drawn under the others (``ViewBlend.under``, ``gaussians.off_head_draw = "under"``; a random
``--under-share`` of the reconstructed Gaussians stands for the off-head ones: 14% in studio-4's
avatar of all photos), and with the expression penalty (``gaussians.view_blend_expr_mm = --expr-mm``,
``ViewBlend.expressions``: each input view given a random expression like the real photos' tracked
ones, 0 to 0.3 per code; ``blend_views_expr_ms``, the first frame's build of the per-avatar tables
apart as ``expr_build_ms``). Medians; timings on a shared machine are noisy.

    python bench/view_blend_frame.py --frames 60
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="tiny", help="preset name or model folder (default: tiny)")
    ap.add_argument("--frames", type=int, default=60, help="timed frames per setting (default 60; 2 more warm up)")
    ap.add_argument("--tau", type=float, default=20.0, help="view_blend_tau_deg of the 'on' frames, degrees (default 20, the shipped value)")
    ap.add_argument("--views", type=int, default=4, help="input views of the benchmark avatar, 1 to 8 (default 4)")
    ap.add_argument("--under-share", type=float, default=0.14, help="share of the reconstructed Gaussians flagged 'under' for the blend_views timing (default 0.14)")
    ap.add_argument("--expr-mm", type=float, default=2.0, help="view_blend_expr_mm of the blend_views_expr timing, millimetres (default 2)")
    args = ap.parse_args(argv)
    if args.expr_mm <= 0:
        ap.error(f"expected --expr-mm > 0, got {args.expr_mm:g}")
    if args.frames < 1 or args.tau <= 0 or not 1 <= args.views <= 8 or not 0 <= args.under_share <= 1:
        ap.error(f"expected --frames >= 1, --tau > 0, --views in 1..8 (view blending's masks hold 8 views) and --under-share in 0..1, "
                 f"got {args.frames}, {args.tau:g}, {args.views}, {args.under_share:g}")
    sys.path.insert(0, str(REPO))
    import fastgha_core  # noqa: F401
    import torch

    from fastgha_core.bench._common import bench_avatar, bench_model
    from fastgha_core.cameras import Cameras
    from server.frames import FrameRenderer

    model = bench_model(args.model)
    model.config.gaussians.view_blend_surface_only = False  # per-view data on this (network-depth) avatar too: the cost is the same
    avatar = bench_avatar(model, args.views)
    renderer = FrameRenderer(model, "cpu")
    cam = Cameras.look_at((0.3, 0.05, 0.95), fov_deg=20.0, width=256, height=256)
    gen = torch.Generator().manual_seed(2)
    exprs = [0.3 * torch.rand(model.config.expression_dim, generator=gen) for _ in range(args.frames + 2)]
    times = {0.0: [], args.tau: []}
    for i, e in enumerate(exprs):
        for tau in times:
            model.config.gaussians.view_blend_tau_deg = tau
            t0 = time.perf_counter()
            renderer.render(avatar, e, cam, 85)
            if i >= 2:
                times[tau].append(1e3 * (time.perf_counter() - t0))
    vb = avatar.view_blend
    g = model.animate(avatar, exprs[0])
    step = []
    for _ in range(200):
        t0 = time.perf_counter()
        f = vb.factors(cam, args.tau)
        op = g.opacities.clone()
        op[: len(f)] *= f
        step.append(1e3 * (time.perf_counter() - t0))
    import dataclasses

    model.config.gaussians.view_blend_tau_deg = args.tau
    under = torch.rand(len(vb), generator=gen) < args.under_share
    with_under = dataclasses.replace(avatar, view_blend=dataclasses.replace(vb, under=under))
    blend = {"without": [], "with": []}
    for _ in range(200):
        for name, av in (("without", avatar), ("with", with_under)):
            t0 = time.perf_counter()
            model.blend_views(av, g, cam)
            blend[name].append(1e3 * (time.perf_counter() - t0))
    # the expression penalty: the same avatar with its input views' expressions recorded
    vexpr = 0.3 * torch.rand(vb.directions.shape[0], model.config.expression_dim, generator=gen)
    with_expr = dataclasses.replace(avatar, view_blend=dataclasses.replace(vb, expressions=vexpr))
    model.config.gaussians.view_blend_expr_mm = args.expr_mm
    t0 = time.perf_counter()
    model.blend_views(with_expr, g, cam, exprs[0])  # builds the per-avatar tables (ExpressionPenalty)
    build_ms = 1e3 * (time.perf_counter() - t0)
    pen = with_expr.view_blend.__dict__.get("_expr")
    expr_t = []
    for i in range(200):
        e = exprs[i % len(exprs)]
        t0 = time.perf_counter()
        model.blend_views(with_expr, g, cam, e)
        expr_t.append(1e3 * (time.perf_counter() - t0))
    model.config.gaussians.view_blend_expr_mm = 0.0
    out = {
        "gaussians": len(avatar.gaussians),
        "frame_ms_off": statistics.median(times[0.0]),
        f"frame_ms_tau{args.tau:g}": statistics.median(times[args.tau]),
        "ratio_on_off": statistics.median(times[args.tau]) / statistics.median(times[0.0]),
        "blend_step_ms": statistics.median(step),
        "blend_views_ms": statistics.median(blend["without"]),
        "blend_views_under_ms": statistics.median(blend["with"]),
        "under": int(under.sum()),
        "blend_views_expr_ms": statistics.median(expr_t),
        "expr_build_ms": build_ms,
        "expr_penalised": 0 if pen is None else len(pen),
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
