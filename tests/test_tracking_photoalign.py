"""Photometric registration of the photos' head poses (tracking/photoalign.py), on synthetic renders
with known cameras: a known pose perturbation is undone; the rotation's derivative; the paths that
must leave the poses alone; the landmark guard."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

pytest.importorskip("cv2", reason="needs OpenCV (the 'faces' extra)")

from fastgha_core.cameras import Cameras  # noqa: E402
from fastgha_core.data.synthetic import SyntheticSubject  # noqa: E402
from fastgha_core.tracking.fit import LandmarkModel, rodrigues  # noqa: E402
from fastgha_core.tracking.photoalign import PhotoAlignConfig, axis_angle_to_matrix, register_photos, sample_face_surface  # noqa: E402

FAST = PhotoAlignConfig()


@pytest.fixture(scope="module")
def scene():
    """One synthetic subject (not a training seed of the yaw tables) at azimuth 0, +25 and -25 degrees, 320 x 320."""
    sub = SyntheticSubject(1_000_207)
    e = np.zeros(53, np.float32)
    frame = sub.frame(e)
    ims, R, t, K = [], [], [], []
    for az in (0.0, 25.0, -25.0):
        a = -math.radians(az)
        cam = Cameras.look_at([math.sin(a), 0.05, math.cos(a)], fov_deg=25, width=320, height=320).flatten()
        ims.append((sub.render(frame, cam)[0].image.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8))
        w2c = cam.w2c[0].double().numpy()
        R.append(w2c[:3, :3])
        t.append(w2c[:3, 3])
        K.append(cam.K[0].double().numpy())
    return sub, ims, np.stack(R), np.stack(t), np.stack(K)


def _reprojection_px(sub, R, t, K, Rt, tt) -> np.ndarray:
    """Mean image distance per view between the face points projected with (R, t) and with the truth."""
    X = sample_face_surface(sub.model, 3000, 5).points(sub.model.vertices(sub.identity).astype(np.float64))
    out = []
    for v in range(len(R)):
        a, b = X @ R[v].T + t[v], X @ Rt[v].T + tt[v]
        a, b = (a @ K[v].T)[:, :2] / (a @ K[v].T)[:, 2:], (b @ K[v].T)[:, :2] / (b @ K[v].T)[:, 2:]
        out.append(np.linalg.norm(a - b, axis=1).mean())
    return np.array(out)


def test_recovers_a_known_pose_perturbation(scene):
    sub, ims, R, t, K = scene
    Rp, tp = R.copy(), t.copy()
    Rp[1] = rodrigues(np.radians([1.2, -1.5, 0.8])) @ R[1]
    tp[1] = t[1] + [0.002, -0.002, 0.0]
    Rp[2] = rodrigues(np.radians([-1.0, 1.8, -0.6])) @ R[2]
    tp[2] = t[2] + [-0.003, 0.001, 0.0]
    before = _reprojection_px(sub, Rp, tp, K, R, t)
    al = register_photos(ims, sub.identity, np.zeros((3, 53)), Rp, tp, K, FAST)
    after = _reprojection_px(sub, al.rotations, al.translations, K, R, t)
    assert al.reference == 0  # the most frontal view is held fixed
    np.testing.assert_allclose(al.rotations[0], Rp[0])
    assert before[1:].min() > 2.0, before  # the perturbation moves the face by pixels
    assert (after[1:] < 0.6 * before[1:]).all() and after[1:].mean() < 0.5 * before[1:].mean(), (before, after)
    assert al.ncc_after > al.ncc_before + 0.1
    assert al.rotation_deg[0] == 0.0 and (al.rotation_deg[1:] > 0).all()


def test_only_photos_turned_far_enough_are_corrected(scene):
    """``free_min_yaw_deg``: a photo the given poses turn less than it keeps its pose exactly, one
    turned further is registered to the others (here both are 3 degrees off the truth)."""
    from fastgha_core.tracking.fit import head_angles_deg

    sub, ims, R, t, K = scene
    Rp = R.copy()
    Rp[1] = rodrigues(np.radians([0.0, -3.0, 0.0])) @ R[1]
    Rp[2] = rodrigues(np.radians([0.0, -3.0, 0.0])) @ R[2]
    yaws = [abs(head_angles_deg(r)[0]) for r in Rp]
    assert yaws[1] > 27.0 and yaws[2] < 23.0, yaws  # the set-up: one photo either side of 25 degrees
    before = _reprojection_px(sub, Rp, t, K, R, t)
    al = register_photos(ims, sub.identity, np.zeros((3, 53)), Rp, t, K, PhotoAlignConfig(free_min_yaw_deg=25.0))
    after = _reprojection_px(sub, al.rotations, al.translations, K, R, t)
    np.testing.assert_array_equal(al.rotations[[0, 2]], Rp[[0, 2]])
    np.testing.assert_array_equal(al.translations[[0, 2]], t[[0, 2]])
    assert al.rotation_deg[2] == 0.0 and al.rotation_deg[1] > 0.5
    assert after[1] < 0.6 * before[1], (before, after)
    # no photo turned that far: nothing is computed, nothing moves
    none = register_photos(ims, sub.identity, np.zeros((3, 53)), Rp, t, K, PhotoAlignConfig(free_min_yaw_deg=40.0))
    np.testing.assert_array_equal(none.rotations, Rp)
    assert (none.rotation_deg == 0).all() and np.isnan(none.ncc_before)
    # with no bound both move
    both = register_photos(ims, sub.identity, np.zeros((3, 53)), Rp, t, K, FAST)
    assert both.rotation_deg[1] > 0.5 and both.rotation_deg[2] > 0.5


def test_true_poses_stay_close(scene):
    """Started at the truth, the registration must not wander off it."""
    sub, ims, R, t, K = scene
    al = register_photos(ims, sub.identity, np.zeros((3, 53)), R, t, K, FAST)
    assert _reprojection_px(sub, al.rotations, al.translations, K, R, t).max() < 1.5


def test_axis_angle_matches_rodrigues_and_its_gradient():
    for w in ([0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [1e-5, 2e-5, -1e-5], [0.0, 2.0, 0.0]):
        got = axis_angle_to_matrix(torch.tensor(w, dtype=torch.float64)).numpy()
        np.testing.assert_allclose(got, rodrigues(np.array(w)), atol=1e-12)
    for w in ([0.3, -0.2, 0.1], [1e-6, -2e-6, 1e-6]):  # autograd against finite differences, also near 0
        assert torch.autograd.gradcheck(axis_angle_to_matrix, (torch.tensor(w, dtype=torch.float64, requires_grad=True),))


def test_no_op_paths_and_refusals(scene):
    sub, ims, R, t, K = scene
    one = register_photos(ims[:1], sub.identity, np.zeros((1, 53)), R[:1], t[:1], K[:1], FAST)
    np.testing.assert_array_equal(one.rotations, R[:1])
    np.testing.assert_array_equal(one.translations, t[:1])
    # photos that share too few points: nothing to compare, nothing moves
    apart = register_photos(ims, sub.identity, np.zeros((3, 53)), R, t, K, PhotoAlignConfig(points=2000, min_shared=10**6))
    np.testing.assert_array_equal(apart.rotations, R)
    assert (apart.rotation_deg == 0).all() and apart.shared[0, 1] > 0
    np.testing.assert_array_equal(apart.identity, sub.identity)  # the identity comes back too (the pipeline may take it)
    with pytest.raises(ValueError, match=r"expected 3 photos' rotations"):
        register_photos(ims, sub.identity, np.zeros((2, 53)), R, t, K, FAST)
    with pytest.raises(ValueError, match="landmark_model"):
        register_photos(ims, sub.identity, np.zeros((3, 53)), R, t, K, FAST, landmarks=[np.zeros((68, 2))] * 3)
    with pytest.raises(ValueError, match="reference"):
        register_photos(ims, sub.identity, np.zeros((3, 53)), R, t, K, FAST, reference=5)


def test_landmark_guard_holds_the_fit(scene):
    """With the detected landmarks exactly where the perturbed poses put them and no growth
    allowed, every correction is shrunk until the landmark RMS stays within the slack."""
    sub, ims, R, t, K = scene
    Rp, tp = R.copy(), t.copy()
    Rp[1] = rodrigues(np.radians([1.2, -1.5, 0.8])) @ R[1]
    Rp[2] = rodrigues(np.radians([-1.0, 1.8, -0.6])) @ R[2]
    model = LandmarkModel.from_head_model(sub.model, num_identity=100, layout="dlib68")
    X = model.points(sub.identity.astype(np.float64), np.zeros(53))
    lms = []
    for v in range(3):
        P = X @ Rp[v].T + tp[v]
        lms.append((P @ K[v].T)[:, :2] / (P @ K[v].T)[:, 2:])
    cfg = PhotoAlignConfig(max_rms_growth=1.0, rms_slack_frac=0.002)
    al = register_photos(ims, sub.identity, np.zeros((3, 53)), Rp, tp, K, cfg, landmarks=lms, landmark_model=model)
    face = [float(np.linalg.norm(lm.max(0) - lm.min(0))) for lm in lms]
    np.testing.assert_allclose(al.rms_before, 0.0, atol=1e-6)
    assert all(al.rms_after[v] <= 0.002 * face[v] + 1e-9 for v in range(3)), al.rms_after
    assert set(al.shrunk) == {1, 2}  # the unguarded registration moves both (previous test)


def test_track_photos_applies_it_only_when_asked(scene):
    """``TrackConfig.photo_align`` replaces the landmark fit's poses by the registered ones, and the
    crops' cameras and the reported landmark RMS follow them; by default only photos turned beyond
    ``TURNED_MIN_YAW_DEG`` are corrected (none here, at 0 and +-25 degrees)."""
    try:
        from fastgha_core.tracking.faces import MeshDetector

        det = MeshDetector(min_face_px=1.0)
    except Exception as e:  # pragma: no cover - without the extra
        pytest.skip(f"needs the 'faces' extra with mediapipe (make install-test): {e}")
    from fastgha_core.tracking.pipeline import TrackConfig, track_photos

    sub, ims, R, t, K = scene
    from fastgha_core.tracking.pipeline import TURNED_MIN_YAW_DEG

    assert TrackConfig().photo_align and TrackConfig().align.free_min_yaw_deg == TURNED_MIN_YAW_DEG == 55.0
    off = track_photos(ims, TrackConfig.with_photo_align("off", size=64), detector=det)
    default = track_photos(ims, TrackConfig(size=64), detector=det)
    assert default.alignment is not None and (default.alignment.rotation_deg == 0).all()  # no photo turned that far
    np.testing.assert_allclose(default.fit.rotations, off.fit.rotations)
    on = track_photos(ims, TrackConfig.with_photo_align("all", size=64), detector=det)
    assert off.alignment is None and on.alignment is not None
    with pytest.raises(ValueError, match="off, turned, all"):
        TrackConfig.with_photo_align("some")
    # the same landmark fit before it (the fit measures with the yaw map of its last round, the registration at the final yaw)
    np.testing.assert_allclose(on.alignment.rms_before, off.fit.rms_px, rtol=0.02)
    np.testing.assert_allclose(on.fit.rotations, on.alignment.rotations)
    np.testing.assert_allclose(on.fit.rms_px, on.alignment.rms_after)
    v = int(np.argmax(on.alignment.rotation_deg))
    assert on.alignment.rotation_deg[v] > 0.05
    assert not np.allclose(on.cameras.w2c[v].numpy(), off.cameras.w2c[v].numpy(), atol=1e-6)
    np.testing.assert_allclose(on.cameras.w2c[on.alignment.reference].numpy(), off.cameras.w2c[on.alignment.reference].numpy(), atol=1e-6)


def test_identity_modes_move_only_the_first_modes(scene):
    sub, ims, R, t, K = scene
    start = np.zeros(100)
    start[:50] = 0.5 * sub.identity[:50]
    poses_only = register_photos(ims, start, np.zeros((3, 53)), R, t, K, FAST)
    np.testing.assert_array_equal(poses_only.identity, start)
    shaped = register_photos(ims, start, np.zeros((3, 53)), R, t, K, PhotoAlignConfig(identity_modes=5))
    np.testing.assert_array_equal(shaped.identity[5:], start[5:])
    assert np.abs(shaped.identity[:5] - start[:5]).max() > 1e-3
    assert shaped.ncc_after > shaped.ncc_before
