"""Gaussians of pixels that see the tracked surface at a grazing angle are lengthened along it
(``model/surface.py``: ``surface_steps``, ``stretch_to_patches``; issue 17, the dark hatched streak
down the nose's far flank of real avatars' frontal renders)."""

from __future__ import annotations

import math

import pytest
import torch

from fastgha_core.cameras import Cameras
from fastgha_core.gaussians import Gaussians
from fastgha_core.model.surface import away_from_face_features, behind_occluding_edges, stretch_to_patches, surface_steps
from fastgha_core.render import render

S = 48


def _plane_view(angle_deg: float, dist: float = 0.6):
    """A camera ``angle_deg`` from the normal of the plane z = 0 and each pixel's distance to it."""
    a = math.radians(angle_deg)
    cam = Cameras.look_at(torch.tensor([[dist * math.sin(a), 0.0, dist * math.cos(a)]]), fov_deg=20.0, width=S, height=S)
    o, d = cam.pixel_rays()
    t = -o[..., 2] / d[..., 2]  # [1, S, S]: every ray of this field of view meets the plane
    return cam, t.float()


def _pixel_gaussians(cam, t, opacity=0.95):
    o, d = cam.pixel_rays()
    means = (o + t[..., None] * d).reshape(-1, 3).float()
    n = len(means)
    foot = (t / cam.K[:, 0, 0, None, None]).reshape(-1, 1).float()
    return Gaussians(
        means=means,
        quats=torch.tensor([1.0, 0, 0, 0]).repeat(n, 1),
        scales=(0.6 * foot).expand(n, 3).contiguous(),  # a little more than half a footprint: head-on neighbours join
        opacities=torch.full((n,), opacity),
        colors=torch.full((n, 3), 0.5),
    )


