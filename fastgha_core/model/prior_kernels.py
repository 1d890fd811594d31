"""numba kernel of the expression prior's per-frame path (``PriorRuntime.frame``, CPU, no gradients).

One pass over the Gaussians writes what ``fastgha.FastGHA.animate`` hands to the rasterizer, in
place of the plain torch path (sparse ``[N, U]`` products for the displacement and the expression
shading, a ``[U, 3] @ [3, 3]`` product, the per-Gaussian opacity gather and ``torch.cat`` of the
reconstructed and interior parts, each a separate pass over ``N`` with its own allocation). Same
maths; only the order of the float32 operations differs (the fit's 3x3 matrix is folded into a
per-avatar copy of the blendshapes of the slots the avatar uses, ``PriorRuntime.compact``, which
holds each slot's shading next to its displacement), so
positions and colours agree with the plain path to float32 rounding, opacities exactly. ``tests/test_prior.py`` checks it against the
plain path.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = ["prior_frame", "shading_rows", "triangle_rotations"]


@njit(parallel=True, cache=True, fastmath=False)
def prior_frame(means, colors, opac, dxyz, drgb, du, local, coef, gidx, table, n_rec, lo, hi, out_means, out_colors, out_op, quats, tidx, tq, out_quats):
    """The first ``n = out_means.shape[0]`` deformed Gaussians of one frame.

    Args:
        means ``[N, 3]``, colors ``[N, 3]``, opac ``[N]``: canonical Gaussians (float32).
        dxyz, drgb ``[n_rec, 3]``: the MLP's residual of the reconstructed Gaussians (any strides).
        du ``[U, 4]``: per slot the blendshape displacement, in the avatar's frame (columns 0-2), and
            the expression shading (column 3, ``z @ shade`` of the slot).
        local ``[N, 3]`` int32 slots and coef ``[N, 3]`` float32 weights (barycentric * fade):
            ``displacement = sum_k coef_k du[local_k]``.
        gidx ``[N]`` int8 index into ``table [T]``, the per-group opacity factors of this frame.
        n_rec: Gaussians ``< n_rec`` get the MLP's residual and a clamped colour times the
            expression shading; the rest (mouth interior, eyelids) keep their colour.
        lo, hi: the colour factor is ``clamp(1 + sum_k coef_k du[local_k, 3], lo, hi)``.
        quats ``[N, 4]`` wxyz, tidx ``[N]`` int32, tq ``[T, 4]`` and out_quats ``[n, 4]`` (or ``[0, 4]``:
            off): the surface rotation (``PriorRuntime.rotation``): ``tq`` holds this frame's rotation
            of each bound triangle (``triangle_rotations``), ``tidx`` each Gaussian's triangle (-1:
            none, the rotation is the identity); ``out_quats[i] = nlerp(1, tq[tidx[i]], w) * quats[i]``
            with the fade weight ``w = sum_k coef_k`` (barycentrics sum to 1).
    Writes ``out_means [n, 3]``, ``out_colors [n, 3]``, ``out_op [n]`` (and ``out_quats [n, 4]``).
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
            r = one + (wa * du[a, 3] + wb * du[b, 3] + wc * du[c, 3])
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
        if out_quats.shape[0] > 0:
            gw, gx, gy, gz = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
            t = tidx[i]
            if t < 0 or (tq[t, 1] == zero and tq[t, 2] == zero and tq[t, 3] == zero):
                out_quats[i, 0], out_quats[i, 1], out_quats[i, 2], out_quats[i, 3] = gw, gx, gy, gz
                continue
            qw, qx, qy, qz = tq[t, 0], tq[t, 1], tq[t, 2], tq[t, 3]
            w = min(max(wa + wb + wc, zero), one)
            if w < one:  # nlerp from the identity by the fade weight
                qw = (one - w) + w * qw
                qx, qy, qz = w * qx, w * qy, w * qz
                r = one / np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
                qw, qx, qy, qz = qw * r, qx * r, qy * r, qz * r
            out_quats[i, 0] = qw * gw - qx * gx - qy * gy - qz * gz
            out_quats[i, 1] = qw * gx + qx * gw + qy * gz - qz * gy
            out_quats[i, 2] = qw * gy - qx * gz + qy * gw + qz * gx
            out_quats[i, 3] = qw * gz + qx * gy - qy * gx + qz * gw
    return 0


