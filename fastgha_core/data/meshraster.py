"""A CPU triangle-mesh rasterizer (numba): ground truth for the synthetic heads.

Independent of the Gaussian renderer on purpose (the two must never share code). For each output
image it

1. projects camera-space vertices with a pinhole ``K`` onto a ``supersample``-times finer grid;
2. bins triangles into horizontal bands of output rows (a sequential counting sort, so each band
   sees its triangles in index order);
3. rasterizes the bands in parallel (``numba.prange``): a z-buffer per sample with a strict
   ``<`` depth test, so among equal depths the lower triangle index wins. Each sample belongs to
   exactly one band and is visited in a fixed order, so the result is bitwise identical for any
   number of threads;
4. interpolates per-vertex attributes ``[Nv, A]`` (colour, normals, ...) with
   perspective-correct barycentrics and depth as ``1 / sum(l_i / z_i)``;
5. box-filters each ``supersample x supersample`` block: alpha = covered fraction, attributes =
   mean over covered samples composited over ``background``, depth = mean camera z of the covered
   samples (0 where none).

Pixel convention as in ``fastgha_core.cameras``: (u, v) = (0, 0) is the top-left corner of the
top-left pixel; sample (i, j) of the fine grid sits at ((j + 0.5) / s, (i + 0.5) / s).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

__all__ = ["MeshRender", "render_mesh", "rasterize_fragments", "blend_basis"]

_NEAR = 1e-4  # metres; triangles with a vertex closer than this to the camera plane are dropped
_BAND_ROWS = 8  # output rows per parallel band


@dataclass
class MeshRender:
    """One rendered image."""

    color: np.ndarray  # [H, W, A] float32 (composited over the background when one was given)
    alpha: np.ndarray  # [H, W] float32 in [0, 1], covered fraction of each pixel
    depth: np.ndarray  # [H, W] float32 camera z in metres, 0 where nothing is hit


# ---------------------------------------------------------------------------- kernels
@numba.njit(parallel=True, cache=True)
def _blend_kernel(basis, w, out):  # basis [K, Nv, 3], w [K], out [Nv, 3] (accumulates)
    nk, nv = basis.shape[0], basis.shape[1]
    for v in numba.prange(nv):
        for d in range(3):
            acc = np.float32(0.0)
            for k in range(nk):
                acc += w[k] * basis[k, v, d]
            out[v, d] = acc


def blend_basis(basis: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``sum_k w[k] * basis[k]`` for ``basis [K, Nv, 3]``, ``w [K]`` -> ``[Nv, 3]`` float32.

    Summed in a fixed order per vertex, so the bytes do not depend on BLAS or thread count.
    """
    basis = np.ascontiguousarray(basis, dtype=np.float32)
    w = np.ascontiguousarray(w, dtype=np.float32)
    if basis.ndim != 3 or basis.shape[2] != 3 or w.shape != (basis.shape[0],):
        raise ValueError(f"expected basis [K, Nv, 3] and w [K], got {basis.shape} and {w.shape}")
    out = np.empty((basis.shape[1], 3), dtype=np.float32)
    _blend_kernel(basis, w, out)
    return out


@numba.njit(cache=True)
def _setup(points, K, faces, ss, width_s, height_s):
    """Per-triangle screen data: xy [F, 3, 2], inverse z [F, 3], bbox [F, 4] (x0, x1, y0, y1 inclusive)."""
    nf = faces.shape[0]
    xy = np.empty((nf, 3, 2), dtype=np.float64)
    iz = np.empty((nf, 3), dtype=np.float64)
    bbox = np.full((nf, 4), -1, dtype=np.int64)
    for f in range(nf):
        ok = True
        for k in range(3):
            p = points[faces[f, k]]
            z = np.float64(p[2])
            if z <= _NEAR:
                ok = False
                break
            x, y = np.float64(p[0]), np.float64(p[1])
            u = (K[0, 0] * x + K[0, 1] * y + K[0, 2] * z) / z
            v = (K[1, 0] * x + K[1, 1] * y + K[1, 2] * z) / z
            xy[f, k, 0] = u * ss
            xy[f, k, 1] = v * ss
            iz[f, k] = 1.0 / z
        if not ok:
            continue
        ax, ay = xy[f, 0, 0], xy[f, 0, 1]
        bx, by = xy[f, 1, 0], xy[f, 1, 1]
        cx, cy = xy[f, 2, 0], xy[f, 2, 1]
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if abs(area) < 1e-12:
            continue
        # sample centres at (j + 0.5, i + 0.5): j from ceil(min - 0.5) to floor(max - 0.5)
        x0 = int(np.ceil(min(ax, bx, cx) - 0.5))
        x1 = int(np.floor(max(ax, bx, cx) - 0.5))
        y0 = int(np.ceil(min(ay, by, cy) - 0.5))
        y1 = int(np.floor(max(ay, by, cy) - 0.5))
        x0, y0 = max(x0, 0), max(y0, 0)
        x1, y1 = min(x1, width_s - 1), min(y1, height_s - 1)
        if x0 > x1 or y0 > y1:
            continue
        bbox[f, 0], bbox[f, 1], bbox[f, 2], bbox[f, 3] = x0, x1, y0, y1
    return xy, iz, bbox


