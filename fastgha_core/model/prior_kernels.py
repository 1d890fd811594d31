"""numba kernel of the expression prior's per-frame path (``PriorRuntime.frame``, CPU, no gradients).

One pass over the Gaussians writes what ``fastgha.FastGHA.animate`` hands to the rasterizer, in
place of the plain torch path (sparse ``[N, U]`` products for the displacement and the expression
shading, a ``[U, 3] @ [3, 3]`` product, the per-Gaussian opacity gather and ``torch.cat`` of the
reconstructed and interior parts, each a separate pass over ``N`` with its own allocation). Same
maths; only the order of the float32 operations differs (the fit's 3x3 matrix is folded into a
per-avatar copy of the blendshapes of the slots the avatar uses, ``PriorRuntime.compact``), so
positions and colours agree with the plain path to float32 rounding, opacities exactly. ``tests/test_prior.py`` checks it against the
plain path.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = ["prior_frame"]


@njit(parallel=True, cache=True, fastmath=False)
def prior_frame(means, colors, opac, dxyz, drgb, du, local, coef, gidx, table, n_rec, shade, lo, hi, out_means, out_colors, out_op):
    """The first ``n = out_means.shape[0]`` deformed Gaussians of one frame.

    Args:
        means ``[N, 3]``, colors ``[N, 3]``, opac ``[N]``: canonical Gaussians (float32).
        dxyz, drgb ``[n_rec, 3]``: the MLP's residual of the reconstructed Gaussians (any strides).
        du ``[U, 3]``: the blendshape displacement of every slot, in the avatar's frame.
        local ``[N, 3]`` int32 slots and coef ``[N, 3]`` float32 weights (barycentric * fade):
            ``displacement = sum_k coef_k du[local_k]``.
        gidx ``[N]`` int8 index into ``table [T]``, the per-group opacity factors of this frame.
        n_rec: Gaussians ``< n_rec`` get the MLP's residual and a clamped colour times the
            expression shading; the rest (mouth interior, eyelids) keep their colour.
        shade ``[U]``: the shading of every slot (``z @ shade_c``): the colour factor is
            ``clamp(1 + sum_k coef_k shade[local_k], lo, hi)``.
    Writes ``out_means [n, 3]``, ``out_colors [n, 3]``, ``out_op [n]``.
    """
    n = out_means.shape[0]
    zero, one = np.float32(0.0), np.float32(1.0)
    for i in prange(n):
        a, b, c = local[i, 0], local[i, 1], local[i, 2]
        wa, wb, wc = coef[i, 0], coef[i, 1], coef[i, 2]
        p0 = wa * du[a, 0] + wb * du[b, 0] + wc * du[c, 0]
        p1 = wa * du[a, 1] + wb * du[b, 1] + wc * du[c, 1]
        p2 = wa * du[a, 2] + wb * du[b, 2] + wc * du[c, 2]
        if i < n_rec:
            out_means[i, 0] = means[i, 0] + (p0 + dxyz[i, 0])
            out_means[i, 1] = means[i, 1] + (p1 + dxyz[i, 1])
            out_means[i, 2] = means[i, 2] + (p2 + dxyz[i, 2])
            r = one + (wa * shade[a] + wb * shade[b] + wc * shade[c])
            r = min(max(r, lo), hi)
            for q in range(3):
                out_colors[i, q] = min(max(min(max(colors[i, q] + drgb[i, q], zero), one) * r, zero), one)
        else:
            out_means[i, 0] = means[i, 0] + p0
            out_means[i, 1] = means[i, 1] + p1
            out_means[i, 2] = means[i, 2] + p2
            for q in range(3):
                out_colors[i, q] = colors[i, q]
        out_op[i] = opac[i] * table[gidx[i]]
    return 0
