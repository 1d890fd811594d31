"""``fastgha bench render``: rasterizer timings, CPU kernels vs pure-torch tiles vs dense reference.

Scene: N Gaussians of head-like density, spread uniformly on a head-sized ellipsoid shell
(semi-axes 8 x 11 x 10 cm) as flat discs tangent to the surface whose size matches the
spacing (what per-pixel Gaussians from 4 input views look like), rendered by one camera
60 cm in front of the face with a 25 degree field of view (the head fills most of the image).

Times are medians over repeats (wall clock; the CPU time summed over threads is recorded
too, as ``*_cpu_ms``, because on a shared machine the wall clock includes waiting): "forward" under ``torch.no_grad()``; "forward+backward"
renders with gradients on means, quats, scales, opacities and colors and back-propagates a
loss on rgb, alpha and depth. Slow baselines are skipped where a calibration run predicts
more than ``--render-budget`` seconds for one repeat (or too much memory); the reason is
recorded in the result.
"""

from __future__ import annotations

import logging
import math
import statistics
import time
from typing import Callable

import torch

from ..cameras import Cameras
from ..gaussians import Gaussians
from ._common import positive_int

log = logging.getLogger(__name__)

DEFAULT_SIZES = (10_000, 65_536, 262_144, 1_048_576)
DEFAULT_RESOLUTIONS = (256, 512)
BACKENDS = ("cpu", "torch_tiles", "reference")
REFERENCE_MAX_PAIRS = 2**31  # (pixel, splat) pairs; beyond this the dense reference is not attempted


# --quick: a smoke run of about a minute on 2 cores: the fast kernels at two sizes, one resolution;
# the slow baselines only where one repeat is predicted to take at most QUICK_BUDGET_S
QUICK_SIZES = (10_000, 65_536)
QUICK_RESOLUTIONS = (256,)
QUICK_REPEATS = 3
QUICK_BUDGET_S = 2.0
DEFAULT_BUDGET_S = 30.0


def add_arguments(parser) -> None:
    parser.add_argument("--render-sizes", default=None, help="comma-separated Gaussian counts (default 10000,65536,262144,1048576; --quick 10000,65536)")
    parser.add_argument("--render-resolutions", default=None, help="comma-separated square image sizes (default 256,512; --quick 256)")
    parser.add_argument("--render-repeats", type=positive_int, default=None, help="timed repeats per entry (default 7, --quick 3)")
    parser.add_argument("--render-budget", type=float, default=None,
                        help=f"skip a baseline entry predicted to take longer than this many seconds per repeat (default {DEFAULT_BUDGET_S:g}, --quick {QUICK_BUDGET_S:g})")


def plan(args) -> dict:
    """The run's configuration from the options: sizes, resolutions, repeats, budget (s per repeat)."""
    quick = bool(getattr(args, "quick", False))
    budget = getattr(args, "render_budget", None)
    return {
        "sizes": _parse(getattr(args, "render_sizes", None), QUICK_SIZES if quick else DEFAULT_SIZES),
        "resolutions": _parse(getattr(args, "render_resolutions", None), QUICK_RESOLUTIONS if quick else DEFAULT_RESOLUTIONS),
        "repeats": getattr(args, "render_repeats", None) or (QUICK_REPEATS if quick else 7),
        "budget": float(budget if budget is not None else (QUICK_BUDGET_S if quick else DEFAULT_BUDGET_S)),
    }


def head_scene(n: int, seed: int = 0, dtype: torch.dtype = torch.float32) -> Gaussians:
    """``n`` Gaussians on a head-sized ellipsoid shell (see the module docstring)."""
    g = torch.Generator().manual_seed(seed)
    axes = torch.tensor([0.08, 0.11, 0.10])
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    r = 1.0 + 0.01 * torch.randn(n, 1, generator=g)  # 1 mm-ish radial jitter
    means = d * axes * r
    normal = torch.nn.functional.normalize(d / axes, dim=-1)
    area = 4 * math.pi * ((axes[0] * axes[1]) ** 1.6 + (axes[0] * axes[2]) ** 1.6 + (axes[1] * axes[2]) ** 1.6) ** (1 / 1.6) / 3 ** (1 / 1.6)
    spacing = math.sqrt(float(area) / n)
    # rotation taking local z to the normal, random spin about it
    z = torch.tensor([0.0, 0.0, 1.0]).expand(n, 3)
    axis = torch.linalg.cross(z, normal, dim=-1)
    s = axis.norm(dim=-1, keepdim=True)
    c = (normal * z).sum(-1, keepdim=True)
    half = torch.atan2(s, c) / 2
    axis = axis / s.clamp_min(1e-9)
    q_tilt = torch.cat([torch.cos(half), axis * torch.sin(half)], dim=-1)  # [n, 4] wxyz
    spin = torch.rand(n, 1, generator=g) * math.pi
    q_spin = torch.cat([torch.cos(spin), torch.zeros(n, 2), torch.sin(spin)], dim=-1)
    w1, v1 = q_tilt[:, :1], q_tilt[:, 1:]
    w2, v2 = q_spin[:, :1], q_spin[:, 1:]
    quats = torch.cat([w1 * w2 - (v1 * v2).sum(-1, keepdim=True), w1 * v2 + w2 * v1 + torch.linalg.cross(v1, v2, dim=-1)], dim=-1)
    jitter = torch.exp(0.3 * torch.randn(n, 3, generator=g))
    scales = torch.tensor([0.7, 0.7, 0.15]) * spacing * jitter
    opacities = 0.5 + 0.5 * torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    return Gaussians(means, quats, scales, opacities, colors).to(dtype=dtype)