@numba.njit(cache=True)
def _bin(bbox, band_rows_s, nbands):
    """Counting sort of triangles into bands; within a band triangles keep ascending index."""
    nf = bbox.shape[0]
    counts = np.zeros(nbands + 1, dtype=np.int64)
    for f in range(nf):
        if bbox[f, 0] < 0:
            continue
        b0, b1 = bbox[f, 2] // band_rows_s, bbox[f, 3] // band_rows_s
        for b in range(b0, b1 + 1):
            counts[b + 1] += 1
    for b in range(nbands):
        counts[b + 1] += counts[b]
    fill = counts[:-1].copy()
    items = np.empty(counts[nbands], dtype=np.int64)
    for f in range(nf):
        if bbox[f, 0] < 0:
            continue
        b0, b1 = bbox[f, 2] // band_rows_s, bbox[f, 3] // band_rows_s
        for b in range(b0, b1 + 1):
            items[fill[b]] = f
            fill[b] += 1
    return counts, items


@numba.njit(cache=True)
def _raster_band(xy, iz, bbox, items, start, stop, r0, r1, width_s, zbuf, tri, bary):
    """Z-buffer the triangles ``items[start:stop]`` into fine rows [r0, r1) (local buffers)."""
    for it in range(start, stop):
        f = items[it]
        ax, ay = xy[f, 0, 0], xy[f, 0, 1]
        bx, by = xy[f, 1, 0], xy[f, 1, 1]
        cx, cy = xy[f, 2, 0], xy[f, 2, 1]
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        inv_area = 1.0 / area
        i0, i1, i2 = iz[f, 0], iz[f, 1], iz[f, 2]
        y_lo, y_hi = max(bbox[f, 2], r0), min(bbox[f, 3], r1 - 1)
        for i in range(y_lo, y_hi + 1):
            py = i + 0.5
            for j in range(bbox[f, 0], bbox[f, 1] + 1):
                px = j + 0.5
                l0 = ((cx - bx) * (py - by) - (cy - by) * (px - bx)) * inv_area
                l1 = ((ax - cx) * (py - cy) - (ay - cy) * (px - cx)) * inv_area
                l2 = 1.0 - l0 - l1
                if l0 < 0.0 or l1 < 0.0 or l2 < 0.0:
                    continue
                w0, w1, w2 = l0 * i0, l1 * i1, l2 * i2
                s = w0 + w1 + w2
                z = 1.0 / s
                li = i - r0
                if z < zbuf[li, j]:
                    zbuf[li, j] = z
                    tri[li, j] = f
                    bary[li, j, 0] = w0 / s
                    bary[li, j, 1] = w1 / s
                    bary[li, j, 2] = w2 / s


