"""Synthetic heads: determinism, landmark/mask/depth consistency, cameras, expressions, depth prior."""

import pickle

import numpy as np
import pytest
import torch

from fastgha_core.cameras import Cameras
from fastgha_core.constants import BACKGROUND_RGB
from fastgha_core.data.headmodel import HeadModel
from fastgha_core.data.synthetic import (
    FOV_DEG,
    HELDOUT_SEEDS,
    TRAIN_SEEDS,
    camera_rig,
    degrade_depth,
    expression_trajectory,
    make_sequence,
    render_views,
)


def _bytes(view):
    return view.image.numpy().tobytes() + view.mask.numpy().tobytes() + view.depth.numpy().tobytes()


def test_seed_ranges_disjoint():
    assert set(TRAIN_SEEDS).isdisjoint(HELDOUT_SEEDS)
    assert len(HELDOUT_SEEDS) >= 1000


def test_same_seed_same_bytes_and_seeds_differ():
    a = make_sequence(7, timesteps=3, num_cameras=3, resolution=48)
    b = make_sequence(7, timesteps=3, num_cameras=3, resolution=48)
    c = make_sequence(8, timesteps=3, num_cameras=3, resolution=48)
    assert _bytes(a.view(2, 1)) == _bytes(b.view(2, 1))
    assert torch.equal(a.cameras(0).w2c, b.cameras(0).w2c) and torch.equal(a.expression(1), b.expression(1))
    assert _bytes(a.view(2, 1)) != _bytes(c.view(2, 1))
    # a pickled copy (DataLoader workers) renders the same bytes
    d = pickle.loads(pickle.dumps(a))
    assert _bytes(d.view(2, 1)) == _bytes(a.view(2, 1))


def test_view_contract():
    seq = make_sequence(3, timesteps=2, num_cameras=2, resolution=64)
    assert seq.expression_space == "ict53" and seq.expression(0).shape == (53,)
    assert len(seq.cameras(0)) == 2 and seq.cameras(0).width == 64
    v = seq.view(1, 0)
    assert v.image.shape == (3, 64, 64) and v.image.dtype == torch.float32
    assert v.mask.shape == (1, 64, 64) and v.depth.shape == (1, 64, 64)
    assert 0 <= v.image.min() and v.image.max() <= 1
    bg = v.mask[0] == 0
    assert bg.any() and (v.mask[0] == 1).any()
    torch.testing.assert_close(v.image[:, bg], torch.tensor(BACKGROUND_RGB).view(3, 1).expand(3, int(bg.sum())))
    assert (v.depth[0][bg] == 0).all() and (v.depth[0][v.mask[0] == 1] > 0.7).all()
    with pytest.raises(IndexError):
        seq.view(2, 0)


def test_landmarks_project_onto_mask_and_depth():
    """Frontal camera: the 68 landmarks of the face interior lie on the rendered head, and the
    rendered depth at the landmarks that face the camera (brows, nose, outer lips, chin) equals
    their camera z. Tolerance: a 256-px pixel at 1 m is 1.24 mm wide (FOV 18 deg); the depth is the
    mean over the pixel's 2x2 samples and on slanted surfaces (nose sides, lips) changes by up to
    ~3 mm across a pixel, so 5 mm max and 2 mm median."""
    seq = make_sequence(11, timesteps=4, num_cameras=4, resolution=256)
    cam = Cameras.look_at(torch.tensor([[0.0, 0.0, 1.0]]), fov_deg=FOV_DEG, width=256, height=256)
    for t in (0, 3):
        view = render_views(seq, t, cam)[0]
        lm = torch.from_numpy(seq.landmarks(t).astype(np.float32))  # [68, 3]
        uv, z = cam.project(lm)
        uv, z = uv[0], z[0]
        px = uv.floor().long()
        assert ((px >= 0) & (px < 256)).all()
        mask = view.mask[0, px[:, 1], px[:, 0]]
        assert (mask[17:68] > 0.99).all(), mask
        sel = list(range(17, 27)) + list(range(27, 36)) + list(range(48, 60)) + [8]
        d = view.depth[0, px[sel, 1], px[sel, 0]]
        err = (d - z[sel]).abs()
        assert err.max() < 5e-3, err
        assert err.median() < 2e-3, err


def test_camera_rig_spread_and_framing():
    cams = camera_rig(np.random.default_rng(0), 16, 128)
    c = cams.centers.double()
    dist = c.norm(dim=-1)
    assert ((dist > 0.93) & (dist < 1.08)).all()
    yaw = torch.rad2deg(torch.atan2(c[:, 0], c[:, 2]))
    pitch = torch.rad2deg(torch.asin(c[:, 1] / dist))
    assert yaw.abs().max() <= 94 and yaw.max() > 70 and yaw.min() < -70
    assert pitch.abs().max() <= 38 and pitch.max() > 15 and pitch.min() < -15
    assert (c[:, 2] > -0.1).all()  # frontal hemisphere (yaw <= ~90 deg)
    uv, _ = cams.project(torch.zeros(1, 3))
    # the head centre projects near the image centre: the look-at target is jittered by <= 1 cm per
    # axis, 1 cm = 128 px / 0.317 m * 0.01 = 4 px, so 8 px bounds it with margin
    assert ((uv - 64).abs() < 8).all()


def test_expressions_sparse_smooth_and_in_range():
    names = HeadModel.load().expression_names
    neutral_frac = []
    for s in range(8):
        e = expression_trajectory(np.random.default_rng(s), 64, names)
        assert e.shape == (64, 53) and e.dtype == np.float32
        assert e.min() >= 0 and e.max() <= 1
        neutral_frac.append(float((e.max(axis=1) < 0.25).mean()))
    assert np.mean(neutral_frac) > 0.45  # near-neutral frames dominate
    strong = expression_trajectory(np.random.default_rng(0), 64, names, activity=0.9, strength=(0.6, 1.0))
    assert (strong.max(axis=1) > 0.5).mean() > 0.6
    # gestures exercise many different blendshapes across subjects
    used = sum((expression_trajectory(np.random.default_rng(s), 64, names).max(0) > 0.3) for s in range(8))
    assert (used > 0).sum() >= 20


def test_subjects_look_different():
    a = make_sequence(20, timesteps=1, num_cameras=1, resolution=48).view(0, 0)
    b = make_sequence(21, timesteps=1, num_cameras=1, resolution=48).view(0, 0)
    both = (a.mask[0] > 0.99) & (b.mask[0] > 0.99)
    assert (a.image[:, both] - b.image[:, both]).abs().mean() > 0.03


def test_degrade_depth():
    d = torch.zeros(1, 64, 64)
    d[0, 16:48, 16:48] = 1.0
    out = degrade_depth(d, np.random.default_rng(0), noise_std=0.002, blur_sigma=1.0, hole_fraction=0.05)
    assert isinstance(out, torch.Tensor) and out.shape == d.shape
    assert (out[d == 0] == 0).all()  # no values outside the surface
    inside = d > 0
    holes = (out == 0) & inside
    assert 0 < holes.sum() < inside.sum() * 0.3
    kept = (out > 0) & inside
    assert (out[kept] - 1.0).abs().mean() < 0.05
    same = degrade_depth(d.numpy(), np.random.default_rng(0), noise_std=0.002, blur_sigma=1.0, hole_fraction=0.05)
    np.testing.assert_array_equal(same, out.numpy())
    clean = degrade_depth(d, np.random.default_rng(0), noise_std=0, blur_sigma=0, scale_error=0, hole_fraction=0)
    torch.testing.assert_close(clean, d)
