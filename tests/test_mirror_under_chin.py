"""The mirrored views' Gaussians below the tracked chin drawn under the others
(``GaussianHeadConfig.mirror_under_below_chin``, ``model/surface.py`` ``below_chin``;
docs/model-card-log.md "Skin and off-colour smears over the shoulders")."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastgha_core.data.headmodel import HeadModel
from fastgha_core.model.surface import HeadSurface, below_chin
import test_surface_hull

head_case = test_surface_hull.head_case  # the tracked head seen from 0 / +-60 degrees: the +-60 degree views get mirrored views


def _chin(surface: HeadSurface) -> np.ndarray:
    head = HeadModel.load()
    ident = np.zeros(head.num_identity, np.float32)
    ident[: len(surface.identity)] = surface.identity[: head.num_identity]
    return np.asarray(head.vertices(ident, None), dtype=np.float64)[head.landmarks68[8]]


def _rot_x(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def test_below_chin_splits_at_the_chin_along_the_heads_up_axis():
    rng = np.random.default_rng(0)
    ident = (rng.standard_normal(100) * 0.5).astype(np.float32)
    surface = HeadSurface(ident, np.zeros((1, 53), np.float32))
    chin = _chin(surface)
    # 1 cm above / below the chin, and well off to the side and in front (only the height counts)
    offs = np.array([[0, 0.01, 0], [0, -0.01, 0], [0.2, 0.01, 0.3], [-0.2, -0.01, -0.3], [0, -0.2, 0]])
    pts = torch.as_tensor(chin + offs, dtype=torch.float32)
    assert below_chin(pts, surface).tolist() == [False, True, False, True, True]
    # a margin moves the line: 2 cm below the chin only the lowest point counts, 2 cm above all but none
    assert below_chin(pts, surface, 0.02).tolist() == [False, False, False, False, True]
    assert below_chin(pts, surface, -0.02).tolist() == [True] * 5
    # a head pitched by 90 degrees in the world: "down" is the head's -y, moved with it (world -z)
    h = np.eye(4)
    h[:3, :3], h[:3, 3] = _rot_x(90.0), [0.1, 0.2, 0.3]
    turned = HeadSurface(ident, np.zeros((1, 53), np.float32), h)
    pw = torch.as_tensor((chin + offs) @ h[:3, :3].T + h[:3, 3], dtype=torch.float32)
    assert below_chin(pw, turned).tolist() == [False, True, False, True, True]
    # the same world points judged with the world's y as up would split differently: the axis is the head's
    assert below_chin(pw, surface).tolist() != [False, True, False, True, True]
    with pytest.raises(ValueError, match="N, 3"):
        below_chin(torch.zeros(4, 2), surface)


def test_reconstruct_draws_only_the_mirrored_gaussians_below_the_chin_under(head_case):
    from fastgha_core.model.fastgha import load_model

    surface, cams, sd, fg = head_case
    model = load_model("tiny")
    s = model.config.input_size
    gc = model.config.gaussians
    assert gc.mirror_views and gc.off_head_draw == "under"
    imgs = test_surface_hull.head_case_photos(fg, s)
    saved = gc.coverage_target, gc.prune_opacity, gc.hair_fit, gc.mirror_under_below_chin, gc.off_head_extrude_m
    gc.coverage_target, gc.prune_opacity, gc.hair_fit, gc.off_head_extrude_m = 0.0, 0.0, False, 0.0  # one Gaussian per pixel
    try:
        gc.mirror_under_below_chin = False
        off = model.reconstruct(imgs, cams, surface=surface)
        gc.mirror_under_below_chin = True
        on = model.reconstruct(imgs, cams, surface=surface)
    finally:
        gc.coverage_target, gc.prune_opacity, gc.hair_fit, gc.mirror_under_below_chin, gc.off_head_extrude_m = saved
    vb0, vb1 = off.view_blend, on.view_blend
    n = len(vb0)
    assert n == 5 * s * s  # 3 real views and the mirrors of the two turned ones
    assert torch.equal(on.gaussians.means, off.gaussians.means) and torch.equal(on.gaussians.opacities, off.gaussians.opacities)
    assert torch.equal(vb1.source_view, vb0.source_view) and torch.equal(vb1.mask, vb0.mask)
    mirrored = vb0.source_view.long() >= 3
    added = vb1.under & ~vb0.under
    assert bool(added.any()) and not bool((added & ~mirrored).any())  # only mirrored Gaussians are added
    assert torch.equal(vb1.under[~mirrored], vb0.under[~mirrored])  # the real views' flags as before
    # the avatar's means are those reconstruct judged up to the prior's neutralising shift (millimetres): 1 cm either side of the chin
    pts = on.gaussians.means[:n]
    assert bool(vb1.under[mirrored & below_chin(pts, surface, 0.01)].all())  # every mirrored Gaussian clearly below the chin is drawn under
    assert not bool(added[~below_chin(pts, surface, -0.01)].any())  # none clearly above it is added
    assert int(added.sum()) < int(mirrored.sum())  # the mirrored face and hair are left as they were
    # per frame the added Gaussians move away from the frame's camera; nothing else changes
    z = torch.zeros(model.config.expression_dim)
    cam = cams[0:1]
    g0, g1 = model.animate(off, z, camera=cam), model.animate(on, z, camera=cam)
    moved = (g1.means - g0.means).norm(dim=-1) > 1e-6
    assert torch.equal(moved[:n], added) and not bool(moved[n:].any())
    assert torch.equal(g1.opacities, g0.opacities)