@numba.njit(parallel=True, cache=True)
def _render(points, K, faces, attrs, width, height, ss, background, has_bg, out_color, out_alpha, out_depth):
    width_s, height_s = width * ss, height * ss
    xy, iz, bbox = _setup(points, K, faces, ss, width_s, height_s)
    band_rows_s = _BAND_ROWS * ss
    nbands = (height + _BAND_ROWS - 1) // _BAND_ROWS
    counts, items = _bin(bbox, band_rows_s, nbands)
    na = attrs.shape[1]
    inv_n = 1.0 / (ss * ss)
    for b in numba.prange(nbands):
        r0 = b * band_rows_s
        r1 = min(r0 + band_rows_s, height_s)
        nr = r1 - r0
        zbuf = np.full((nr, width_s), np.inf)
        tri = np.full((nr, width_s), -1, dtype=np.int64)
        bary = np.zeros((nr, width_s, 3))
        _raster_band(xy, iz, bbox, items, counts[b], counts[b + 1], r0, r1, width_s, zbuf, tri, bary)
        acc = np.zeros(na)
        for oi in range(r0 // ss, (r1 + ss - 1) // ss):
            for oj in range(width):
                acc[:] = 0.0
                cov = 0
                zsum = 0.0
                for di in range(ss):
                    li = oi * ss + di - r0
                    for dj in range(ss):
                        j = oj * ss + dj
                        f = tri[li, j]
                        if f < 0:
                            continue
                        cov += 1
                        zsum += zbuf[li, j]
                        v0, v1, v2 = faces[f, 0], faces[f, 1], faces[f, 2]
                        b0, b1, b2 = bary[li, j, 0], bary[li, j, 1], bary[li, j, 2]
                        for a in range(na):
                            acc[a] += b0 * attrs[v0, a] + b1 * attrs[v1, a] + b2 * attrs[v2, a]
                alpha = cov * inv_n
                out_alpha[oi, oj] = alpha
                out_depth[oi, oj] = zsum / cov if cov > 0 else 0.0
                for a in range(na):
                    c = acc[a] * inv_n
                    if has_bg:
                        c += (1.0 - alpha) * background[a]
                    out_color[oi, oj, a] = c


# ---------------------------------------------------------------------------- public API
def render_mesh(
    points_cam: np.ndarray,  # [Nv, 3] camera-space vertices (OpenCV axes, z forward, metres)
    faces: np.ndarray,  # [F, 3] int
    attrs: np.ndarray,  # [Nv, A] per-vertex attributes
    K: np.ndarray,  # [3, 3] intrinsics in output pixels
    width: int,
    height: int,
    supersample: int = 2,
    background=None,  # [A] or None (premultiplied output)
) -> MeshRender:
    """Rasterize one mesh into one ``width x height`` image (see module doc)."""
    points_cam = np.ascontiguousarray(points_cam, dtype=np.float32)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    attrs = np.ascontiguousarray(attrs, dtype=np.float32)
    K = np.ascontiguousarray(K, dtype=np.float64)
    if points_cam.ndim != 2 or points_cam.shape[1] != 3:
        raise ValueError(f"points_cam must be [Nv, 3], got {points_cam.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be [F, 3], got {faces.shape}")
    if attrs.ndim != 2 or attrs.shape[0] != points_cam.shape[0]:
        raise ValueError(f"attrs must be [Nv={points_cam.shape[0]}, A], got {attrs.shape}")
    if K.shape != (3, 3):
        raise ValueError(f"K must be [3, 3], got {K.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= points_cam.shape[0]):
        raise ValueError(f"faces index vertices outside [0, {points_cam.shape[0]})")
    if int(supersample) < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    if width <= 0 or height <= 0:
        raise ValueError(f"width and height must be positive, got {width}x{height}")
    na = attrs.shape[1]
    has_bg = background is not None
    bg = np.zeros(na, dtype=np.float64) if background is None else np.asarray(background, dtype=np.float64)
    if bg.shape != (na,):
        raise ValueError(f"background must have {na} values (one per attribute), got shape {bg.shape}")
    color = np.zeros((height, width, na), dtype=np.float32)
    alpha = np.zeros((height, width), dtype=np.float32)
    depth = np.zeros((height, width), dtype=np.float32)
    _render(points_cam, K, faces, attrs, int(width), int(height), int(supersample), bg, has_bg, color, alpha, depth)
    return MeshRender(color=color, alpha=alpha, depth=depth)


def rasterize_fragments(points_cam: np.ndarray, faces: np.ndarray, K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """One sample per pixel: triangle id ``[H, W]`` int64 (-1 = none) and depth ``[H, W]``.

    Implemented with the same kernel by rendering the triangle's index as an attribute of a
    de-indexed mesh; meant for tests and visibility queries, not speed.
    """
    faces = np.asarray(faces, dtype=np.int64)
    pts = np.asarray(points_cam, dtype=np.float32)[faces.reshape(-1)]  # [3F, 3] one vertex per corner
    ids = np.repeat(np.arange(faces.shape[0], dtype=np.float32), 3)[:, None]  # [3F, 1]
    flat = np.arange(3 * faces.shape[0], dtype=np.int64).reshape(-1, 3)
    r = render_mesh(pts, flat, ids, K, width, height, supersample=1)
    tri = np.where(r.alpha > 0, np.rint(r.color[..., 0]).astype(np.int64), -1)
    return tri, r.depth
