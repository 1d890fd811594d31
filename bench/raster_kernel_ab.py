"""A/B of the compositing kernel against the one in another git revision, side by side in one process.

    python bench/raster_kernel_ab.py 0a3a0ea        # the commit before the fixed-width row loops

    python bench/raster_kernel_ab.py 70c35b7 --pass backward   # the scalar gradient kernel

    python bench/raster_kernel_ab.py 1a81e15 --pass backward --isa avx2   # both compiled for AVX2 only

Both kernels composite the same packed splats of the shipped model's avatar of the first shipped
sample (one frame from the default camera at 256² and 512²); the script prints the median ms of
each over interleaved repeats. Forward: it checks the outputs are bit-identical. Backward (incoming
gradients drawn from a fixed seed, as a loss on every pixel would give): it prints the largest
difference of the per-splat gradients between the two, relative to each gradient's largest value
(the kernels sum in different orders, so they agree to float32 rounding, not bit for bit).
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import fastgha_core  # noqa: F401  (sets the OpenMP defaults before torch is imported)
import numba
import numpy as np
import torch

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bench_cli import add_isa, run_as_isa  # noqa: E402
KERNELS = "fastgha_core/render/cpu_kernels.py"


def kernels_at(rev: str):
    """The ``cpu_kernels`` module as it was at ``rev``, imported under another name."""
    src = subprocess.run(["git", "show", f"{rev}:{KERNELS}"], cwd=REPO, check=True, capture_output=True, text=True).stdout
    src = src.replace("from .projection import", "from fastgha_core.render.projection import")
    path = Path(tempfile.mkdtemp()) / "cpu_kernels_ab.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("cpu_kernels_ab", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def packed_frame(res: int):
    """Packed, sorted, binned splats of one served frame: the kernel's inputs."""
    from fastgha_core import load_model
    from fastgha_core.data.samples import load_sample
    from fastgha_core.render import cpu_kernels as K
    from fastgha_core.render.cpu_backend import _np, project_cpu
    from server.frames import FrameRenderer

    model = load_model("tiny")
    sample = load_sample(gt=False)
    images, cams = model.prepare(sample.request_images, sample.request_cameras, sample.request_masks)
    with torch.inference_mode():
        g = model.animate(model.reconstruct(images, cams), sample.expressions[3])
        cam = FrameRenderer(model, "cpu").default_camera.resize(res, res).flatten()
        proj, rects = project_cpu(g.means, g.quats, g.scales, cam.K, cam.w2c, res, res)
        values = torch.cat([g.colors.expand(1, -1, 3), proj.depths[..., None]], dim=-1)
    n, tw = len(g), (res + 15) // 16
    rec_all, vis = np.empty((n, K.N_REC), np.float32), np.empty(n, np.uint8)
    K.pack_splats(_np(proj.means2d[0]), _np(proj.conics[0]), _np(rects[0]), _np(g.opacities), _np(values[0]), rec_all, vis)
    rec, trect = K.gather_rows(rec_all, _np(rects[0]), K.sort_visible(_np(proj.depths[0]).view(np.uint32), vis))
    offsets, ids = K.bin_sorted(trect, tw * tw, tw, numba.get_num_threads())
    return rec, offsets, ids, tw


def backward_ab(kernels, rev, rec, offsets, ids, tw, res, nch, repeats):
    """Times ``raster_backward_fast`` of both modules on one frame and compares their gradients."""
    from fastgha_core.render import cpu_kernels as K

    acc, T = np.zeros((res, res, 4), np.float32), np.zeros((res, res), np.float32)
    K.raster_forward_fast(rec, offsets, ids, res, res, tw, nch, acc, T)
    rng = np.random.default_rng(0)
    g_acc = rng.standard_normal((res, res, 4)).astype(np.float32)
    g_alpha = rng.standard_normal((res, res)).astype(np.float32)
    grads, times = {}, {k: [] for k in kernels}
    for name, mod in kernels.items():  # also compiles
        out = np.empty((len(ids), mod.N_GRAD32), np.float32)
        mod.raster_backward_fast(rec, offsets, ids, res, res, tw, nch, acc, T, g_acc, g_alpha, out)
        grads[name] = K.reduce_rows(ids, out, rec.shape[0])
    for _ in range(repeats):
        for name, mod in kernels.items():
            out = np.empty((len(ids), mod.N_GRAD32), np.float32)
            t = time.perf_counter()
            mod.raster_backward_fast(rec, offsets, ids, res, res, tw, nch, acc, T, g_acc, g_alpha, out)
            times[name].append(1e3 * (time.perf_counter() - t))
    a, b = grads.values()
    rel = float((np.abs(a - b).max(0) / np.maximum(np.abs(a).max(0), 1e-30)).max())
    med = {k: statistics.median(v) for k, v in times.items()}
    old_ms, new_ms = med[rev], med["working tree"]
    print(f"{res}² backward: {len(ids)} intersections; {rev} {old_ms:.2f} ms, working tree {new_ms:.2f} ms, "
          f"{old_ms / new_ms:.2f}x; largest gradient difference {rel:.1e} of each gradient's largest value")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("rev", help="git revision holding the other kernel")
    p.add_argument("--repeats", type=int, default=15)
    p.add_argument("--pass", dest="which", choices=("forward", "backward"), default="forward")
    add_isa(p)
    args = p.parse_args(argv)
    run_as_isa(args.isa, __file__, argv)
    from fastgha_core.render import cpu_kernels as new

    kernels = {args.rev: kernels_at(args.rev), "working tree": new}
    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    nch = numba.get_num_threads()
    for res in (256, 512):
        rec, offsets, ids, tw = packed_frame(res)
        if args.which == "backward":
            backward_ab(kernels, args.rev, rec, offsets, ids, tw, res, nch, args.repeats)
            continue
        outs, times = {}, {k: [] for k in kernels}
        for name, K in kernels.items():  # also compiles
            acc, T = np.zeros((res, res, 4), np.float32), np.zeros((res, res), np.float32)
            K.raster_forward_fast(rec, offsets, ids, res, res, tw, nch, acc, T)
            outs[name] = (acc, T)
        (a0, t0), (a1, t1) = outs.values()
        same = np.array_equal(a0, a1) and np.array_equal(t0, t1)
        for _ in range(args.repeats):
            for name, K in kernels.items():
                acc, T = np.empty((res, res, 4), np.float32), np.empty((res, res), np.float32)
                t = time.perf_counter()
                K.raster_forward_fast(rec, offsets, ids, res, res, tw, nch, acc, T)
                times[name].append(1e3 * (time.perf_counter() - t))
        med = {k: statistics.median(v) for k, v in times.items()}
        old_ms, new_ms = med[args.rev], med["working tree"]
        print(f"{res}²: {len(ids)} intersections; {args.rev} {old_ms:.2f} ms, working tree {new_ms:.2f} ms, "
              f"{old_ms / new_ms:.2f}x; outputs bit-identical: {same}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
