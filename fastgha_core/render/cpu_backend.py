"""CPU backend: torch projection (autograd) + numba tile compositing (a torch.autograd.Function).

Without gradients and in float32 (the per-frame server path) ``rasterize_cpu`` takes a faster
path with the same rules: depth radix sort of the splats that can contribute, packed float32
records, branch-free SIMD compositing, no state kept for a backward pass
(``cpu_kernels.sort_pack`` / ``bin_sorted`` / ``raster_forward_fast``). It agrees with the
float64 kernels to float32 rounding (tested against the dense reference).

With gradients and in float32 (training, test-time refinement) it runs the same float32 forward
and ``cpu_kernels.raster_backward_fast``, which walks each tile front to back again and takes
the colour behind a splat from the final sums (one running sum per pixel, no transmittance
recovered by division).
Float64 inputs, and ``FASTGHA_RASTER_FAST=0``, keep the float64 kernels (``raster_forward`` /
``raster_backward``, the exact path the gradcheck test uses).

Threads: numba uses ``FASTGHA_NUMBA_THREADS`` threads when that environment variable is set,
else as many as torch (``torch.get_num_threads()``), capped by numba's pool size. The setting
is applied per call (``numba.set_num_threads`` is thread-local), never at import.
"""

from __future__ import annotations

import os
import time

import numba
import numpy as np
import torch
from torch import Tensor

from . import cpu_kernels as _K
from .projection import EPS2D, NEAR_PLANE, TILE_SIZE, Projected, tile_rects

__all__ = ["num_threads", "project_cpu", "bin_tiles_cpu", "rasterize_cpu", "rasterize_fast"]


def num_threads() -> int:
    """numba threads used by the CPU rasterizer (see the module docstring)."""
    env = os.environ.get("FASTGHA_NUMBA_THREADS")
    if env:
        try:
            n = int(env)
        except ValueError:
            raise ValueError(f"FASTGHA_NUMBA_THREADS must be a positive integer, got {env!r}") from None
    else:
        n = torch.get_num_threads()
    return max(1, min(n, numba.config.NUMBA_NUM_THREADS))