@njit(parallel=True, cache=True, fastmath=False)
def triangle_rotations(du, tslots, tgeom, out):
    """This frame's rotation of each bound triangle, ``out [T, 4]`` wxyz (w >= 0), from ``du [U, 4]``
    (``prior_frame``'s), ``tslots [T, 3]`` int32 (the corners' slots) and ``tgeom [T, 15]`` float32:
    the neutral edges ``e1 = b - a``, ``e2 = c - a`` and the neutral frame ``F0 = [x, y, n]`` (the
    columns ``x = e1 / |e1|``, ``n = (e1 x e2) / |e1 x e2|``, ``y = n x x``, stored as x, y, n).

    With the displaced edges ``e1 + du[b] - du[a]``, ``e2 + du[c] - du[a]`` and their frame ``F1``
    (the same construction), the rotation is ``R = F1 F0^T`` as a quaternion (Shepperd's method, as
    ``gaussian_head.matrix_to_quaternion``); the identity where the corners do not move apart or
    the displaced triangle is degenerate. ``PriorRuntime.rotation`` is the same maths in torch.
    """
    one, zero = np.float32(1.0), np.float32(0.0)
    for t in prange(tslots.shape[0]):
        a, b, c = tslots[t, 0], tslots[t, 1], tslots[t, 2]
        d1x, d1y, d1z = du[b, 0] - du[a, 0], du[b, 1] - du[a, 1], du[b, 2] - du[a, 2]
        d2x, d2y, d2z = du[c, 0] - du[a, 0], du[c, 1] - du[a, 1], du[c, 2] - du[a, 2]
        out[t, 0], out[t, 1], out[t, 2], out[t, 3] = one, zero, zero, zero
        if d1x == zero and d1y == zero and d1z == zero and d2x == zero and d2y == zero and d2z == zero:
            continue
        e1x, e1y, e1z = tgeom[t, 0] + d1x, tgeom[t, 1] + d1y, tgeom[t, 2] + d1z
        e2x, e2y, e2z = tgeom[t, 3] + d2x, tgeom[t, 4] + d2y, tgeom[t, 5] + d2z
        r0 = e1y * e2z - e1z * e2y
        r1 = e1z * e2x - e1x * e2z
        r2 = e1x * e2y - e1y * e2x
        l1 = np.sqrt(e1x * e1x + e1y * e1y + e1z * e1z)
        ln = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        if not (l1 > 1e-12 and ln > 1e-18):
            continue
        l1, ln = one / l1, one / ln
        p0, p1, p2 = e1x * l1, e1y * l1, e1z * l1
        r0, r1, r2 = r0 * ln, r1 * ln, r2 * ln
        q0 = r1 * p2 - r2 * p1
        q1 = r2 * p0 - r0 * p2
        q2 = r0 * p1 - r1 * p0
        a0, a1, a2 = tgeom[t, 6], tgeom[t, 7], tgeom[t, 8]
        b0, b1, b2 = tgeom[t, 9], tgeom[t, 10], tgeom[t, 11]
        c0, c1, c2 = tgeom[t, 12], tgeom[t, 13], tgeom[t, 14]
        # R = F1 F0^T with F0 = [a b c] and F1 = [p q r] (columns)
        m00 = p0 * a0 + q0 * b0 + r0 * c0
        m01 = p0 * a1 + q0 * b1 + r0 * c1
        m02 = p0 * a2 + q0 * b2 + r0 * c2
        m10 = p1 * a0 + q1 * b0 + r1 * c0
        m11 = p1 * a1 + q1 * b1 + r1 * c1
        m12 = p1 * a2 + q1 * b2 + r1 * c2
        m20 = p2 * a0 + q2 * b0 + r2 * c0
        m21 = p2 * a1 + q2 * b1 + r2 * c1
        m22 = p2 * a2 + q2 * b2 + r2 * c2
        k0 = one + m00 + m11 + m22
        k1 = one + m00 - m11 - m22
        k2 = one - m00 + m11 - m22
        k3 = one - m00 - m11 + m22
        if k0 >= k1 and k0 >= k2 and k0 >= k3:
            qw, qx, qy, qz = k0, m21 - m12, m02 - m20, m10 - m01
        elif k1 >= k2 and k1 >= k3:
            qw, qx, qy, qz = m21 - m12, k1, m01 + m10, m02 + m20
        elif k2 >= k3:
            qw, qx, qy, qz = m02 - m20, m01 + m10, k2, m12 + m21
        else:
            qw, qx, qy, qz = m10 - m01, m02 + m20, m12 + m21, k3
        s = one / np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        if qw < zero:
            s = -s
        out[t, 0], out[t, 1], out[t, 2], out[t, 3] = qw * s, qx * s, qy * s, qz * s
    return 0


