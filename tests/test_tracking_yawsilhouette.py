"""The silhouette features of the yaw measurement (fastgha_core/tracking/yawsilhouette.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fastgha_core.tracking.yawsilhouette import (
    HEIGHTS,
    NEAR_CONTOUR,
    fit_folded_ridge,
    near_contour_fraction,
    predict_folded,
    silhouette_edges,
    silhouette_features,
)


def _face(cx: float = 200.0, top: float = 100.0, length: float = 200.0, nose_x: float = 260.0) -> np.ndarray:
    p = np.zeros((468, 2))
    p[:, 0] = cx + np.linspace(-20.0, 20.0, 468)  # the face's centre at cx
    p[:, 1] = top + length * np.linspace(0.1, 0.9, 468)
    p[10], p[152], p[1] = [cx, top], [cx, top + length], [nose_x, top + 0.6 * length]
    return p


def _mask(h: int = 400, w: int = 500, x0: int = 80, x1: int = 300, y0: int = 60, y1: int = 330) -> np.ndarray:
    m = np.zeros((h, w), bool)
    m[y0:y1, x0:x1] = True  # the head: pixels x0 .. x1 - 1
    m[:, 420:470] = True  # another person beside it, not connected: ignored
    return m


def test_edges_of_a_box_head_relative_to_the_nose_tip():
    p, m = _face(), _mask()
    e = silhouette_edges(m, p, +1)
    assert e.shape == (len(HEIGHTS), 2)
    # every scan line crosses the box: back edge at x = 80, front edge at the last pixel (299.x), nose at 260, L = 200
    np.testing.assert_allclose(e[:, 0], (80.0 - 260.0) / 200.0, atol=0.01)
    np.testing.assert_allclose(e[:, 1], (300.0 - 260.0) / 200.0, atol=0.01)
    # folded the other way: the back edge is the box's right side, distances measured towards -x
    f = silhouette_edges(m, p, -1)
    np.testing.assert_allclose(f[:, 0], -(300.0 - 260.0) / 200.0, atol=0.01)
    np.testing.assert_allclose(f[:, 1], -(80.0 - 260.0) / 200.0, atol=0.01)


def test_edges_are_mirror_and_similarity_invariant():
    p, m = _face(), _mask()
    e = silhouette_edges(m, p, +1)
    W = m.shape[1]
    pm = p.copy()
    pm[:, 0] = W - p[:, 0]
    np.testing.assert_allclose(silhouette_edges(m[:, ::-1], pm, -1), e, atol=0.01)  # a head turned the other way
    # the photo twice as large and rolled by 20 degrees (about the image centre): same features
    a = math.radians(20.0)
    S = 2.0 * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    c = np.array([250.0, 200.0])
    q = (p - c) @ S.T + 2 * c
    yy, xx = np.mgrid[0:800, 0:1000] + 0.5
    back = np.stack([xx - 2 * c[0], yy - 2 * c[1]], -1) @ np.linalg.inv(S).T + c  # each big pixel's centre in the small photo
    inside = (back[..., 0] >= 80) & (back[..., 0] < 300) & (back[..., 1] >= 60) & (back[..., 1] < 330)
    np.testing.assert_allclose(silhouette_edges(inside, q, +1), e, atol=0.02)


def test_rows_without_mask_are_nan_and_features_zero_there():
    p = _face()
    m = _mask(y0=150, y1=330)  # the top of the head cut off: the forehead rows hit nothing
    e = silhouette_edges(m, p, +1)
    y = 200.0 + np.array(HEIGHTS) * 200.0  # the scan rows (the face axis is vertical)
    assert np.isnan(e[y < 150]).all() and np.isfinite(e[y >= 151]).all()
    f = silhouette_features(m, p, +1)
    assert f.shape == (2 * len(HEIGHTS),) and np.isfinite(f).all() and (f.reshape(-1, 2)[y < 150] == 0).all()
    with pytest.raises(ValueError, match="468"):
        silhouette_edges(m, p[:100], +1)
    q = p.copy()
    q[152] = q[10]
    with pytest.raises(ValueError, match="coincide"):
        silhouette_edges(m, q, +1)


def test_near_contour_fraction_is_the_face_share_between_back_edge_and_nose():
    p, m = _face(), _mask()
    for k, j in enumerate(NEAR_CONTOUR[1]):
        p[j] = [120.0, 140.0 + 30.0 * k]  # the cheek outline towards the ear, 40 px inside the back edge (x = 80)
    assert near_contour_fraction(m, p, +1) == pytest.approx((120.0 - 80.0) / (260.0 - 80.0), abs=0.01)
    for j in NEAR_CONTOUR[1]:
        p[j, 0] = 200.0  # further round the face
    assert near_contour_fraction(m, p, +1) == pytest.approx((200.0 - 80.0) / (260.0 - 80.0), abs=0.01)
    assert math.isnan(near_contour_fraction(np.zeros_like(m), p, +1))


def test_folded_ridge_recovers_a_linear_map_with_an_unpenalised_intercept():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(200, 12))
    y = X @ rng.normal(size=12) + 60.0
    c = fit_folded_ridge(X, y, 1e-9)
    np.testing.assert_allclose(predict_folded(c, X), y, atol=1e-6)
    c = fit_folded_ridge(X, y, 1e6)  # all slopes shrunk away: the intercept alone is the mean
    np.testing.assert_allclose(predict_folded(c, X), y.mean(), atol=0.2)
