"""Off-head pixels beside the face lie no nearer their camera than the ears' plane
(``model/surface.py`` ``off_head_behind_ears``, ``GaussianHeadConfig.off_head_behind_ears``; issue 17:
a frontal photo's hair beside the cheeks stood in front of the mouth of side views)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastgha_core.cameras import Cameras
from fastgha_core.model.surface import (
    BESIDE_FACE_LATERAL_M,
    BESIDE_FACE_MAX_MOVE_M,
    HeadSurface,
    off_head_behind_ears,
    surface_ray_depth,
)
from fastgha_core.tracking.camera import pose_to_cameras
from fastgha_core.tracking.fit import FRONTAL_R, default_intrinsics, rodrigues

S = 64


def _view(yaw_deg: float = 0.0, pitch_deg: float = 0.0, dist: float = 0.6):
    R = FRONTAL_R @ rodrigues(np.array([np.radians(pitch_deg), np.radians(yaw_deg), 0.0]))
    return pose_to_cameras(R[None], np.array([[0.0, 0.01, dist]]), default_intrinsics(S, S, 40.0), S, S)


def _head(views: int = 1, head_to_world=None):
    return HeadSurface(np.zeros(100, np.float32), np.zeros((views, 53), np.float32), head_to_world)


def _points(cam: Cameras, t: torch.Tensor) -> torch.Tensor:
    o, d = cam.to(dtype=torch.float64).pixel_rays()
    return (o + t.double()[..., None] * d)[0]  # [S, S, 3]


def test_hair_beside_a_frontal_face_moves_back_to_the_ears_plane():
    from fastgha_core.data.headmodel import HeadModel

    cam, head = _view(), _head()
    sd = surface_ray_depth(head, cam)
    out = off_head_behind_ears(sd, head, cam)
    moved = (out.t != sd.t)[0]
    assert int(moved.sum()) > 20  # a band either side of the cheeks
    assert not bool((moved & sd.hit[0]).any())  # the head's own pixels keep their distance
    before, after = _points(cam, sd.t)[moved], _points(cam, out.t)[moved]
    assert float(after[:, 2].abs().max()) < 1e-4  # on the ears' coronal plane (head frame z = 0)
    assert bool((before[:, 2] > 0).all()) and bool((before[:, 0].abs() > BESIDE_FACE_LATERAL_M).all())
    step = (out.t - sd.t)[0][moved]
    assert float(step.min()) > 0 and float(step.max()) <= BESIDE_FACE_MAX_MOVE_M + 1e-6  # only ever further back
    hm = HeadModel.load()
    verts = head.vertices(0, hm)
    chin, brow = float(verts[hm.landmarks68[8], 1]), float(verts[hm.landmarks68[17:27], 1].mean())
    assert bool((before[:, 1] > chin).all())  # the neck and the collar below the chin keep theirs
    assert bool((before[:, 1] < brow).all())  # hair above the brows (the temples, the crown) keeps its place


def test_hair_above_the_brows_stays_where_it_would_otherwise_move():
    """A view from above sees off-head pixels beside the skull above the brows that pass every other
    test (beside the face, in front of the ears, a move within the limit): they stay."""
    from fastgha_core.data.headmodel import HeadModel

    hm = HeadModel.load()
    for pitch in (0.0, -25.0):
        cam, head = _view(pitch_deg=pitch), _head()
        sd = surface_ray_depth(head, cam)
        out = off_head_behind_ears(sd, head, cam)
        p = _points(cam, sd.t)
        o, d = cam.to(dtype=torch.float64).pixel_rays()
        t_plane = -o[0, ..., 2] / d[0, ..., 2]
        verts = head.vertices(0, hm)
        brow = float(verts[hm.landmarks68[17:27], 1].mean())
        other_tests = (~sd.hit[0] & (p[..., 0].abs() > BESIDE_FACE_LATERAL_M) & (p[..., 2] > 0)
                       & (t_plane > sd.t[0].double()) & (t_plane - sd.t[0].double() <= BESIDE_FACE_MAX_MOVE_M))
        above = other_tests & (p[..., 1] > brow)
        assert int(above.sum()) > 0  # the case exists
        assert torch.equal(out.t[0][above], sd.t[0][above])


def test_the_head_frame_is_taken_through_head_to_world():
    cam, head = _view(), _head()
    ref = off_head_behind_ears(surface_ray_depth(head, cam), head, cam).t
    h2w = np.eye(4)
    h2w[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    h2w[:3, 3] = [0.05, -0.02, 0.1]
    w2c = cam.w2c[0].double().numpy() @ np.linalg.inv(h2w)  # the same camera, with the head placed in another world
    cam_w = Cameras(cam.K, torch.from_numpy(w2c).float()[None], S, S)
    head_w = _head(head_to_world=h2w)
    sd = surface_ray_depth(head_w, cam_w)
    out = off_head_behind_ears(sd, head_w, cam_w).t
    moved_ref, moved = ref != surface_ray_depth(head, cam).t, out != sd.t
    assert int((moved_ref ^ moved).sum()) <= 2  # the same pixels, up to float rounding at the borders
    both = moved_ref & moved
    assert float((out[both] - ref[both]).abs().max()) < 1e-4


def test_side_views_keep_their_off_head_pixels():
    for yaw in (70.0, -80.0):
        cam, head = _view(yaw), _head()
        sd = surface_ray_depth(head, cam)
        assert torch.equal(off_head_behind_ears(sd, head, cam).t, sd.t)


def test_it_checks_its_inputs():
    cam, head = _view(), _head()
    sd = surface_ray_depth(head, cam)
    with pytest.raises(ValueError, match="lateral_m and max_move_m must be > 0"):
        off_head_behind_ears(sd, head, cam, lateral_m=0.0)
    with pytest.raises(ValueError, match="max_angle_deg must be in"):
        off_head_behind_ears(sd, head, cam, max_angle_deg=120.0)
    with pytest.raises(ValueError, match="surface views"):
        off_head_behind_ears(sd, _head(2), cam)


def test_reconstruct_moves_only_those_gaussians():
    from fastgha_core.model.fastgha import load_model

    model = load_model("tiny")
    s = model.config.input_size
    yaws = [0.0, 35.0]
    R = np.stack([FRONTAL_R @ rodrigues(np.array([0.0, np.radians(y), 0.0])) for y in yaws])
    cams = pose_to_cameras(R, np.tile([0.0, 0.01, 0.6], (2, 1)), default_intrinsics(s, s, 40.0), s, s)
    head = _head(2)
    imgs = torch.rand(2, 3, s, s)
    gc = model.config.gaussians
    assert gc.off_head_behind_ears  # the default
    gc.mirror_views = False  # the photos' own Gaussians only (a fresh model: nothing to restore)
    gc.off_head_extrude_m = 0.0  # ... one per pixel (no copies of long hair further back)
    gc.prune_opacity, model.config.deform.prior = 0.0, False  # keep every pixel's Gaussian, in order
    gc.off_head_smooth = 0.0  # the moved pixels alone (the relaxation of the others depends on which moved: test_surface_smooth.py)
    on = model.reconstruct(imgs, cams, surface=head).gaussians
    gc.off_head_behind_ears = False
    off = model.reconstruct(imgs, cams, surface=head).gaussians
    changed = (on.means != off.means).any(-1)
    assert int(changed.sum()) > 20
    p_on, p_off = on.means[changed], off.means[changed]
    assert float(p_on[:, 2].abs().max()) < 1e-3  # the tracker's world is the head frame: on the ears' plane
    assert bool((p_off[:, 2] > 0).all()) and bool((p_off[:, 0].abs() > BESIDE_FACE_LATERAL_M - 1e-3).all())
    assert torch.equal(on.colors[~changed], off.colors[~changed])
