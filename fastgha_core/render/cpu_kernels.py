"""numba kernels of the CPU rasterizer: tile binning, forward and backward compositing.

All kernels are ``@njit(parallel=True, cache=True, fastmath=False)`` and parallel over
16x16 tiles (``prange``). Gradients are deterministic: every (tile, splat) intersection is
owned by exactly one thread, which writes its gradient into its own row of a per-intersection
buffer; a second pass sums those rows per splat in a fixed order.

Internal arithmetic is float64 whatever the input dtype (float32 or float64).

Rules (see ``projection.py`` and ``compositing.py``; identical to the torch backends):
``sigma = 0.5 (a dx^2 + c dy^2) + b dx dy`` with ``(dx, dy) = mean2d - pixel centre``;
``alpha = min(ALPHA_MAX, o exp(-sigma))``; skip when ``sigma < 0`` or ``alpha < ALPHA_MIN``;
stop (without compositing) when ``T (1 - alpha) <= T_MIN``.

Speed: a splat is only evaluated on the pixels of its tile that lie inside the box where
``o exp(-sigma) >= ALPHA_MIN`` is possible (plus a one-pixel margin) and ``exp`` is not
evaluated where ``sigma`` is surely above ``log(255 o)``; both are exact shortcuts of the
skip rule, so the result equals evaluating every pixel of the tile.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .projection import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE_SIZE

__all__ = ["project_forward", "bin_tiles", "raster_forward", "raster_backward", "reduce_grads", "N_GRAD"]

_TS = TILE_SIZE
_NPIX = TILE_SIZE * TILE_SIZE
_LOG_INV_AMIN = math.log(1.0 / ALPHA_MIN)  # log(255)
N_GRAD = 6  # per-splat gradient slots before the values: mx, my, conic a, b, c, opacity


@njit(cache=True, fastmath=False)
def _box(o, A, B, Cc, mx, my, x0, y0, x1, y1):
    """Pixel box [jx0, jx1) x [iy0, iy1) of tile pixels where alpha >= ALPHA_MIN is possible,
    and the sigma threshold above which alpha < ALPHA_MIN for sure."""
    thresh = math.log(o) + _LOG_INV_AMIN  # alpha >= ALPHA_MIN needs sigma <= thresh
    det = A * Cc - B * B
    if det <= 0.0 or not (thresh >= 0.0):
        return x0, x0, y0, y0, -1.0
    ext2 = 2.0 * thresh * 1.0001 + 1e-6
    hx = math.sqrt(ext2 * Cc / det) + 1.0
    hy = math.sqrt(ext2 * A / det) + 1.0
    fx0 = math.floor(mx - hx - 0.5)
    fx1 = math.ceil(mx + hx - 0.5) + 1.0
    fy0 = math.floor(my - hy - 0.5)
    fy1 = math.ceil(my + hy - 0.5) + 1.0
    jx0 = x0 if fx0 < x0 else (x1 if fx0 > x1 else int(fx0))
    jx1 = x0 if fx1 < x0 else (x1 if fx1 > x1 else int(fx1))
    iy0 = y0 if fy0 < y0 else (y1 if fy0 > y1 else int(fy0))
    iy1 = y0 if fy1 < y0 else (y1 if fy1 > y1 else int(fy1))
    return jx0, jx1, iy0, iy1, thresh * (1.0 + 1e-6) + 1e-6


@njit(cache=True, fastmath=False)
def _row_span(A, B, Cc, sig_max, mx, dy, jx0, jx1):
    """Columns [j0, j1) of one pixel row (offset dy) where sigma <= sig_max is possible (+1 px margin)."""
    disc = B * B * dy * dy - A * (Cc * dy * dy - 2.0 * sig_max)
    if not (disc >= 0.0) or not (A > 0.0):
        return jx0, jx0
    sq = math.sqrt(disc)
    lo = mx - (-B * dy + sq) / A - 0.5 - 1.0
    hi = mx - (-B * dy - sq) / A - 0.5 + 2.0
    j0 = jx0 if lo < jx0 else (jx1 if lo > jx1 else int(math.floor(lo)))
    j1 = jx0 if hi < jx0 else (jx1 if hi > jx1 else int(math.ceil(hi)))
    return max(j0, jx0), min(j1, jx1)


@njit(cache=True, fastmath=False)
def _tile_of(t, tw, tpc, width, height):
    c = t // tpc
    r = t - c * tpc
    ty = r // tw
    tx = r - ty * tw
    x0 = tx * _TS
    y0 = ty * _TS
    return c, x0, y0, min(x0 + _TS, width), min(y0 + _TS, height)


@njit(parallel=True, cache=True, fastmath=False)
def bin_tiles(rects, order, tpc, tw, n_chunks):
    """List (splat, tile) intersections, each tile's list in depth order.

    Args:
        rects: ``[C, N, 4]`` int64 tile rectangles (x0, y0, x1, y1), end-exclusive.
        order: ``[C, N]`` int64 splat indices of each camera in (depth, index) order.
        tpc: tiles per camera; tw: tiles per row; n_chunks: parallel chunks for listing.
    Returns:
        offsets ``[C*tpc + 1]`` int64 and ids ``[M]`` int32 (splat index within its camera).
        Chunks of the ordered sequence fill disjoint, consecutive slots of each tile, so every
        list keeps the depth order and the result does not depend on ``n_chunks``.
    """
    C, N = order.shape
    n_tiles = C * tpc
    total = C * N
    csize = (total + n_chunks - 1) // n_chunks
    counts = np.zeros((n_chunks, n_tiles), np.int64)
    for ch in prange(n_chunks):
        for f in range(ch * csize, min(total, (ch + 1) * csize)):
            c = f // N
            g = order[c, f - c * N]
            for ty in range(rects[c, g, 1], rects[c, g, 3]):
                base = c * tpc + ty * tw
                for tx in range(rects[c, g, 0], rects[c, g, 2]):
                    counts[ch, base + tx] += 1
    offsets = np.zeros(n_tiles + 1, np.int64)
    cursor = np.empty((n_chunks, n_tiles), np.int64)
    run = 0
    for t in range(n_tiles):
        offsets[t] = run
        for ch in range(n_chunks):
            cursor[ch, t] = run
            run += counts[ch, t]
    offsets[n_tiles] = run
    ids = np.empty(run, np.int32)
    for ch in prange(n_chunks):
        for f in range(ch * csize, min(total, (ch + 1) * csize)):
            c = f // N
            g = order[c, f - c * N]
            for ty in range(rects[c, g, 1], rects[c, g, 3]):
                base = c * tpc + ty * tw
                for tx in range(rects[c, g, 0], rects[c, g, 2]):
                    ids[cursor[ch, base + tx]] = g
                    cursor[ch, base + tx] += 1
    return offsets, ids


@njit(parallel=True, cache=True, fastmath=False)
def raster_forward(means2d, conics, opac, values, offsets, ids, width, height, tw, out_acc, out_T, out_n):
    """Front-to-back compositing per tile.

    Args:
        means2d ``[C, N, 2]``, conics ``[C, N, 3]``, opac ``[N]``, values ``[C, N, D]``,
        offsets/ids from ``bin_tiles``.
    Writes:
        out_acc ``[C, H, W, D]`` premultiplied sums, out_T ``[C, H, W]`` final transmittance,
        out_n ``[C, H, W]`` int32: one past the position (in the tile's list) of the last
        composited splat.
    """
    n_tiles = offsets.shape[0] - 1
    C = means2d.shape[0]
    tpc = n_tiles // C
    D = values.shape[2]
    for t in prange(n_tiles):
        c, x0, y0, x1, y1 = _tile_of(t, tw, tpc, width, height)
        acc = np.zeros((_NPIX, D))
        T = np.ones(_NPIX)
        done = np.zeros(_NPIX, np.bool_)
        ncon = np.zeros(_NPIX, np.int32)
        vals = np.empty(D)
        n_pix = (x1 - x0) * (y1 - y0)
        n_done = 0
        s = offsets[t]
        for k in range(s, offsets[t + 1]):
            g = ids[k]
            o = float(opac[g])
            if not (o >= ALPHA_MIN):
                continue
            mx = float(means2d[c, g, 0])
            my = float(means2d[c, g, 1])
            A = float(conics[c, g, 0])
            B = float(conics[c, g, 1])
            Cc = float(conics[c, g, 2])
            jx0, jx1, iy0, iy1, sig_max = _box(o, A, B, Cc, mx, my, x0, y0, x1, y1)
            for d in range(D):
                vals[d] = values[c, g, d]
            for i in range(iy0, iy1):
                dy = my - (i + 0.5)
                prow = (i - y0) * _TS - x0
                j0, j1 = _row_span(A, B, Cc, sig_max, mx, dy, jx0, jx1)
                for j in range(j0, j1):
                    p = prow + j
                    if done[p]:
                        continue
                    dx = mx - (j + 0.5)
                    sigma = 0.5 * (A * dx * dx + Cc * dy * dy) + B * dx * dy
                    if sigma < 0.0 or sigma > sig_max:
                        continue
                    alpha = o * math.exp(-sigma)
                    if alpha > ALPHA_MAX:
                        alpha = ALPHA_MAX
                    if alpha < ALPHA_MIN:
                        continue
                    Tp = T[p]
                    nT = Tp * (1.0 - alpha)
                    if nT <= T_MIN:
                        done[p] = True
                        n_done += 1
                        continue
                    w = alpha * Tp
                    for d in range(D):
                        acc[p, d] += vals[d] * w
                    T[p] = nT
                    ncon[p] = k - s + 1
            if n_done == n_pix:
                break
        for i in range(y0, y1):
            for j in range(x0, x1):
                p = (i - y0) * _TS + (j - x0)
                for d in range(D):
                    out_acc[c, i, j, d] = acc[p, d]
                out_T[c, i, j] = T[p]
                out_n[c, i, j] = ncon[p]


@njit(parallel=True, cache=True, fastmath=False)
def raster_backward(means2d, conics, opac, values, offsets, ids, width, height, tw, T_final, ncon, g_acc, g_alpha, out_g):
    """Back-to-front gradient pass per tile (the transmittance is recovered by division).

    Args:
        as ``raster_forward`` plus its outputs ``T_final [C, H, W]``, ``ncon [C, H, W]`` and the
        incoming gradients ``g_acc [C, H, W, D]``, ``g_alpha [C, H, W]`` (for alpha = 1 - T_final).
    Writes:
        out_g ``[M, N_GRAD + D]`` float64, one row per intersection (zero where it got none):
        d/d(mx, my, conic a, b, c, opacity, values...).
    """
    n_tiles = offsets.shape[0] - 1
    C = means2d.shape[0]
    tpc = n_tiles // C
    D = values.shape[2]
    for t in prange(n_tiles):
        c, x0, y0, x1, y1 = _tile_of(t, tw, tpc, width, height)
        s = offsets[t]
        e = offsets[t + 1]
        if e == s:
            continue
        T = np.ones(_NPIX)
        Tf = np.ones(_NPIX)
        S = np.zeros((_NPIX, D))
        gA_pix = np.zeros((_NPIX, D))
        gal = np.zeros(_NPIX)
        nc = np.zeros(_NPIX, np.int32)
        gv = np.zeros(D)
        vals = np.empty(D)
        n_max = 0
        for i in range(y0, y1):
            for j in range(x0, x1):
                p = (i - y0) * _TS + (j - x0)
                T[p] = T_final[c, i, j]
                Tf[p] = T_final[c, i, j]
                gal[p] = g_alpha[c, i, j]
                nc[p] = ncon[c, i, j]
                n_max = max(n_max, nc[p])
                for d in range(D):
                    gA_pix[p, d] = g_acc[c, i, j, d]
        for k in range(s + n_max, e):
            for q in range(N_GRAD + D):
                out_g[k, q] = 0.0
        for k in range(s + n_max - 1, s - 1, -1):
            kk = k - s
            g = ids[k]
            o = float(opac[g])
            gmx = 0.0
            gmy = 0.0
            ga = 0.0
            gb = 0.0
            gc = 0.0
            go = 0.0
            for d in range(D):
                gv[d] = 0.0
            if o >= ALPHA_MIN:
                mx = float(means2d[c, g, 0])
                my = float(means2d[c, g, 1])
                A = float(conics[c, g, 0])
                B = float(conics[c, g, 1])
                Cc = float(conics[c, g, 2])
                jx0, jx1, iy0, iy1, sig_max = _box(o, A, B, Cc, mx, my, x0, y0, x1, y1)
                for d in range(D):
                    vals[d] = values[c, g, d]
                for i in range(iy0, iy1):
                    dy = my - (i + 0.5)
                    prow = (i - y0) * _TS - x0
                    j0, j1 = _row_span(A, B, Cc, sig_max, mx, dy, jx0, jx1)
                    for j in range(j0, j1):
                        p = prow + j
                        if kk >= nc[p]:
                            continue
                        dx = mx - (j + 0.5)
                        sigma = 0.5 * (A * dx * dx + Cc * dy * dy) + B * dx * dy
                        if sigma < 0.0 or sigma > sig_max:
                            continue
                        G = math.exp(-sigma)
                        raw = o * G
                        alpha = ALPHA_MAX if raw > ALPHA_MAX else raw
                        if alpha < ALPHA_MIN:
                            continue
                        ra = 1.0 / (1.0 - alpha)
                        Ti = T[p] * ra
                        w = alpha * Ti
                        dal = gal[p] * Tf[p] * ra
                        for d in range(D):
                            v = vals[d]
                            gd = gA_pix[p, d]
                            gv[d] += w * gd
                            dal += gd * (v * Ti - S[p, d] * ra)
                            S[p, d] += v * w
                        T[p] = Ti
                        if raw <= ALPHA_MAX:
                            dsig = -dal * raw
                            go += dal * G
                            ga += 0.5 * dx * dx * dsig
                            gc += 0.5 * dy * dy * dsig
                            gb += dx * dy * dsig
                            gmx += (A * dx + B * dy) * dsig
                            gmy += (Cc * dy + B * dx) * dsig
            out_g[k, 0] = gmx
            out_g[k, 1] = gmy
            out_g[k, 2] = ga
            out_g[k, 3] = gb
            out_g[k, 4] = gc
            out_g[k, 5] = go
            for d in range(D):
                out_g[k, N_GRAD + d] = gv[d]


@njit(parallel=True, cache=True, fastmath=False)
def reduce_grads(offsets, ids, isect_g, C, N, n_chunks):
    """Sum per-intersection gradient rows ``[M, K]`` into ``[C, N, K]`` in a fixed order.

    Thread ``ch`` owns splats ``g % n_chunks == ch`` and scans all rows in order, so the sum
    order (and the result) does not depend on the thread count.
    """
    K = isect_g.shape[1]
    out = np.zeros((C, N, K))
    n_tiles = offsets.shape[0] - 1
    tpc = n_tiles // C
    for ch in prange(n_chunks):
        for c in range(C):
            for k in range(offsets[c * tpc], offsets[(c + 1) * tpc]):
                g = ids[k]
                if g % n_chunks == ch:
                    for q in range(K):
                        out[c, g, q] += isect_g[k, q]
    return out


@njit(parallel=True, cache=True, fastmath=False)
def project_forward(means, quats, scales, K, w2c, width, height, near, eps2d, out_m2d, out_conic, out_depth, out_radii, out_rect, opac):
    """No-gradient projection, the same maths as ``projection.project_gaussians`` + ``tile_rects``.

    Args: means ``[N, 3]``, quats ``[N, 4]``, scales ``[N, 3]``, K ``[C, 3, 3]``, w2c ``[C, 4, 4]``;
    opac ``[N]`` or ``[0]``: when given, a Gaussian with opacity below ``ALPHA_MIN`` (which the
    compositing skips everywhere) is not projected: its outputs are zeros (radius 0, empty rect).
    Writes: ``out_m2d [C, N, 2]``, ``out_conic [C, N, 3]``, ``out_depth [C, N]``,
    ``out_radii [C, N]`` int32, ``out_rect [C, N, 4]`` int64.
    """
    N = means.shape[0]
    C = K.shape[0]
    tw = (width + _TS - 1) // _TS
    th = (height + _TS - 1) // _TS
    skip_faint = opac.shape[0] > 0
    for n in prange(N):
        if skip_faint and not (float(opac[n]) >= ALPHA_MIN):
            for c in range(C):
                out_radii[c, n] = 0
                out_depth[c, n] = 0.0
                for q in range(4):
                    out_rect[c, n, q] = 0
                for q in range(2):
                    out_m2d[c, n, q] = 0.0
                for q in range(3):
                    out_conic[c, n, q] = 0.0
            continue
        qw, qx, qy, qz = float(quats[n, 0]), float(quats[n, 1]), float(quats[n, 2]), float(quats[n, 3])
        qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qn = max(qn, 1e-12)
        qw, qx, qy, qz = qw / qn, qx / qn, qy / qn, qz / qn
        r00 = 1 - 2 * (qy * qy + qz * qz)
        r01 = 2 * (qx * qy - qw * qz)
        r02 = 2 * (qx * qz + qw * qy)
        r10 = 2 * (qx * qy + qw * qz)
        r11 = 1 - 2 * (qx * qx + qz * qz)
        r12 = 2 * (qy * qz - qw * qx)
        r20 = 2 * (qx * qz - qw * qy)
        r21 = 2 * (qy * qz + qw * qx)
        r22 = 1 - 2 * (qx * qx + qy * qy)
        sx, sy, sz = float(scales[n, 0]), float(scales[n, 1]), float(scales[n, 2])
        # M = Rq diag(s); cov3 = M M^T
        m00, m01, m02 = r00 * sx, r01 * sy, r02 * sz
        m10, m11, m12 = r10 * sx, r11 * sy, r12 * sz
        m20, m21, m22 = r20 * sx, r21 * sy, r22 * sz
        s00 = m00 * m00 + m01 * m01 + m02 * m02
        s01 = m00 * m10 + m01 * m11 + m02 * m12
        s02 = m00 * m20 + m01 * m21 + m02 * m22
        s11 = m10 * m10 + m11 * m11 + m12 * m12
        s12 = m10 * m20 + m11 * m21 + m12 * m22
        s22 = m20 * m20 + m21 * m21 + m22 * m22
        mx, my, mz = float(means[n, 0]), float(means[n, 1]), float(means[n, 2])
        for c in range(C):
            out_radii[c, n] = 0
            for q in range(4):
                out_rect[c, n, q] = 0
            R = w2c[c]
            x = R[0, 0] * mx + R[0, 1] * my + R[0, 2] * mz + R[0, 3]
            y = R[1, 0] * mx + R[1, 1] * my + R[1, 2] * mz + R[1, 3]
            z = R[2, 0] * mx + R[2, 1] * my + R[2, 2] * mz + R[2, 3]
            out_depth[c, n] = z
            fx, fy, cx, cy = float(K[c, 0, 0]), float(K[c, 1, 1]), float(K[c, 0, 2]), float(K[c, 1, 2])
            if not (z >= near):
                out_m2d[c, n, 0] = 0.0
                out_m2d[c, n, 1] = 0.0
                for q in range(3):
                    out_conic[c, n, q] = 0.0
                continue
            rz = 1.0 / z
            tan_fovx = 0.5 * width / fx
            tan_fovy = 0.5 * height / fy
            lxp = (width - cx) / fx + 0.3 * tan_fovx
            lxn = cx / fx + 0.3 * tan_fovx
            lyp = (height - cy) / fy + 0.3 * tan_fovy
            lyn = cy / fy + 0.3 * tan_fovy
            tx = z * min(lxp, max(-lxn, x * rz))
            ty = z * min(lyp, max(-lyn, y * rz))
            j00 = fx * rz
            j02 = -fx * tx * rz * rz
            j11 = fy * rz
            j12 = -fy * ty * rz * rz
            # T = J W (2x3), W = rotation part of w2c
            t00 = j00 * R[0, 0] + j02 * R[2, 0]
            t01 = j00 * R[0, 1] + j02 * R[2, 1]
            t02 = j00 * R[0, 2] + j02 * R[2, 2]
            t10 = j11 * R[1, 0] + j12 * R[2, 0]
            t11 = j11 * R[1, 1] + j12 * R[2, 1]
            t12 = j11 * R[1, 2] + j12 * R[2, 2]
            # cov2 = T S T^T
            u0 = t00 * s00 + t01 * s01 + t02 * s02
            u1 = t00 * s01 + t01 * s11 + t02 * s12
            u2 = t00 * s02 + t01 * s12 + t02 * s22
            a = u0 * t00 + u1 * t01 + u2 * t02 + eps2d
            b = u0 * t10 + u1 * t11 + u2 * t12
            v0 = t10 * s00 + t11 * s01 + t12 * s02
            v1 = t10 * s01 + t11 * s11 + t12 * s12
            v2 = t10 * s02 + t11 * s12 + t12 * s22
            cc = v0 * t10 + v1 * t11 + v2 * t12 + eps2d
            det = a * cc - b * b
            u = fx * x * rz + cx
            v = fy * y * rz + cy
            out_m2d[c, n, 0] = u
            out_m2d[c, n, 1] = v
            if not (det > 0.0):
                for q in range(3):
                    out_conic[c, n, q] = 0.0
                continue
            out_conic[c, n, 0] = cc / det
            out_conic[c, n, 1] = -b / det
            out_conic[c, n, 2] = a / det
            half = 0.5 * (a + cc)
            lam = half + math.sqrt(max(half * half - det, 0.01))
            radius = math.ceil(3.0 * math.sqrt(lam))
            if not (radius > 0.0 and radius < 1e9):
                continue
            if u + radius <= 0 or u - radius >= width or v + radius <= 0 or v - radius >= height:
                continue
            out_radii[c, n] = int(radius)
            rt = radius / _TS
            gx = u / _TS
            gy = v / _TS
            x0 = min(max(math.floor(gx - rt), 0.0), float(tw))
            x1 = min(max(math.ceil(gx + rt), 0.0), float(tw))
            y0 = min(max(math.floor(gy - rt), 0.0), float(th))
            y1 = min(max(math.ceil(gy + rt), 0.0), float(th))
            out_rect[c, n, 0] = int(x0)
            out_rect[c, n, 1] = int(y0)
            out_rect[c, n, 2] = int(x1)
            out_rect[c, n, 3] = int(y1)


# ---------------------------------------------------------------------------------------------
# No-gradient float32 fast path (``cpu_backend.rasterize_cpu`` picks it for float32 inputs when
# no gradient is needed). Same rules as above; what changes is how the work is laid out:
#
# - only splats that can contribute (listed in a tile and opacity >= ALPHA_MIN) are kept, radix
#   sorted by the bits of their float32 depth (stable: ties keep index order, like torch.sort);
# - their screen-space parameters are packed, in depth order, into one float32 record per splat,
#   and the pixel box where alpha >= ALPHA_MIN is possible is computed once per splat;
# - the compositing inner loop runs over whole 16-pixel tile rows without branches, with a
#   polynomial exp (relative error < 1e-6), so LLVM turns it into SIMD code;
# - each tile row keeps a bit mask of its live pixels, and a splat skips a row none of whose live
#   pixels lies in its box columns (e.g. splats behind a surface whose pixels stopped, in rows that
#   are still live elsewhere): exact, since outside its box a splat's alpha is below ALPHA_MIN;
# - the record of the splat four places ahead in a tile's list is loaded early, so its cache miss
#   overlaps the current splat's rows (composite -10 % at 256² on served frames, same output);
# - no per-pixel state for the backward pass is kept.
# ---------------------------------------------------------------------------------------------

_F32 = np.float32
_HALF = _F32(0.5)
_ONE = _F32(1.0)
_ZERO = _F32(0.0)
_AMAX = _F32(ALPHA_MAX)
_AMIN = _F32(ALPHA_MIN)
_TMIN = _F32(T_MIN)
_SIG_CLAMP = _F32(12.0)  # exp(-12) < ALPHA_MIN: anything beyond is skipped whatever the opacity
_LOG2E = _F32(1.4426950408889634)
_LN2 = _F32(0.6931471805599453)
# exp(-x) on |x| <= ln2/2 (Taylor to degree 7: relative error < 2e-9 before float32 rounding)
_E1, _E2, _E3 = _F32(-1.0), _F32(1.0 / 2), _F32(-1.0 / 6)
_E4, _E5, _E6, _E7 = _F32(1.0 / 24), _F32(-1.0 / 120), _F32(1.0 / 720), _F32(-1.0 / 5040)


@njit(cache=True, fastmath=False, inline="always")
def _exp_neg32(s):
    """``exp(-s)`` for float32 ``s >= 0`` (clamped at 12) without a libm call, so loops vectorise."""
    t = min(s, _SIG_CLAMP) * _LOG2E  # [0, 17.4]
    k = np.int32(t + _HALF)  # round to nearest, >= 0
    x = (t - _F32(k)) * _LN2  # |x| <= ln2 / 2
    p = _ONE + x * (_E1 + x * (_E2 + x * (_E3 + x * (_E4 + x * (_E5 + x * (_E6 + x * _E7))))))
    # times 2^-k, k in [0, 17], by selects (vectorisable, unlike ldexp)
    p = p * (_F32(0.5) if (k & 1) else _ONE)
    p = p * (_F32(0.25) if (k & 2) else _ONE)
    p = p * (_F32(1.0 / 16) if (k & 4) else _ONE)
    p = p * (_F32(1.0 / 256) if (k & 8) else _ONE)
    p = p * (_F32(1.0 / 65536) if (k & 16) else _ONE)
    return p


@njit(cache=True, fastmath=False)
def exp_neg32(s):
    """Vector form of ``_exp_neg32`` for tests: ``s [M]`` float32 -> ``[M]`` float32."""
    out = np.empty_like(s)
    for i in range(s.shape[0]):
        out[i] = _exp_neg32(s[i])
    return out


R_BOX = 10  # rec[:, R_BOX:R_BOX + 4] = pixel box (x0, x1, y0, y1) stored as float32 integers
N_REC = 16  # packed splat record (one 64-byte line): mx, my, conic a, b, c, opacity, values x4, box x4, 2 spare


@njit(parallel=True, cache=True, fastmath=False)
def pack_splats(m2d, conic, rects, opac, values, rec, vis):
    """Per-splat records in index order (one camera).

    Args:
        m2d ``[N, 2]``, conic ``[N, 3]``, rects ``[N, 4]`` int64 tile rects, opac ``[N]``, values ``[N, 4]``.
    Writes:
        rec ``[N, N_REC]`` float32; vis ``[N]`` uint8: listed in a tile and opacity >= ALPHA_MIN
        (such a splat has depth >= NEAR_PLANE > 0, so ``sort_visible`` may sort float32 depth bits). The box holds the pixel centres where ``sigma <= log(255 o)``
        (alpha >= ALPHA_MIN) is possible, with 1e-4 relative + 1e-3 px slack for float32 rounding.
    """
    N = m2d.shape[0]
    for n in prange(N):
        o = float(opac[n])
        mx, my = float(m2d[n, 0]), float(m2d[n, 1])
        A, B, Cc = float(conic[n, 0]), float(conic[n, 1]), float(conic[n, 2])
        rec[n, 0], rec[n, 1], rec[n, 2], rec[n, 3], rec[n, 4], rec[n, 5] = mx, my, A, B, Cc, o
        for d in range(4):
            rec[n, 6 + d] = values[n, d]
        for q in range(4):
            rec[n, R_BOX + q] = 0.0
        rec[n, 14] = 0.0
        rec[n, 15] = 0.0
        ok = rects[n, 2] > rects[n, 0] and rects[n, 3] > rects[n, 1] and o >= ALPHA_MIN
        thresh = math.log(o) + _LOG_INV_AMIN if o > 0.0 else -1.0
        det = A * Cc - B * B
        if not ok or det <= 0.0 or not (thresh >= 0.0):
            vis[n] = 0
            continue
        vis[n] = 1
        hx = math.sqrt(2.0 * thresh * Cc / det) * 1.0001 + 1e-3
        hy = math.sqrt(2.0 * thresh * A / det) * 1.0001 + 1e-3
        lim = 8388608.0  # 2^23: exact in float32
        rec[n, R_BOX + 0] = max(-lim, math.ceil(mx - 0.5 - hx))
        rec[n, R_BOX + 1] = min(lim, math.floor(mx - 0.5 + hx) + 1.0)
        rec[n, R_BOX + 2] = max(-lim, math.ceil(my - 0.5 - hy))
        rec[n, R_BOX + 3] = min(lim, math.floor(my - 0.5 + hy) + 1.0)
    return 0


@njit(cache=True, fastmath=False)
def sort_visible(keys, vis):
    """Indices ``[M]`` int64 of the splats with ``vis``, stably sorted by ``keys`` (LSD radix, 3 x 11 bits).

    ``keys [N]`` uint32: the bits of positive float32 depths (a ``view``), whose integer order is
    their order as floats; ties keep index order, as ``torch.sort(stable=True)`` does.
    """
    N = keys.shape[0]
    m = 0
    for n in range(N):
        m += vis[n]
    idx = np.empty(m, np.int64)
    key = np.empty(m, np.uint32)
    m = 0
    for n in range(N):
        if vis[n]:
            idx[m] = n
            key[m] = keys[n]
            m += 1
    idx2 = np.empty_like(idx)
    key2 = np.empty_like(key)
    for shift in (0, 11, 22):
        cnt = np.zeros(2049, np.int64)
        for i in range(m):
            cnt[((key[i] >> shift) & 2047) + 1] += 1
        for b in range(2048):
            cnt[b + 1] += cnt[b]
        for i in range(m):
            b = (key[i] >> shift) & 2047
            dst = cnt[b]
            cnt[b] = dst + 1
            idx2[dst] = idx[i]
            key2[dst] = key[i]
        idx, idx2 = idx2, idx
        key, key2 = key2, key
    return idx


@njit(parallel=True, cache=True, fastmath=False)
def gather_rows(rec_all, rects, idx):
    """``rec_all[idx]`` ``[M, N_REC]`` float32 and ``rects[idx]`` as ``[M, 4]`` int32, in parallel."""
    M = idx.shape[0]
    K = rec_all.shape[1]
    rec = np.empty((M, K), np.float32)
    trect = np.empty((M, 4), np.int32)
    for r in prange(M):
        g = idx[r]
        for q in range(K):
            rec[r, q] = rec_all[g, q]
        for q in range(4):
            trect[r, q] = rects[g, q]
    return rec, trect


@njit(parallel=True, cache=True, fastmath=False)
def bin_sorted(trect, n_tiles, tw, n_chunks):
    """Tile lists of packed splats (already in depth order): ``offsets [n_tiles + 1]``, ``ids [M]`` int32."""
    M = trect.shape[0]
    csize = (M + n_chunks - 1) // n_chunks
    counts = np.zeros((n_chunks, n_tiles), np.int64)
    for ch in prange(n_chunks):
        for r in range(ch * csize, min(M, (ch + 1) * csize)):
            for ty in range(trect[r, 1], trect[r, 3]):
                for tx in range(trect[r, 0], trect[r, 2]):
                    counts[ch, ty * tw + tx] += 1
    offsets = np.zeros(n_tiles + 1, np.int64)
    cursor = np.empty((n_chunks, n_tiles), np.int64)
    run = 0
    for t in range(n_tiles):
        offsets[t] = run
        for ch in range(n_chunks):
            cursor[ch, t] = run
            run += counts[ch, t]
    offsets[n_tiles] = run
    ids = np.empty(run, np.int32)
    for ch in prange(n_chunks):
        for r in range(ch * csize, min(M, (ch + 1) * csize)):
            for ty in range(trect[r, 1], trect[r, 3]):
                for tx in range(trect[r, 0], trect[r, 2]):
                    t = ty * tw + tx
                    ids[cursor[ch, t]] = r
                    cursor[ch, t] += 1
    return offsets, ids


@njit(cache=True, fastmath=False, inline="always")
def _splat_px(S, jj, dx, hA, cy, by, o):
    """The compositing decision of one splat at column ``jj`` of a tile row ``S`` (``S[0]`` = T,
    ``S[1]`` = live), shared by the forward and the backward so both take it in the same float32
    operations. Returns ``(G, raw, al, Tp, nT, stop, comp, w)``: ``G = exp(-sigma)``, ``raw = o G``,
    ``al = min(ALPHA_MAX, raw)``, the transmittance before and after, whether the splat stops the
    pixel (without compositing) or is composited, and its weight ``al Tp`` (0 unless composited)."""
    sig = hA * dx * dx + cy + by * dx
    G = _exp_neg32(max(sig, _ZERO))
    raw = o * G
    al = min(_AMAX, raw)
    Tp = S[0, jj]
    nT = Tp * (_ONE - al)
    ok = (sig >= _ZERO) & (al >= _AMIN) & (S[1, jj] > _ZERO)
    stop = ok & (nT <= _TMIN)
    comp = ok & (nT > _TMIN)
    w = al * Tp if comp else _ZERO
    return G, raw, al, Tp, nT, stop, comp, w


@njit(cache=True, fastmath=False, inline="always")
def _composite_px(S, jj, dx, hA, cy, by, o, v0, v1, v2, v3):
    """One splat at column ``jj`` of a tile row ``S [6, 16]`` (T, live, acc x4); 1 when it stops the pixel."""
    _, _, _, Tp, nT, stop, comp, w = _splat_px(S, jj, dx, hA, cy, by, o)
    S[2, jj] += w * v0
    S[3, jj] += w * v1
    S[4, jj] += w * v2
    S[5, jj] += w * v3
    S[0, jj] = nT if comp else Tp
    S[1, jj] = _ZERO if stop else S[1, jj]
    return np.int32(stop)


# Two window widths with trip counts fixed at compile time: LLVM then vectorises the row without
# runtime trip-count and remainder code, which for 8-16 iterations cost more than the work. The
# pixel centre is ``xb + q`` (exact in float32), the same value as ``float32(x) + 0.5``.
#
# Nothing in the row loops is 64 bits wide. LLVM sizes a loop's vectors by its widest element, and
# AVX2 (256-bit registers, no vector int64 -> float conversion) then got 4 float lanes instead of 8,
# with the gradient row mostly scalar: 2.5x slower than the AVX-512 build on the same core
# (``bench/raster_kernel_ab.py --pass backward --isa avx2``). So the column offsets are loaded as
# float32 from ``_COL`` (not converted from the int64 loop index), and the loops count the pixels
# they stop in an int32, cast back at each step (numba types integer sums as int64), instead of
# setting bits at ``1 << q``; the caller rebuilds the row's live mask when a count is not 0.
_COL = np.arange(_TS, dtype=np.float32)


@njit(cache=True, fastmath=False, inline="always")
def _composite_row8(S, lo, xb, mx, hA, cy, by, o, v0, v1, v2, v3):
    """Columns ``[lo, lo + 8)`` of a tile row; ``xb`` = centre of column ``lo``. Returns how many
    pixels it stopped."""
    stopped = np.int32(0)
    for q in range(8):
        stopped = np.int32(stopped + _composite_px(S, lo + q, mx - (xb + _COL[q]), hA, cy, by, o, v0, v1, v2, v3))
    return stopped


@njit(cache=True, fastmath=False, inline="always")
def _composite_row16(S, xb, mx, hA, cy, by, o, v0, v1, v2, v3):
    """All 16 columns of a tile row; ``xb`` = centre of column 0. Returns how many pixels it stopped."""
    stopped = np.int32(0)
    for q in range(16):
        stopped = np.int32(stopped + _composite_px(S, q, mx - (xb + _COL[q]), hA, cy, by, o, v0, v1, v2, v3))
    return stopped


@njit(cache=True, fastmath=False)
def _live_mask(S):
    """Bit mask of the live columns of a tile row ``S`` (``S[1]`` > 0), rebuilt after a splat stopped
    pixels in it (at most once per pixel, so rarely)."""
    m = np.int32(0)
    for q in range(_TS):
        if S[1, q] > _ZERO:
            m |= np.int32(1) << q
    return m


@njit(parallel=True, cache=True, fastmath=False)
def raster_forward_fast(rec, offsets, ids, width, height, tw, n_chunks, out_acc, out_T):
    """Front-to-back compositing of packed splats (``gather_rows`` + ``bin_sorted``), float32, D = 4.

    Writes ``out_acc [H, W, 4]`` (premultiplied rgb + depth sums) and ``out_T [H, W]``. Tiles are
    dealt round-robin to ``n_chunks`` threads (neighbouring tiles cost alike, so this balances).
    """
    n_tiles = offsets.shape[0] - 1
    per = (n_tiles + n_chunks - 1) // n_chunks
    for k in prange(n_chunks * per):
        t = (k % per) * n_chunks + k // per
        if t >= n_tiles:
            continue
        ty = t // tw
        x0 = (t - ty * tw) * _TS
        y0 = ty * _TS
        x1 = min(x0 + _TS, width)
        y1 = min(y0 + _TS, height)
        # tile state, one 16-pixel row per S[row]: T, live (1 while compositing, 0 once stopped or
        # outside the image), acc rgb+depth. One array (not six) so LLVM can prove no aliasing
        # and vectorise the row loop.
        S = np.zeros((_TS, 6, _TS), np.float32)
        # live columns per row as a bit mask: a row none of whose live pixels lies in a splat's box
        # columns is skipped (outside its box a splat's alpha is below ALPHA_MIN: nothing to do)
        rowmask = np.zeros(_TS, np.int32)
        n_live = 0
        for i in range(y0, y1):
            for jj in range(_TS):
                S[i - y0, 0, jj] = _ONE
            for j in range(x0, x1):
                S[i - y0, 1, j - x0] = _ONE
            rowmask[i - y0] = (1 << (x1 - x0)) - 1
            n_live += x1 - x0
        k_end = offsets[t + 1]
        touch = _ZERO
        for kk in range(offsets[t], k_end):
            r = ids[kk]
            # load the record four splats ahead now: its cache miss then overlaps this splat's rows
            touch += rec[ids[min(kk + 4, k_end - 1)], 0]
            bx0 = int(rec[r, R_BOX + 0])
            bx1 = int(rec[r, R_BOX + 1])
            iy0 = max(int(rec[r, R_BOX + 2]), y0)
            iy1 = min(int(rec[r, R_BOX + 3]), y1)
            if bx0 >= x1 or bx1 <= x0 or iy0 >= iy1:
                continue
            mx = rec[r, 0]
            my = rec[r, 1]
            hA = _HALF * rec[r, 2]
            B = rec[r, 3]
            hC = _HALF * rec[r, 4]
            o = rec[r, 5]
            v0 = rec[r, 6]
            v1 = rec[r, 7]
            v2 = rec[r, 8]
            v3 = rec[r, 9]
            c0 = max(bx0 - x0, 0)
            c1 = min(bx1 - x0, _TS)
            narrow = c1 - c0 <= _TS // 2  # one 8-column window holds the box
            lo = min(c0, _TS // 2) if narrow else 0
            xb = _F32(x0 + lo) + _HALF
            boxmask = ((1 << c1) - 1) ^ ((1 << c0) - 1)  # columns [c0, c1)
            for i in range(iy0, iy1):
                if (rowmask[i - y0] & boxmask) == 0:
                    continue
                dy = my - (_F32(i) + _HALF)
                if narrow:
                    st = _composite_row8(S[i - y0], lo, xb, mx, hA, hC * dy * dy, B * dy, o, v0, v1, v2, v3)
                else:
                    st = _composite_row16(S[i - y0], xb, mx, hA, hC * dy * dy, B * dy, o, v0, v1, v2, v3)
                if st:
                    n_live -= st
                    rowmask[i - y0] = _live_mask(S[i - y0])
            if n_live == 0:
                break
        if touch != touch:  # never (the loads above only warm the cache); keeps them from being dropped
            out_T[y0, x0] = touch
        for i in range(y0, y1):
            for j in range(x0, x1):
                jj = j - x0
                out_acc[i, j, 0] = S[i - y0, 2, jj]
                out_acc[i, j, 1] = S[i - y0, 3, jj]
                out_acc[i, j, 2] = S[i - y0, 4, jj]
                out_acc[i, j, 3] = S[i - y0, 5, jj]
                out_T[i, j] = S[i - y0, 0, jj]


# ---------------------------------------------------------------------------------------------
# Float32 gradient path (``cpu_backend.rasterize_cpu`` picks it for float32 inputs that need
# gradients). The forward is ``raster_forward_fast`` above, unchanged. The backward walks every
# tile FRONT to back again, repeating the forward's exact float32 arithmetic (so the same splats
# are composited and the same pixels stop), and gets the colour behind splat i from the final
# sums: ``S_after = acc_final - acc_through_i``, carried per pixel as one running sum ``R`` of the
# incoming gradient times it (``raster_backward_fast``). No transmittance is recovered by division
# (which loses accuracy behind opaque splats).
#
# Gradient of one composited splat at one pixel (w = alpha T, a = alpha, Tf = final T):
#   d acc_d / d a = v_d T - S_after_d / (1 - a),  d (1 - Tf) / d a = Tf / (1 - a),
#   a = o exp(-sigma) (where not clamped at ALPHA_MAX), sigma = 0.5 (A dx^2 + C dy^2) + B dx dy.
# Per-pixel contributions of a splat are accumulated in 16 lanes (one per tile column, so the
# row loop vectorises) and summed into one row per (tile, splat) intersection; ``reduce_rows``
# then sums those rows per splat in list order (deterministic for any thread count).
# ---------------------------------------------------------------------------------------------

N_GRAD32 = 10  # per-intersection gradient row: v0..v3, opacity, conic a, b, c, mx, my
_NB = 7  # backward tile-row state: T, live, g_acc x4, R (see raster_backward_fast)
_NL = 8  # per-column gradient lanes of one splat: w g0..g3, dal G, dsig, dsig dy, dsig dy^2


@njit(cache=True, fastmath=False, inline="always")
def _grad_px(S, L, jj, dx, dy, dy2, hA, cy, by, o, v0, v1, v2, v3):
    """Gradient of one splat at column ``jj`` of a tile row ``S [_NB, 16]``, into lanes ``L [_NL, 16]``.

    The compositing decisions are ``_composite_px``'s (both take them from ``_splat_px``); returns 1
    when the splat stops the pixel."""
    G, raw, al, Tp, nT, stop, comp, w = _splat_px(S, jj, dx, hA, cy, by, o)
    g0 = S[2, jj]
    g1 = S[3, jj]
    g2 = S[4, jj]
    g3 = S[5, jj]
    gv = g0 * v0 + g1 * v1 + g2 * v2 + g3 * v3
    R = S[6, jj] + w * gv
    S[6, jj] = R
    S[0, jj] = nT if comp else Tp
    S[1, jj] = _ZERO if stop else S[1, jj]
    L[0, jj] += w * g0
    L[1, jj] += w * g1
    L[2, jj] += w * g2
    L[3, jj] += w * g3
    dal = (R / (_ONE - al) + Tp * gv) if (comp & (raw < _AMAX)) else _ZERO
    dsig = -dal * raw
    L[4, jj] += dal * G
    L[5, jj] += dsig
    L[6, jj] += dsig * dy
    L[7, jj] += dsig * dy2
    return np.int32(stop)


@njit(cache=True, fastmath=False, inline="always")
def _grad_row16(S, L, xb, mx, dy, dy2, hA, cy, by, o, v0, v1, v2, v3):
    """``_grad_px`` over all 16 columns; how many pixels it stopped (as ``_composite_row16``).

    Always the whole row, also for a splat whose box fits in 8 columns (where the forward takes
    ``_composite_row8``): ``S`` and ``L`` are two arrays, so LLVM vectorises the loop only behind a
    run-time overlap check, and it does not do that for loops of fewer than 16 iterations; the
    8-column loop stayed scalar and took 2.7x the time of the whole backward with 16 columns
    (``bench/raster_kernel_ab.py --pass backward``)."""
    stopped = np.int32(0)
    for q in range(16):
        stopped = np.int32(stopped + _grad_px(S, L, q, mx - (xb + _COL[q]), dy, dy2, hA, cy, by, o, v0, v1, v2, v3))
    return stopped


@njit(parallel=True, cache=True, fastmath=False)
def raster_backward_fast(rec, offsets, ids, width, height, tw, n_chunks, acc_final, T_final, g_acc, g_alpha, out_g):
    """Gradients of ``raster_forward_fast`` (same ``rec``/``offsets``/``ids``), float32, D = 4.

    Args:
        acc_final ``[H, W, 4]`` and T_final ``[H, W]``: the forward's outputs; g_acc ``[H, W, 4]``,
        g_alpha ``[H, W]``: incoming gradients of acc and of alpha = 1 - T_final.
    Writes:
        out_g ``[M, N_GRAD32]`` float32, one row per intersection (``ids`` order): d/d(v0..v3,
        opacity, conic a, b, c, mx, my); rows of splats never composited are zero.

    The tile is walked front to back again, row by row as the forward does (a row none of whose
    live pixels lies in the splat's box columns is skipped), always over whole 16-column rows
    (``_grad_row16``; outside its box a splat's alpha is below ALPHA_MIN, so the columns the
    forward's 8-column window leaves out change nothing), and the per-pixel float32 arithmetic that decides alpha,
    compositing and stopping is the forward's (same operations in the same order, no fused
    multiply-add), so the same splats are composited at the same pixels. The colour behind a
    splat enters only through ``sum_d g_d S_after_d``; each pixel carries
    ``R = g_alpha T_final - sum_d g_d (acc_final_d - acc_d)`` and adds ``w sum_d g_d v_d`` per
    composited splat, so ``d loss / d alpha = R / (1 - alpha) + T sum_d g_d v_d``.
    """
    n_tiles = offsets.shape[0] - 1
    per = (n_tiles + n_chunks - 1) // n_chunks
    for k in prange(n_chunks * per):
        t = (k % per) * n_chunks + k // per
        if t >= n_tiles:
            continue
        s = offsets[t]
        e = offsets[t + 1]
        for kk in range(s, e):
            for q in range(N_GRAD32):
                out_g[kk, q] = _ZERO
        if e == s:
            continue
        ty = t // tw
        x0 = (t - ty * tw) * _TS
        y0 = ty * _TS
        x1 = min(x0 + _TS, width)
        y1 = min(y0 + _TS, height)
        S = np.zeros((_TS, _NB, _TS), np.float32)
        L = np.zeros((_NL, _TS), np.float32)
        rowmask = np.zeros(_TS, np.int32)
        n_live = 0
        for i in range(y0, y1):
            for jj in range(_TS):
                S[i - y0, 0, jj] = _ONE
            for j in range(x0, x1):
                jj = j - x0
                S[i - y0, 1, jj] = _ONE
                g0 = g_acc[i, j, 0]
                g1 = g_acc[i, j, 1]
                g2 = g_acc[i, j, 2]
                g3 = g_acc[i, j, 3]
                S[i - y0, 2, jj] = g0
                S[i - y0, 3, jj] = g1
                S[i - y0, 4, jj] = g2
                S[i - y0, 5, jj] = g3
                gf = g0 * acc_final[i, j, 0] + g1 * acc_final[i, j, 1] + g2 * acc_final[i, j, 2] + g3 * acc_final[i, j, 3]
                S[i - y0, 6, jj] = g_alpha[i, j] * T_final[i, j] - gf
            rowmask[i - y0] = (1 << (x1 - x0)) - 1
            n_live += x1 - x0
        for kk in range(s, e):
            r = ids[kk]
            bx0 = int(rec[r, R_BOX + 0])
            bx1 = int(rec[r, R_BOX + 1])
            iy0 = max(int(rec[r, R_BOX + 2]), y0)
            iy1 = min(int(rec[r, R_BOX + 3]), y1)
            if bx0 >= x1 or bx1 <= x0 or iy0 >= iy1:
                continue
            mx = rec[r, 0]
            my = rec[r, 1]
            A = rec[r, 2]
            hA = _HALF * A
            B = rec[r, 3]
            Cc = rec[r, 4]
            hC = _HALF * Cc
            o = rec[r, 5]
            v0 = rec[r, 6]
            v1 = rec[r, 7]
            v2 = rec[r, 8]
            v3 = rec[r, 9]
            c0 = max(bx0 - x0, 0)
            c1 = min(bx1 - x0, _TS)
            xb = _F32(x0) + _HALF
            boxmask = ((1 << c1) - 1) ^ ((1 << c0) - 1)
            for i in range(iy0, iy1):
                if (rowmask[i - y0] & boxmask) == 0:
                    continue
                dy = my - (_F32(i) + _HALF)
                dy2 = dy * dy
                st = _grad_row16(S[i - y0], L, xb, mx, dy, dy2, hA, hC * dy * dy, B * dy, o, v0, v1, v2, v3)
                if st:
                    n_live -= st
                    rowmask[i - y0] = _live_mask(S[i - y0])
            # lane sums; dx is one value per column, so the dx-weighted sums are taken here
            gv0 = _ZERO
            gv1 = _ZERO
            gv2 = _ZERO
            gv3 = _ZERO
            go = _ZERO
            sx = _ZERO
            sxx = _ZERO
            sy = _ZERO
            sxy = _ZERO
            syy = _ZERO
            for jj in range(_TS):
                dx = mx - (xb + _F32(jj))
                gv0 += L[0, jj]
                gv1 += L[1, jj]
                gv2 += L[2, jj]
                gv3 += L[3, jj]
                go += L[4, jj]
                sx += dx * L[5, jj]
                sxx += dx * dx * L[5, jj]
                sy += L[6, jj]
                sxy += dx * L[6, jj]
                syy += L[7, jj]
                for q in range(_NL):
                    L[q, jj] = _ZERO
            out_g[kk, 0] = gv0
            out_g[kk, 1] = gv1
            out_g[kk, 2] = gv2
            out_g[kk, 3] = gv3
            out_g[kk, 4] = go
            out_g[kk, 5] = _HALF * sxx
            out_g[kk, 6] = sxy
            out_g[kk, 7] = _HALF * syy
            out_g[kk, 8] = A * sx + B * sy
            out_g[kk, 9] = Cc * sy + B * sx
            if n_live == 0:
                break


@njit(cache=True, fastmath=False)
def reduce_rows(ids, isect_g, n_rows):
    """Sum per-intersection rows ``[M, K]`` into ``[n_rows, K]`` float64 by ``ids`` in list order."""
    K = isect_g.shape[1]
    out = np.zeros((n_rows, K))
    for k in range(ids.shape[0]):
        r = ids[k]
        for q in range(K):
            out[r, q] += isect_g[k, q]
    return out
