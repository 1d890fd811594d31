"""Test-time refinement cost, side by side in one process (timings on a shared machine are noisy:
compare the ratios, and prefer the CPU-time columns).

    python bench/refine_timing.py [--repeats 5] [--steps 60] [--skip-raster] [--previous] [--against PRESET] [--isa avx2]

1. Rasterizer forward+backward of ``fastgha bench render``'s 65,536-Gaussian head scene at 256²
   (loss on rgb, alpha and depth): the float64 kernels (``FASTGHA_RASTER_FAST=0``, the path before
   the float32 backward existed) against the float32 gradient path, interleaved, median of repeats.
2. ``refine_avatar`` of the shipped sample's 4-view avatar with the default ``RefineConfig`` (and
   ``--steps``): wall and process CPU seconds, and seconds per step; ``--previous`` also times the
   defaults before 2026-11-30 (night), interleaved with the current ones, and prints the ratio;
   ``--against PRESET`` does the same for ``REFINE_PRESETS[PRESET]`` (e.g. ``colour``: the defaults
   before the scale corrections).

``--isa avx2`` runs it all as an AVX2-only machine would compile and dispatch it (``_bench_cli.run_as_isa``).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import fastgha_core  # noqa: F401  (sets the OpenMP defaults before torch is imported)
import torch


def _time(fn):
    t, c = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - t, time.process_time() - c


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--steps", type=int, default=60, help="refinement steps (default %(default)s: RefineConfig.steps, as the figures in docs/benchmarks.md used)")
    ap.add_argument("--skip-raster", action="store_true")
    ap.add_argument("--previous", action="store_true", help="also time the defaults before 2026-11-30 night (REFINE_PRESETS['smooth']), interleaved")
    ap.add_argument("--against", default=None, help="also time REFINE_PRESETS[PRESET], interleaved, and print the ratio")
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _bench_cli import add_isa, run_as_isa

    add_isa(ap)
    args = ap.parse_args(argv)
    run_as_isa(args.isa, __file__, argv)
    if args.previous and not args.against:
        args.against = "smooth"
    from fastgha_core.bench.render import bench_camera, head_scene
    from fastgha_core.gaussians import Gaussians
    from fastgha_core.render import render

    print(f"threads: torch {torch.get_num_threads()}, cpus {os.cpu_count()}")
    if not args.skip_raster:
        g, cams = head_scene(65536), bench_camera(256)

        def fb():
            x = {k: getattr(g, k).detach().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "colors")}
            out = render(Gaussians(**x), cams, background=(1.0, 1.0, 1.0), backend="cpu")
            (out.rgb.sum() + out.alpha.sum() + 0.1 * out.depth.sum()).backward()

        res = {"0": [], "1": []}
        for mode in "01":
            os.environ["FASTGHA_RASTER_FAST"] = mode
            fb()
        for _ in range(args.repeats):
            for mode in "01":
                os.environ["FASTGHA_RASTER_FAST"] = mode
                res[mode].append(_time(fb))
        os.environ.pop("FASTGHA_RASTER_FAST")
        med = {m: (statistics.median(a for a, _ in r) * 1e3, statistics.median(b for _, b in r) * 1e3) for m, r in res.items()}
        print(f"render fwd+bwd 65k @256²  float64 kernels: {med['0'][0]:.1f} ms wall, {med['0'][1]:.1f} ms cpu")
        print(f"render fwd+bwd 65k @256²  float32 path   : {med['1'][0]:.1f} ms wall, {med['1'][1]:.1f} ms cpu")
        print(f"ratio (wall) {med['0'][0] / med['1'][0]:.2f}x, (cpu) {med['0'][1] / med['1'][1]:.2f}x")

    from fastgha_core.model.fastgha import load_model
    from fastgha_core.refine import REFINE_PRESETS, RefineConfig, refine_avatar
    from fastgha_core.refine.measure import SAMPLE_REQUEST, read_request

    model = load_model("tiny")
    images, masks, cams, expr = read_request(SAMPLE_REQUEST)
    imgs, in_cams = model.prepare(list(images), [cams[i : i + 1] for i in range(len(cams.K))], list(masks))
    avatar = model.reconstruct(imgs, in_cams)
    configs = {"default config": RefineConfig(steps=args.steps)}
    if args.against:
        configs[f"preset {args.against}"] = RefineConfig(**{**REFINE_PRESETS[args.against].__dict__, "steps": args.steps})
    for cfg in configs.values():  # warm-up
        refine_avatar(model, avatar, images, cams, masks, config=RefineConfig(**{**cfg.__dict__, "steps": 2}), expressions=expr)
    runs: dict[str, list] = {k: [] for k in configs}
    for _ in range(max(1, args.repeats // 2)):
        for name, cfg in configs.items():  # interleaved, so both see the same load
            runs[name].append(_time(lambda cfg=cfg: refine_avatar(model, avatar, images, cams, masks, config=cfg, expressions=expr)))
    walls = {}
    for name, r in runs.items():
        wall = walls[name] = statistics.median(a for a, _ in r)
        cpu = statistics.median(b for _, b in r)
        print(f"refine_avatar 4 views, {len(avatar)} Gaussians, {args.steps} steps ({name}): {wall:.2f} s wall, {cpu:.2f} s cpu, {wall / args.steps * 1e3:.0f} ms/step")
    if args.against:
        cpus = {name: statistics.median(b for _, b in r) for name, r in runs.items()}
        other = f"preset {args.against}"
        print(f"ratio default / {other} (wall) {walls['default config'] / walls[other]:.2f}, (cpu) {cpus['default config'] / cpus[other]:.2f}")

if __name__ == "__main__":
    main()