def _np(t: Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


def project_cpu(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    K: Tensor,  # [C, 3, 3]
    w2c: Tensor,  # [C, 4, 4]
    width: int,
    height: int,
    opacities: Tensor | None = None,  # [N]
) -> tuple[Projected, Tensor]:
    """``projection.project_gaussians`` + ``tile_rects`` in one numba pass, without gradients.

    With ``opacities``, Gaussians below ``ALPHA_MIN`` (which compositing skips at every pixel) are
    not projected: their radius is 0, their tile rect empty and their other outputs 0, so the
    rendered image is the same. Returns the projection and the tile rects ``[C, N, 4]``.
    """
    C, N = K.shape[0], means.shape[0]
    dtype = means.dtype
    m2d = torch.empty(C, N, 2, dtype=dtype)
    conic = torch.empty(C, N, 3, dtype=dtype)
    depth = torch.empty(C, N, dtype=dtype)
    radii = torch.empty(C, N, dtype=torch.int32)
    rects = torch.empty(C, N, 4, dtype=torch.int64)
    _K.project_forward(
        _np(means), _np(quats), _np(scales), _np(K).astype("float64"), _np(w2c).astype("float64"),
        width, height, NEAR_PLANE, EPS2D, m2d.numpy(), conic.numpy(), depth.numpy(), radii.numpy(), rects.numpy(),
        np.zeros(0, np.float32) if opacities is None else _np(opacities if opacities.dtype == torch.float64 else opacities.float()),
    )
    return Projected(m2d, conic, depth, radii), rects


def bin_tiles_cpu(proj: Projected, width: int, height: int, rects: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Sorted (splat, tile) intersections: ``offsets [C*TH*TW + 1]`` int64, ``ids [M]`` int32."""
    tw = (width + TILE_SIZE - 1) // TILE_SIZE
    th = (height + TILE_SIZE - 1) // TILE_SIZE
    if rects is None:
        rects = tile_rects(proj.means2d, proj.radii, width, height)  # [C, N, 4]
    order = torch.sort(proj.depths.detach(), dim=1, stable=True).indices  # [C, N] (depth, index) order
    offsets, ids = _K.bin_tiles(_np(rects), order.numpy(), th * tw, tw, numba.get_num_threads())
    return torch.from_numpy(offsets), torch.from_numpy(ids)


class _RasterizeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, values, offsets, ids, width, height):  # type: ignore[override]
        C, N, D = values.shape
        tw = (width + TILE_SIZE - 1) // TILE_SIZE
        dtype = values.dtype
        acc = np.empty((C, height, width, D), dtype=np.dtype(str(dtype).removeprefix("torch.")))
        T = np.empty((C, height, width), dtype=acc.dtype)
        ncon = np.empty((C, height, width), dtype=np.int32)
        m2, co, op, va = _np(means2d), _np(conics), _np(opacities), _np(values)
        _K.raster_forward(m2, co, op, va, offsets.numpy(), ids.numpy(), width, height, tw, acc, T, ncon)
        T_t, ncon_t = torch.from_numpy(T), torch.from_numpy(ncon)
        ctx.save_for_backward(means2d, conics, opacities, values, offsets, ids, T_t, ncon_t)
        ctx.size = (width, height)
        ctx.mark_non_differentiable(T_t)
        return torch.from_numpy(acc), 1.0 - T_t

    @staticmethod
    def backward(ctx, g_acc, g_alpha):  # type: ignore[override]
        means2d, conics, opacities, values, offsets, ids, T, ncon = ctx.saved_tensors
        width, height = ctx.size
        C, N, D = values.shape
        tw = (width + TILE_SIZE - 1) // TILE_SIZE
        if g_acc is None:
            g_acc = torch.zeros(C, height, width, D, dtype=values.dtype)
        if g_alpha is None:
            g_alpha = torch.zeros(C, height, width, dtype=values.dtype)
        isect = np.empty((ids.shape[0], _K.N_GRAD + D), dtype=np.float64)
        _K.raster_backward(
            _np(means2d), _np(conics), _np(opacities), _np(values), offsets.numpy(), ids.numpy(),
            width, height, tw, T.numpy(), ncon.numpy(), _np(g_acc), _np(g_alpha), isect,
        )
        g = _K.reduce_grads(offsets.numpy(), ids.numpy(), isect, C, N, numba.get_num_threads())
        g = torch.from_numpy(g).to(values.dtype)  # [C, N, N_GRAD + D]
        return g[..., 0:2], g[..., 2:5], g[..., 5].sum(0), g[..., _K.N_GRAD :], None, None, None, None


def rasterize_fast(
    proj: Projected,
    opacities: Tensor,  # [N] float32
    values: Tensor,  # [C, N, 4] float32
    width: int,
    height: int,
    rects: Tensor | None = None,  # [C, N, 4]
    stages: dict[str, float] | None = None,
) -> tuple[Tensor, Tensor]:
    """The no-gradient float32 path (see the module docstring): ``acc [C, H, W, 4]``, ``alpha [C, H, W]``.

    Call it inside the thread setting of ``rasterize_cpu`` (or use that, which picks this path).
    ``stages``: when given, the seconds of each kernel (pack, sort, gather, bin, composite) are
    added to it, and the counts of composited splats and tile intersections (``fastgha bench frame``).
    """
    C, N, D = values.shape
    if values.dtype != torch.float32 or D != 4:
        raise ValueError(f"rasterize_fast needs float32 values [C, N, 4], got {values.dtype} {list(values.shape)}")
    tw = (width + TILE_SIZE - 1) // TILE_SIZE
    th = (height + TILE_SIZE - 1) // TILE_SIZE
    if rects is None:
        rects = tile_rects(proj.means2d, proj.radii, width, height)  # [C, N, 4]
    acc = torch.empty(C, height, width, 4, dtype=torch.float32)
    T = torch.empty(C, height, width, dtype=torch.float32)
    n_chunks = numba.get_num_threads()
    op = _np(opacities.float())
    m2d_all, con_all, rect_all, val_all = _np(proj.means2d.float()), _np(proj.conics.float()), _np(rects), _np(values)
    bits_all = _np(proj.depths.float()).view(np.uint32)  # [C, N] depth bits
    rec_all = np.empty((N, _K.N_REC), np.float32)
    vis = np.empty(N, np.uint8)
    clock = _StageClock(stages)
    for c in range(C):
        _K.pack_splats(m2d_all[c], con_all[c], rect_all[c], op, val_all[c], rec_all, vis)
        clock.lap("pack")
        idx = _K.sort_visible(bits_all[c], vis)
        clock.lap("sort")
        rec, trect = _K.gather_rows(rec_all, rect_all[c], idx)
        clock.lap("gather")
        offsets, ids = _K.bin_sorted(trect, th * tw, tw, n_chunks)
        clock.lap("bin")
        _K.raster_forward_fast(rec, offsets, ids, width, height, tw, n_chunks, acc[c].numpy(), T[c].numpy())
        clock.lap("composite")
        clock.count("composited_splats", len(idx))
        clock.count("intersections", len(ids))
    return acc, T.neg_().add_(1.0)


class _RasterizeFast32(torch.autograd.Function):
    """The float32 gradient path: ``raster_forward_fast`` + ``raster_backward_fast`` (see cpu_kernels)."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, values, depths, rects, width, height):  # type: ignore[override]
        C, N, D = values.shape
        tw = (width + TILE_SIZE - 1) // TILE_SIZE
        th = (height + TILE_SIZE - 1) // TILE_SIZE
        n_chunks = numba.get_num_threads()
        acc = torch.empty(C, height, width, 4, dtype=torch.float32)
        T = torch.empty(C, height, width, dtype=torch.float32)
        op = _np(opacities.detach().float())
        m2d_all, con_all = _np(means2d.detach().float()), _np(conics.detach().float())
        val_all, rect_all = _np(values.detach().float()), _np(rects)
        bits_all = _np(depths.detach().float()).view(np.uint32)  # [C, N] depth bits
        saved = []
        for c in range(C):
            rec_all = np.empty((N, _K.N_REC), np.float32)
            vis = np.empty(N, np.uint8)
            _K.pack_splats(m2d_all[c], con_all[c], rect_all[c], op, val_all[c], rec_all, vis)
            idx = _K.sort_visible(bits_all[c], vis)
            rec, trect = _K.gather_rows(rec_all, rect_all[c], idx)
            offsets, ids = _K.bin_sorted(trect, th * tw, tw, n_chunks)
            _K.raster_forward_fast(rec, offsets, ids, width, height, tw, n_chunks, acc[c].numpy(), T[c].numpy())
            saved.append((rec, offsets, ids, idx))
        ctx.saved = saved
        ctx.meta = (C, N, width, height)
        ctx.save_for_backward(acc, T)
        ctx.mark_non_differentiable(T)
        return acc, 1.0 - T

    @staticmethod
    def backward(ctx, g_acc, g_alpha):  # type: ignore[override]
        acc, T = ctx.saved_tensors
        C, N, width, height = ctx.meta
        tw = (width + TILE_SIZE - 1) // TILE_SIZE
        g_acc = torch.zeros(C, height, width, 4) if g_acc is None else g_acc.float().contiguous()
        g_alpha = torch.zeros(C, height, width) if g_alpha is None else g_alpha.float().contiguous()
        prev = numba.get_num_threads()
        numba.set_num_threads(num_threads())
        try:
            n_chunks = numba.get_num_threads()
            g = torch.zeros(C, N, _K.N_GRAD32, dtype=torch.float64)
            for c, (rec, offsets, ids, idx) in enumerate(ctx.saved):
                isect = np.empty((ids.shape[0], _K.N_GRAD32), np.float32)
                _K.raster_backward_fast(
                    rec, offsets, ids, width, height, tw, n_chunks,
                    acc[c].numpy(), T[c].numpy(), g_acc[c].numpy(), g_alpha[c].numpy(), isect,
                )
                g[c, torch.from_numpy(idx)] = torch.from_numpy(_K.reduce_rows(ids, isect, idx.shape[0]))
        finally:
            numba.set_num_threads(prev)
        g = g.float()  # ctx.saved stays: a graph kept with retain_graph=True may run backward again
        # row layout: v0..v3, opacity, conic a, b, c, mx, my
        return g[..., 8:10], g[..., 5:8], g[..., 4].sum(0), g[..., 0:4], None, None, None, None


class _StageClock:
    """Adds the time since the previous lap to ``stages[name]``; does nothing when ``stages`` is None."""

    def __init__(self, stages: dict[str, float] | None) -> None:
        self.stages = stages
        self.t = time.perf_counter() if stages is not None else 0.0

    def lap(self, name: str) -> None:
        if self.stages is not None:
            t = time.perf_counter()
            self.stages[name] = self.stages.get(name, 0.0) + (t - self.t)
            self.t = t

    def count(self, name: str, n: int) -> None:
        if self.stages is not None:
            self.stages[name] = self.stages.get(name, 0) + n


def _wants_fast(opacities: Tensor, values: Tensor, *more: Tensor) -> bool:
    if values.dtype != torch.float32 or values.shape[-1] != 4:
        return False
    if torch.is_grad_enabled() and any(t.requires_grad for t in (opacities, values, *more)):
        return False
    return os.environ.get("FASTGHA_RASTER_FAST", "1") != "0"


def _wants_fast_grad(values: Tensor) -> bool:
    if values.dtype != torch.float32 or values.shape[-1] != 4:
        return False
    return os.environ.get("FASTGHA_RASTER_FAST", "1") != "0"


def rasterize_cpu(
    proj: Projected,
    opacities: Tensor,  # [N]
    values: Tensor,  # [C, N, D]
    width: int,
    height: int,
    rects: Tensor | None = None,  # [C, N, 4] from project_cpu, else computed here
    fast: bool | None = None,
) -> tuple[Tensor, Tensor]:
    """Tile compositing with the numba kernels. Returns ``acc [C, H, W, D]`` and ``alpha [C, H, W]``.

    ``fast``: ``None`` picks the no-gradient float32 path when it applies (float32, D = 4, no
    gradient needed; ``FASTGHA_RASTER_FAST=0`` turns it off), ``False`` never takes it.
    """
    if values.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"the cpu backend supports float32 and float64, got {values.dtype}")
    prev = numba.get_num_threads()
    numba.set_num_threads(num_threads())
    try:
        if fast is not False and _wants_fast(opacities, values, proj.means2d, proj.conics):
            return rasterize_fast(proj, opacities, values, width, height, rects)
        if fast is not False and _wants_fast_grad(values):
            if rects is None:
                rects = tile_rects(proj.means2d, proj.radii, width, height)
            return _RasterizeFast32.apply(proj.means2d, proj.conics, opacities, values, proj.depths, rects, width, height)
        offsets, ids = bin_tiles_cpu(proj, width, height, rects)
        return _RasterizeCPU.apply(proj.means2d, proj.conics, opacities, values, offsets, ids, width, height)
    finally:
        numba.set_num_threads(prev)
