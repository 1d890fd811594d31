"""CPU mesh rasterizer against a plain numpy reference; antialiasing; thread-count independence."""

import numba
import numpy as np
import pytest

from fastgha_core.data.meshraster import blend_basis, rasterize_fragments, render_mesh


def _scene(seed=0, n=12):
    rng = np.random.default_rng(seed)
    centres = rng.uniform([-0.3, -0.3, 1.5], [0.3, 0.3, 3.0], (n, 1, 3))
    pts = (centres + rng.normal(0, 0.25, (n, 3, 3)) * [1, 1, 0.3]).reshape(-1, 3).astype(np.float32)
    faces = np.arange(3 * n).reshape(n, 3)
    attrs = rng.uniform(0, 1, (3 * n, 3)).astype(np.float32)
    K = np.array([[30.0, 0, 16.0], [0, 30.0, 16.0], [0, 0, 1]])
    return pts, faces, attrs, K


def _reference(pts, faces, attrs, K, W, H):
    """One sample per pixel centre, nearest surface wins (ties: lower triangle index)."""
    uv = pts @ K.T
    xy = uv[:, :2] / uv[:, 2:3]
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    zbest = np.full((H, W), np.inf)
    color = np.zeros((H, W, attrs.shape[1]))
    for f in faces:
        a, b, c = xy[f]
        area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        l0 = ((c[0] - b[0]) * (ii - b[1]) - (c[1] - b[1]) * (jj - b[0])) / area
        l1 = ((a[0] - c[0]) * (ii - c[1]) - (a[1] - c[1]) * (jj - c[0])) / area
        l2 = 1 - l0 - l1
        inside = (l0 >= 0) & (l1 >= 0) & (l2 >= 0)
        z = pts[f, 2].astype(np.float64)
        w = np.stack([l0 / z[0], l1 / z[1], l2 / z[2]], -1)
        depth = 1 / w.sum(-1)
        hit = inside & (depth < zbest)
        zbest = np.where(hit, depth, zbest)
        col = (w / w.sum(-1, keepdims=True)) @ attrs[f].astype(np.float64)
        color = np.where(hit[..., None], col, color)
    cov = np.isfinite(zbest)
    return color, cov, np.where(cov, zbest, 0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_reference(seed):
    pts, faces, attrs, K = _scene(seed)
    r = render_mesh(pts, faces, attrs, K, 32, 32, supersample=1)
    color, cov, depth = _reference(pts, faces, attrs, K, 32, 32)
    assert cov.sum() > 50
    np.testing.assert_array_equal(r.alpha > 0, cov)
    np.testing.assert_allclose(r.color, color, atol=1e-5)
    np.testing.assert_allclose(r.depth, depth, atol=1e-5)
    tri, d2 = rasterize_fragments(pts, faces, K, 32, 32)
    assert ((tri >= 0) == cov).all()
    np.testing.assert_allclose(d2, depth, atol=1e-5)


def test_supersampling_is_box_filter_of_fine_render():
    pts, faces, attrs, K = _scene(3)
    for s in (2, 3):
        fine = render_mesh(pts, faces, attrs, K * np.array([[s], [s], [1]]), 32 * s, 32 * s, supersample=1)
        coarse = render_mesh(pts, faces, attrs, K, 32, 32, supersample=s, background=[1.0, 1.0, 1.0])

        def box(a, s=s):
            return a.reshape(32, s, 32, s, *a.shape[2:]).mean((1, 3))

        alpha = box(fine.alpha)
        np.testing.assert_allclose(coarse.alpha, alpha, atol=1e-6)
        np.testing.assert_allclose(coarse.color, box(fine.color) + (1 - alpha[..., None]), atol=1e-5)
    # a half-covered pixel: a big triangle whose edge passes through pixel centres' midline
    pts = np.array([[-1, -1, 2], [0, -1, 2], [0, 1, 2]], np.float32)  # x <= 0 half (edge x = 0 at column 16)
    K = np.array([[16.0, 0, 16.0], [0, 16.0, 16.0], [0, 0, 1]])
    r = render_mesh(pts, np.array([[0, 1, 2]]), np.ones((3, 1), np.float32), K, 32, 32, supersample=4)
    assert r.alpha[16, 15] == 1.0 and r.alpha[16, 16] == 0.0  # edge at u = 16 exactly between pixels


def test_independent_of_thread_count():
    pts, faces, attrs, K = _scene(4, n=200)
    n0 = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        a = render_mesh(pts, faces, attrs, K, 32, 32, supersample=2)
        numba.set_num_threads(max(n0, 2) if numba.config.NUMBA_NUM_THREADS >= 2 else 1)
        b = render_mesh(pts, faces, attrs, K, 32, 32, supersample=2)
    finally:
        numba.set_num_threads(n0)
    assert a.color.tobytes() == b.color.tobytes() and a.depth.tobytes() == b.depth.tobytes()


def test_behind_camera_dropped_and_errors():
    pts = np.array([[0, 0, -1], [1, 0, -1], [0, 1, -1]], np.float32)
    K = np.array([[10.0, 0, 8], [0, 10.0, 8], [0, 0, 1]])
    r = render_mesh(pts, np.array([[0, 1, 2]]), np.ones((3, 1), np.float32), K, 16, 16)
    assert r.alpha.max() == 0 and r.depth.max() == 0
    with pytest.raises(ValueError, match="attrs"):
        render_mesh(pts, np.array([[0, 1, 2]]), np.ones((4, 1), np.float32), K, 16, 16)
    with pytest.raises(ValueError, match="faces index"):
        render_mesh(pts, np.array([[0, 1, 5]]), np.ones((3, 1), np.float32), K, 16, 16)


def test_blend_basis_reference():
    rng = np.random.default_rng(0)
    basis = rng.normal(size=(7, 50, 3)).astype(np.float32)
    w = rng.normal(size=7).astype(np.float32)
    np.testing.assert_allclose(blend_basis(basis, w), np.einsum("k,kvd->vd", w, basis), atol=1e-5)