def test_steps_measure_the_slope_and_skip_occluding_edges():
    cam, t = _plane_view(70.0)
    steps, foot = surface_steps(t, cam)
    ratio = steps[0, S // 2, S // 2].norm(dim=-1) / foot[0, S // 2, S // 2]
    assert abs(float(ratio[0]) - 1 / math.cos(math.radians(70.0))) < 0.25  # along the slope: footprint / cos(incidence)
    assert abs(float(ratio[1]) - 1.0) < 0.1  # across it: one footprint
    flat_cam, flat_t = _plane_view(0.0)
    stepped = flat_t.clone()
    stepped[:, :, S // 2 :] += 0.05  # a 5 cm step, ~20 footprints: an occluding edge (the nose ridge)
    steps, foot = surface_steps(stepped, flat_cam)
    r = steps[0, S // 2].norm(dim=-1)[:, 0] / foot[0, S // 2]
    assert float((r - 1).abs().max()) < 0.1  # the edge's pixels keep their one-sided step


def test_a_surface_seen_at_a_grazing_angle_is_covered_from_its_front():
    cam, t = _plane_view(75.0)
    g = _pixel_gaussians(cam, t)
    front = Cameras.look_at(torch.tensor([[0.0, 0.0, 0.6]]), fov_deg=20.0, width=S, height=S)
    box = (slice(S // 2 - 4, S // 2 + 4), slice(S // 2 - 4, S // 2 + 4))
    before = render(g, front).alpha[0, 0][box]
    assert float(before.min()) < 0.5  # the setting: gaps between the grazing view's columns
    out = stretch_to_patches(g, *surface_steps(t, cam))
    after = render(out, front).alpha[0, 0][box]
    assert float(after.min()) > 0.9
    assert torch.equal(out.means, g.means) and torch.equal(out.opacities, g.opacities)
    # the source view itself barely changes: the added length lies almost along its rays
    a0, a1 = render(g, cam).rgb, render(out, cam).rgb
    assert float((a0 - a1).abs().mean()) < 0.02


def test_head_on_pixels_keep_their_gaussians():
    cam, t = _plane_view(20.0)  # patches 1.06 footprints long: below min_ratio
    g = _pixel_gaussians(cam, t)
    out = stretch_to_patches(g, *surface_steps(t, cam))
    assert torch.equal(out.scales, g.scales) and torch.equal(out.quats, g.quats)


def test_stretch_checks_its_sizes():
    cam, t = _plane_view(70.0)
    g = _pixel_gaussians(cam, t)
    steps, foot = surface_steps(t, cam)
    with pytest.raises(ValueError, match="expected"):
        stretch_to_patches(g[: len(g) - 1], steps, foot)
    with pytest.raises(ValueError, match="surface_steps: t must have shape"):
        surface_steps(t[0], cam)
    with pytest.raises(ValueError, match="behind_occluding_edges: t must have shape"):
        behind_occluding_edges(t[0], cam)


def test_only_pixels_just_behind_an_occluding_edge_are_flagged():
    cam, t = _plane_view(0.0)
    assert not bool(behind_occluding_edges(t, cam).any())  # a smooth surface has no edge
    stepped = t.clone()
    stepped[:, :, S // 2 :] += 0.05  # the right half 5 cm further: behind the left half's edge
    m = behind_occluding_edges(stepped, cam, radius_px=3)[0]
    cols = m.any(0).nonzero()[:, 0].tolist()
    assert cols == list(range(S // 2, S // 2 + 3))  # three columns behind the edge, none in front of it
    # where= limits the stretch to those pixels
    slope_cam, slope_t = _plane_view(75.0)
    g = _pixel_gaussians(slope_cam, slope_t)
    where = torch.zeros(1, S, S, dtype=torch.bool)
    where[:, :, 20:25] = True
    out = stretch_to_patches(g, *surface_steps(slope_t, slope_cam), where=where)
    changed = (out.scales != g.scales).any(-1).reshape(S, S)
    assert bool(changed[:, 20:25].all()) and not bool(changed[:, :20].any() or changed[:, 25:].any())


def test_reconstruct_lengthens_grazing_gaussians_away_from_the_face_features():
    import numpy as np

    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.model.surface import HeadSurface, surface_ray_depth
    from fastgha_core.tracking.camera import pose_to_cameras
    from fastgha_core.tracking.fit import FRONTAL_R, default_intrinsics, rodrigues

    model = load_model("tiny")
    s = model.config.input_size
    yaws = [0.0, 35.0, -35.0]
    R = np.stack([FRONTAL_R @ rodrigues(np.array([0.0, np.radians(y), 0.0])) for y in yaws])
    cams = pose_to_cameras(R, np.tile([0.0, 0.01, 0.6], (3, 1)), default_intrinsics(s, s, 30.0), s, s)
    head = HeadSurface(np.zeros(100, np.float32), np.zeros((3, 53), np.float32))
    imgs = torch.tensor(BACKGROUND_RGB, dtype=torch.float32).view(1, 3, 1, 1).repeat(3, 1, s, s)
    imgs[:, :, s // 4 : 3 * s // 4, s // 4 : 3 * s // 4] = torch.rand(3, 3, s // 2, s // 2)
    gc = model.config.gaussians
    assert gc.grazing_stretch > 0 and gc.grazing_edge_px == 0 and gc.grazing_keep_features_mm > 0  # the defaults
    gc.mirror_views = False  # the photos' own Gaussians only (a fresh model: nothing to restore)
    gc.off_head_extrude_m = 0.0  # ... one per pixel (no copies of long hair further back)
    gc.prune_opacity, model.config.deform.prior = 0.0, False  # keep every pixel's Gaussian, in order
    gc.off_head_behind_ears, gc.off_head_smooth = False, 0.0  # the off-head pixels where surface_ray_depth puts them (the edges below are found on its depth)

    def changed_by(**fields):
        for k, v in fields.items():
            setattr(gc, k, v)
        on = model.reconstruct(imgs, cams, surface=head).gaussians
        assert torch.equal(on.means, off.means)
        ch = (on.scales != off.scales).any(-1).reshape(3, s, s)
        grown = on.scales.max(-1).values.reshape(3, s, s)[ch] / off.scales.max(-1).values.reshape(3, s, s)[ch]
        assert float(grown.min()) >= 1.0 - 1e-5 and float(grown.max()) > 1.5
        return ch

    gc.grazing_stretch = 0.0
    off = model.reconstruct(imgs, cams, surface=head).gaussians
    t = surface_ray_depth(head, cams).t
    # behind an occluding edge only, on the features too (the first form of the stretch)
    changed = changed_by(grazing_stretch=1.0, grazing_edge_px=3, grazing_keep_features_mm=0.0)
    near = behind_occluding_edges(t, cams, 3)
    assert bool(changed[1:].any())  # the turned views see the far side of the nose at a grazing angle
    assert not bool((changed & ~near).any())  # nothing away from an occluding edge
    # the default: everywhere but the brows, eyes, nose and mouth
    changed = changed_by(grazing_edge_px=0, grazing_keep_features_mm=25.0)
    away = away_from_face_features(t, cams, head, 0.025)
    assert not bool((changed & ~away).any())  # nothing within 25 mm of a feature landmark
    assert int(changed[0].sum()) > 20  # the frontal view's cheeks and the side of its head
    everywhere = changed_by(grazing_keep_features_mm=0.0)
    assert bool((everywhere & ~away).any()) and bool((changed & ~everywhere).sum() == 0)


def test_feature_pixels_are_those_near_the_tracked_landmarks():
    import numpy as np

    from fastgha_core.data.headmodel import HeadModel
    from fastgha_core.model.surface import FACE_FEATURE_LANDMARKS, HeadSurface, surface_ray_depth
    from fastgha_core.tracking.camera import pose_to_cameras
    from fastgha_core.tracking.fit import FRONTAL_R, default_intrinsics

    hm = HeadModel.load()
    s = 64
    cam = pose_to_cameras(FRONTAL_R[None], np.array([[0.0, 0.01, 0.6]]), default_intrinsics(s, s, 30.0), s, s)
    head = HeadSurface(np.zeros(100, np.float32), np.zeros((1, 53), np.float32))
    t = surface_ray_depth(head, cam).t
    away = away_from_face_features(t, cam, head, 0.02)
    lm = head.vertices(0, hm)[hm.landmarks68]
    uv, _ = cam.project(torch.as_tensor(lm, dtype=torch.float32))
    px = uv.reshape(-1, 2).floor().long().clamp(0, s - 1)  # corner convention: pixel x covers [x, x + 1)
    feats = list(FACE_FEATURE_LANDMARKS)
    assert not bool(away[0, px[feats, 1], px[feats, 0]].any())  # every feature landmark's own pixel is near a feature
    assert bool(away[0, px[[0, 16], 1], px[[0, 16], 0]].all())  # the jaw line's ends (beside the ears) are not
    assert 0.2 < float(away.float().mean()) < 0.95  # a part of the frame, not all or nothing
    with pytest.raises(ValueError, match="radius_m must be > 0"):
        away_from_face_features(t, cam, head, 0.0)
    with pytest.raises(ValueError, match="away_from_face_features: t must have shape"):
        away_from_face_features(t[0], cam, head, 0.02)


def test_surface_points_are_the_views_vertices():
    import numpy as np

    from fastgha_core.data.headmodel import HeadModel
    from fastgha_core.model.surface import HeadSurface

    hm = HeadModel.load()
    rng = np.random.default_rng(0)
    h2w = np.eye(4)
    h2w[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    h2w[:3, 3] = [0.01, 0.02, -0.03]
    head = HeadSurface(rng.normal(size=100).astype(np.float32), rng.uniform(0, 0.6, (3, 53)).astype(np.float32), h2w)
    ids = hm.landmarks68[17:]
    ref = np.stack([head.vertices(v, hm)[ids] for v in range(3)])
    assert np.abs(head.points(ids, hm) - ref).max() < 1e-6
