"""The regressed-yaw prior of wide-turned heads (fastgha_core/tracking/yawprior.py, fit.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fastgha_core.tracking.fit import FRONTAL_R, FitConfig, LandmarkModel, _Problem, rodrigues
from fastgha_core.tracking.realsets import head_angles_deg
from fastgha_core.tracking.yawprior import layout_features, load_regression, predict_yaw, train_regression


def _layout(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = rng.normal(0.0, 40.0, (468, 2)) + 256.0
    p[10] = [250.0, 150.0]  # forehead
    p[152] = [262.0, 360.0]  # chin
    return p


def test_layout_features_drop_translation_scale_and_roll():
    p = _layout()
    a = math.radians(23.0)
    S = 1.7 * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    q = p @ S.T + np.array([31.0, -12.0])
    np.testing.assert_allclose(layout_features(q), layout_features(p), atol=1e-9)
    mirrored = p * np.array([-1.0, 1.0])  # a mirror is not a similarity: the layout changes
    assert not np.allclose(layout_features(mirrored), layout_features(p))
    with pytest.raises(ValueError, match="468"):
        layout_features(p[:100])
    q = p.copy()
    q[152] = q[10]
    with pytest.raises(ValueError, match="coincide"):
        layout_features(q)


def test_train_regression_recovers_a_linear_map_and_needs_wide_views():
    rng = np.random.default_rng(1)
    pts = np.stack([_layout(s) for s in range(60)])
    w = rng.normal(size=936)
    yaw = np.array([layout_features(p) @ w for p in pts])
    yaw = 70.0 * yaw / np.abs(yaw).max()
    coef = train_regression(pts, yaw, min_yaw=0.0, ridge=1e-9)
    pred = np.array([predict_yaw(p, coef) for p in pts])
    np.testing.assert_allclose(pred, yaw, atol=1e-3)
    with pytest.raises(ValueError, match="at least 10"):
        train_regression(pts[:5], yaw[:5])


def test_shipped_regression_is_loaded():
    coef = load_regression()
    assert coef is not None and coef.shape == (937,) and np.isfinite(coef).all()


def test_yaw_prior_jacobian_matches_finite_differences():
    m = LandmarkModel.from_head_model(num_identity=5, layout="mediapipe")
    rng = np.random.default_rng(0)
    Rs = np.stack([FRONTAL_R @ rodrigues(np.radians([5, 60, 3])), FRONTAL_R @ rodrigues(np.radians([-4, -70, 2]))])
    ts = np.array([[0.0, 0.0, 1.0], [0.01, 0.0, 0.9]])
    K = np.array([[600.0, 0, 256], [0, 600, 256], [0, 0, 1]])
    p = _Problem(m, rng.normal(256, 50, (2, m.num_points, 2)), np.stack([K, K]), FitConfig(), None, True, True)
    p.yaw_target = np.array([math.radians(75.0), math.radians(-85.0)])
    beta, E = rng.normal(size=5) * 0.3, rng.uniform(0, 0.5, (2, 53))
    J, r0 = p.jacobian(beta, E, Rs, ts), p.residuals(beta, E, Rs, ts)
    assert J.shape[0] == r0.shape[0]
    yaw = np.radians([head_angles_deg(R)[0] for R in Rs])  # the same convention as the real-set report
    np.testing.assert_allclose(r0[-2:], (yaw - p.yaw_target) / math.radians(0.2), rtol=1e-9)
    for c in range(J.shape[1]):
        x = np.zeros(J.shape[1])
        x[c] = 1e-6
        num = (p.residuals(*p.apply(x, beta, E, Rs, ts))[-2:] - r0[-2:]) / 1e-6
        np.testing.assert_allclose(J[-2:, c], num, rtol=1e-4, atol=1e-3)


def test_calibration_table_bins_both_ways():
    from fastgha_core.tracking.yawprior import calibration_table

    true = np.array([60.0, 61.0, -59.0, 80.0, -80.0, 85.0])
    read = np.array([63.0, 64.0, -66.0, 62.0, 64.0, 67.0])  # the -80 view read on the wrong side
    t = calibration_table(true, read)
    rows = {c: (n, m, e) for c, n, m, e in t["by_true"]}
    assert sorted(rows) == [60.0, 80.0, 85.0]
    n, m, e = rows[60.0]
    assert n == 3 and m == pytest.approx((63 + 64 + 66) / 3) and e == pytest.approx((3 + 3 + 7) / 3)
    n, m, e = rows[80.0]
    assert n == 2 and m == pytest.approx((62 - 64) / 2) and e == pytest.approx((18 + 144) / 2)
    reads = {c: (n, m) for c, n, m in t["by_reading"]}
    assert reads[60.0] == (3, pytest.approx((60 + 61 + 80) / 3)) and reads[65.0] == (2, pytest.approx((59 + 85) / 2))
    assert reads[-65.0] == (1, pytest.approx(80.0))
    with pytest.raises(ValueError, match="same length"):
        calibration_table(true, read[:3])