@njit(parallel=True, cache=True, fastmath=False)
def shading_rows(neutral, id_basis, identity, dbasis, rows, faces, vmap, light, ambient, floor, out):
    """The expression shading (``prior.shading_basis``) at a subset of the head model's vertices.

    Args:
        neutral ``[Nv, 3]``, id_basis ``[K, Nv, 3]`` float32 and identity ``[K]`` float64: the fitted
            head at neutral is ``neutral + sum_k identity_k id_basis_k`` (float64, model frame).
        dbasis ``[E, Nv, 3]`` float32: the expression blendshapes.
        rows ``[R]`` int64: the blendshapes to evaluate (the other rows of ``out`` are left alone).
        faces ``[F, 3]`` int64: every triangle that touches a wanted vertex, in ``bind_faces`` order.
        vmap ``[Nv]`` int64: column of ``out`` of each wanted vertex, -1 elsewhere.
        light ``[3]`` float64, ambient, floor: ``SHADE_LIGHT``, ``SHADE_AMBIENT`` and the floor of the
            neutral brightness (0.05).
    Writes ``out[e, vmap[i]] = b(v + dbasis[e])[i] / max(b(v)[i], floor) - 1`` for ``e`` in ``rows``,
    with ``b`` the brightness of ``prior._brightness``: per vertex the area-weighted normal summed
    per triangle corner in float64 and rounded to float32 as ``headmodel.vertex_normals`` does (the
    same triangles in the same order). The head's identity sum and the final dot products may round
    differently from numpy's (``tests/test_prior_runtime.py`` compares the result with ``shading_basis``).
    """
    nv = neutral.shape[0]
    m = out.shape[1]
    used = np.zeros(nv, np.bool_)
    for f in range(faces.shape[0]):
        for k in range(3):
            used[faces[f, k]] = True
    v = np.zeros((nv, 3), np.float64)
    for i in prange(nv):
        if used[i]:
            for q in range(3):
                s = np.float64(neutral[i, q])
                t = 0.0
                for k in range(identity.shape[0]):
                    t += identity[k] * np.float64(id_basis[k, i, q])
                v[i, q] = s + t
    zero3 = np.zeros((1, 3), np.float32)
    base = _brightness_at(v, zero3, faces, vmap, m, light, ambient)  # [m] float64
    for c in range(m):
        base[c] = max(base[c], floor)
    for t in prange(rows.shape[0]):
        e = rows[t]
        b = _brightness_at(v, dbasis[e], faces, vmap, m, light, ambient)
        for c in range(m):
            out[e, c] = np.float32(b[c] / base[c] - 1.0)
    return 0


@njit(cache=True, fastmath=False)
def _brightness_at(v, d, faces, vmap, m, light, ambient):
    """``prior._brightness`` of ``v + d`` (``d [Nv, 3]``, or ``[1, 3]`` zeros) at the wanted vertices -> ``[m]`` float64."""
    acc = np.zeros((3, m, 3), np.float64)  # per triangle corner k, as vertex_normals' three bincount passes
    one_d = d.shape[0] == 1
    p = np.empty((3, 3), np.float32)
    for f in range(faces.shape[0]):
        for k in range(3):
            i = faces[f, k]
            for q in range(3):
                p[k, q] = np.float32(v[i, q] + (np.float64(d[0, q]) if one_d else np.float64(d[i, q])))
        ux, uy, uz = p[1, 0] - p[0, 0], p[1, 1] - p[0, 1], p[1, 2] - p[0, 2]
        wx, wy, wz = p[2, 0] - p[0, 0], p[2, 1] - p[0, 1], p[2, 2] - p[0, 2]
        n0 = uy * wz - uz * wy
        n1 = uz * wx - ux * wz
        n2 = ux * wy - uy * wx
        for k in range(3):
            c = vmap[faces[f, k]]
            if c >= 0:
                acc[k, c, 0] += np.float64(n0)
                acc[k, c, 1] += np.float64(n1)
                acc[k, c, 2] += np.float64(n2)
    out = np.empty(m, np.float64)
    for c in range(m):
        x = np.float32(0.0) + np.float32(acc[0, c, 0]) + np.float32(acc[1, c, 0]) + np.float32(acc[2, c, 0])
        y = np.float32(0.0) + np.float32(acc[0, c, 1]) + np.float32(acc[1, c, 1]) + np.float32(acc[2, c, 1])
        z = np.float32(0.0) + np.float32(acc[0, c, 2]) + np.float32(acc[1, c, 2]) + np.float32(acc[2, c, 2])
        ln = np.float32(np.sqrt(x * x + y * y + z * z))
        ln = max(ln, np.float32(1e-12))
        x, y, z = x / ln, y / ln, z / ln
        s = np.float64(x) * light[0] + np.float64(y) * light[1] + np.float64(z) * light[2]
        out[c] = ambient + (1.0 - ambient) * max(s, 0.0)
    return out