def bench_camera(resolution: int) -> Cameras:
    return Cameras.look_at(torch.tensor([[0.0, 0.02, 0.6]]), fov_deg=25.0, width=resolution, height=resolution)


def _median_time(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """Median wall-clock and median process CPU seconds (all threads) of ``fn``."""
    fn()  # warm-up (numba compile / cache load, allocator)
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def _forward(g: Gaussians, cams: Cameras, backend: str) -> Callable[[], object]:
    from ..render import render

    def f():
        with torch.no_grad():
            return render(g, cams, background=(1.0, 1.0, 1.0), backend=backend)

    return f


def _forward_backward(g: Gaussians, cams: Cameras, backend: str) -> Callable[[], object]:
    from ..render import render

    def f():
        x = {k: getattr(g, k).detach().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "colors")}
        out = render(Gaussians(**x), cams, background=(1.0, 1.0, 1.0), backend=backend)
        (out.rgb.sum() + out.alpha.sum() + 0.1 * out.depth.sum()).backward()
        return out

    return f


def _visible(g: Gaussians, cams: Cameras) -> int:
    """Splats that reach ``cams``' image (radius > 0: the projection's own culling)."""
    from ..render.projection import project_gaussians

    with torch.no_grad():
        proj = project_gaussians(g.means, g.quats, g.scales, cams.K.reshape(-1, 3, 3), cams.w2c.reshape(-1, 4, 4), cams.width, cams.height)
    return int((proj.radii > 0).sum())


def _predict(g: Gaussians, res: int, backend: str, mode: str) -> float:
    """Seconds for one repeat extrapolated from a 64x64 centre crop of the image.

    Cost scales with the pixels, and for the dense ``reference`` backend with the splats that reach
    the image too: every visible splat is evaluated at every pixel. The crop sees only the splats
    over the middle of the head, so scaling by pixels alone predicted 5 s for a 35-68 s entry
    (10,000 splats at 256², measured 2026-12-06); the visible-splat ratio is now applied as well.
    """
    small = 64
    cams = bench_camera(res).crop((res - small) // 2, (res - small) // 2, small, small)
    fn = (_forward if mode == "forward" else _forward_backward)(g, cams, backend)
    t0 = time.perf_counter()
    fn()
    seconds = time.perf_counter() - t0
    scale = (res * res) / (small * small)
    if backend == "reference":
        scale *= _visible(g, bench_camera(res)) / max(1, _visible(g, cams))
    return seconds * scale


def run(args) -> dict:
    cfg = plan(args)
    sizes, resolutions, repeats, budget = cfg["sizes"], cfg["resolutions"], cfg["repeats"], cfg["budget"]
    from ..render.cpu_backend import num_threads

    rows = []
    print(f"render benchmark: torch threads {torch.get_num_threads()}, numba threads {num_threads()}, {repeats} repeats, median ms; "
          f"baselines skipped where one repeat is predicted > {budget:g} s")
    header = f"{'N':>9} {'res':>5} | " + " | ".join(f"{b + ' fwd':>18} {b + ' f+b':>18}" for b in BACKENDS)
    print(header, flush=True)
    for n in sizes:
        g = head_scene(n)
        for res in resolutions:
            cams = bench_camera(res)
            row: dict = {"n": n, "resolution": res}
            print(f"{n:>9} {res:>5} |", end="", flush=True)  # the row fills in cell by cell as entries finish
            for backend in BACKENDS:
                for mode, make in (("forward", _forward), ("forward_backward", _forward_backward)):
                    key = f"{backend}_{mode}_ms"
                    if backend == "reference" and res * res * n > REFERENCE_MAX_PAIRS:
                        row[key] = None
                        row[f"{backend}_{mode}_skipped"] = f"{res * res * n / 1e9:.1f}e9 pixel-splat pairs (dense, chunked to bound memory)"
                    elif backend != "cpu" and (est := _predict(g, res, backend, mode)) > budget:
                        row[key] = None
                        row[f"{backend}_{mode}_skipped"] = f"predicted {est:.0f} s per repeat > budget {budget:g} s"
                    else:
                        reps = repeats if backend == "cpu" else max(1, min(repeats, 3))
                        wall, cpu = _median_time(make(g, cams, backend), reps)
                        row[key] = 1000.0 * wall
                        row[f"{backend}_{mode}_cpu_ms"] = 1000.0 * cpu
                    v = row[key]
                    print(f" {v:18.1f}" if v is not None else f" {'skipped':>18}", end="", flush=True)
                if backend != BACKENDS[-1]:
                    print(" |", end="", flush=True)
            print(flush=True)
            if row.get("torch_tiles_forward_ms") and row.get("cpu_forward_ms"):
                row["speedup_forward_vs_torch_tiles"] = row["torch_tiles_forward_ms"] / row["cpu_forward_ms"]
            rows.append(row)

    summary = {}
    for row in rows:
        if row["n"] == 262_144 and row["resolution"] == 512:
            summary["render_cpu_forward_ms_262k_512"] = row["cpu_forward_ms"]
            summary["render_cpu_forward_backward_ms_262k_512"] = row["cpu_forward_backward_ms"]
            summary["render_speedup_vs_torch_tiles_262k_512"] = row.get("speedup_forward_vs_torch_tiles")
    return {"rows": rows, "repeats": repeats, "budget_s": budget, "torch_threads": torch.get_num_threads(), "numba_threads": num_threads(), "summary": summary}


def _parse(text: str | None, default: tuple[int, ...]) -> tuple[int, ...]:
    if not text:
        return tuple(default)
    try:
        vals = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"expected comma-separated integers, got {text!r}") from None
    if not vals or min(vals) <= 0:
        raise ValueError(f"expected positive integers, got {text!r}")
    return vals
