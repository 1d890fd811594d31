"""The neck cylinder for off-head pixels below the chin (``model/surface.py`` ``neck_cylinder_depth``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastgha_core.data.headmodel import HeadModel
from fastgha_core.model.surface import HeadSurface, neck_ring_vertices, surface_ray_depth
from fastgha_core.tracking.camera import pose_to_cameras
from fastgha_core.tracking.fit import FRONTAL_R, default_intrinsics, rodrigues


def _cameras(yaws_deg, size=128, dist=0.9, h2w=None):
    R = np.stack([FRONTAL_R @ rodrigues(np.array([0.0, np.radians(y), 0.0])) for y in yaws_deg])
    t = np.tile([0.0, -0.12, dist], (len(yaws_deg), 1))  # the camera low: the neck below the mesh in view
    if h2w is not None:  # the same views of a head moved by h2w: w2c' = w2c @ inv(h2w)
        inv = np.linalg.inv(h2w)
        t = np.stack([R[i] @ inv[:3, 3] + t[i] for i in range(len(R))])
        R = np.stack([r @ inv[:3, :3] for r in R])
    return pose_to_cameras(R, t, default_intrinsics(size, size, 30.0), size, size)


def _h2w():
    h = np.eye(4)
    h[:3, :3] = rodrigues(np.array([0.2, -0.4, 0.1]))
    h[:3, 3] = [0.1, -0.2, 0.3]
    return h


@pytest.fixture(scope="module", params=["head frame", "moved head"])
def case(request):
    rng = np.random.default_rng(7)
    ident = np.zeros(100, np.float32)
    ident[:20] = rng.standard_normal(20) * 0.7
    h2w = _h2w() if request.param == "moved head" else None
    surface = HeadSurface(ident, np.zeros((3, 53), np.float32), h2w)
    cams = _cameras([0.0, -70.0, 55.0], h2w=h2w)
    return surface, cams, h2w


def test_below_the_chin_off_head_pixels_lie_on_the_neck_cylinder_and_nothing_else_moves(case):
    surface, cams, h2w = case
    head = HeadModel.load()
    off = surface_ray_depth(surface, cams)
    on = surface_ray_depth(surface, cams, neck="off_head")
    assert torch.equal(off.hit, on.hit) and torch.equal(off.beyond_face, on.beyond_face)
    assert torch.equal(on.t[on.hit], off.t[off.hit])  # the head's own pixels keep their hits
    moved = on.t != off.t
    assert not bool((moved & on.hit).any())
    origins, dirs = cams.flatten().pixel_rays()
    up = np.array([0.0, 1.0, 0.0]) if h2w is None else h2w[:3, 1]
    for v in range(3):
        m = moved[v].numpy()
        assert m.sum() > 50, (v, m.sum())  # the neck below the jaw is in view
        vw = surface.vertices(v, head).astype(np.float64)
        ring = vw[neck_ring_vertices(head)]
        c = ring.mean(0)
        rad = np.median(np.linalg.norm((ring - c) - ((ring - c) @ up)[:, None] * up, axis=1))
        assert 0.04 < rad < 0.09  # a neck's radius (metres)
        o, d = origins[v].double().numpy()[m], dirs[v].double().numpy()[m]
        p = o + on.t[v].double().numpy()[m][:, None] * d

        def dist_axis(x):
            q = x - c
            return np.linalg.norm(q - (q @ up)[:, None] * up, axis=1)

        assert np.abs(dist_axis(p) - rad).max() < 1e-3  # on the cylinder
        assert (dist_axis(p - 0.002 * d) > rad).all()  # where the ray enters it, not where it leaves
        chin = vw[head.landmarks68[8]]
        assert ((p - chin) @ up < 0).all()  # only below the chin


def test_the_turned_views_neck_pixels_move_behind_the_jaw(case):
    """The defect it is for: a turned view's neck pixels took the jaw's distance, in front of the neck."""
    surface, cams, _ = case
    off = surface_ray_depth(surface, cams)
    on = surface_ray_depth(surface, cams, neck="off_head")
    moved = on.t[1] != off.t[1]
    assert float((on.t[1] - off.t[1])[moved].median()) > 0.0


def test_below_ring_also_moves_the_meshs_collar_and_keeps_the_head_above_it(case):
    surface, cams, h2w = case
    head = HeadModel.load()
    off = surface_ray_depth(surface, cams)
    ring = surface_ray_depth(surface, cams, neck="below_ring")
    moved = ring.t != off.t
    assert bool((moved & off.hit).any())  # the collar's own pixels move too
    origins, dirs = cams.flatten().pixel_rays()
    up = np.array([0.0, 1.0, 0.0]) if h2w is None else h2w[:3, 1]
    for v in range(3):
        vw = surface.vertices(v, head).astype(np.float64)
        low = float((vw[neck_ring_vertices(head)] @ up).min())
        m = (moved[v] & off.hit[v]).numpy()
        p = origins[v].double().numpy()[m] + off.t[v].double().numpy()[m][:, None] * dirs[v].double().numpy()[m]
        assert (p @ up < low + 1e-4).all()  # only hits below the neck ring
        chin = vw[head.landmarks68[8]]
        keep = off.hit[v].numpy() & ~m
        q = origins[v].double().numpy()[keep] + off.t[v].double().numpy()[keep][:, None] * dirs[v].double().numpy()[keep]
        assert (q @ up >= (chin @ up) - 0.2).any() and torch.equal(ring.t[v][torch.from_numpy(keep)], off.t[v][torch.from_numpy(keep)])


def test_neck_mode_is_checked(case):
    surface, cams, _ = case
    with pytest.raises(ValueError, match="neck must be"):
        surface_ray_depth(surface, cams, neck="yes")
