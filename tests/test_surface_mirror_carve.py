"""The hair layer and the back-of-head shell carved by the photos' outlines and their mirror images
(``model/surface.py`` ``midline_reflection``, ``hair_carve_fractions(mirror=True)``,
``carve_into_mattes(mirror=...)``; ``GaussianHeadConfig.hair_carve_mirror``; issue 17: with one side
photo left out, the shell and the hair stood 1-2 cm beyond the back of phone-5's head in that photo's
view, since only the other side photo's outline bounds the back of the head, on its own side)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastgha_core.data.headmodel import HeadModel
from fastgha_core.model.surface import HeadSurface, carve_into_mattes, hair_carve_fractions, hair_vertex_weight, midline_reflection
from test_mirror import _with  # the config-override context (one definition for the reconstruct tests)
from test_surface import _cameras  # head-centric cameras around the head (one definition for the surface tests)
from test_surface_coverage import _head_masks  # the fitted head's silhouette per view, as mattes


def test_midline_reflection_mirrors_the_head_frame_x():
    a, b = midline_reflection(None)
    p = np.array([[0.05, 0.02, -0.07], [0.0, 0.1, 0.03]])
    assert np.allclose(p @ a.T + b, p * [-1.0, 1.0, 1.0])
    h2w = np.eye(4)
    c, s = np.cos(0.7), np.sin(0.7)
    h2w[:3, :3] = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]) @ np.array([[1.0, 0.0, 0.0], [0.0, np.cos(0.3), -np.sin(0.3)], [0.0, np.sin(0.3), np.cos(0.3)]])
    h2w[:3, 3] = [0.04, -0.03, 0.5]
    a, b = midline_reflection(h2w)
    pw = p @ h2w[:3, :3].T + h2w[:3, 3]  # the head-frame points in that world
    mw = pw @ a.T + b
    back = (mw - h2w[:3, 3]) @ h2w[:3, :3]  # to the head frame
    assert np.allclose(back, p * [-1.0, 1.0, 1.0])
    assert np.allclose((mw @ a.T + b), pw)  # twice: where it was


def test_a_point_whose_mirror_image_leaves_the_matte_is_carved_in():
    cams = _cameras([0.0]).to(dtype=torch.float32)
    p = torch.tensor([[0.1, 0.0, 0.0]])
    uv_p, _ = cams[0].project(p)
    uv_q, _ = cams[0].project(-p)
    fg = torch.zeros(1, 128, 128)
    lo, hi = sorted([int(uv_p[0, 0]), int(uv_q[0, 0])])
    # foreground: a band around the head centre, reaching the point's side but not its mirror image's
    if uv_p[0, 0] > uv_q[0, 0]:
        fg[0, 40:90, lo + 8 : hi + 6] = 1.0
    else:
        fg[0, 40:90, lo - 5 : hi - 8] = 1.0
    assert torch.equal(carve_into_mattes(p, cams, fg), p)  # the view holds the point itself
    moved = carve_into_mattes(p, cams, fg, mirror=midline_reflection(None))
    assert 0.05 < float(moved.norm()) < 0.1 - 0.005  # pulled in along its radius ...
    for q in (moved, moved * torch.tensor([-1.0, 1.0, 1.0])):  # ... until it and its mirror image are inside
        uv, _ = cams[0].project(q)
        assert fg[0, int(uv[0, 1]), int(uv[0, 0])] > 0.5


def test_one_side_view_carves_the_back_of_the_other_side_through_the_mirror():
    """A single view from 80 degrees, its matte the bald head: without the mirror only the seen
    side's outline is carved; with it the unseen side's scalp (its mirror image on that outline)
    too, and no vertex keeps more hair than without."""
    bald = HeadSurface(np.zeros(100, np.float32), np.zeros((1, 53), np.float32))
    cams = _cameras([80.0]).to(dtype=torch.float32)
    fg = _head_masks(bald, cams, 0.0)
    plain = hair_carve_fractions(bald, cams, fg, 0.02)
    mirrored = hair_carve_fractions(bald, cams, fg, 0.02, mirror=True)
    assert np.all(mirrored <= plain)
    head = HeadModel.load()
    v = bald.vertices(0, head)
    centre = np.linalg.inv(cams.w2c[0].double().numpy())[:3, 3]  # the camera centre (world = head frame)
    hair = hair_vertex_weight(head) > 0.5
    far = hair & (v[:, 0] * centre[0] < -0.03)  # the scalp on the side the camera does not see
    near = hair & (v[:, 0] * centre[0] > 0.03)
    assert float((plain[near] < 1).mean()) > 0.2  # the seen side's outline is carved either way
    assert float((plain[far] < 1).mean()) < 0.1  # the unseen side projects inside the head's own silhouette
    assert float((mirrored[far] < 1).mean()) > float((plain[far] < 1).mean()) + 0.15


def test_reconstruct_carves_the_shell_by_the_mirror_images(tmp_path):
    """Views from one side only, mattes of a head narrower than the tracked one (the bald head's,
    eroded by 4 pixels): with ``hair_carve_mirror`` the shell on the unseen side moves in towards the
    head centre as the seen side's does; without it, it stays where it was laid."""
    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.model.prior import back_shell_vertices
    from test_surface_hair_shell import _inputs

    tiny = load_model("tiny")
    imgs, cams, surface, fg = _inputs(tiny, [60.0, 85.0], hair_m=0.0)
    narrow = -torch.nn.functional.max_pool2d(-fg[:, None], 9, 1, 4)[:, 0]
    bg = torch.tensor(BACKGROUND_RGB).view(1, 3, 1, 1)
    imgs = imgs * narrow[:, None] + bg * (1 - narrow[:, None])
    k = len(back_shell_vertices(tiny.head_basis()))
    shells = {}
    for on in (False, True):
        with _with(tiny, mirror_views=False, hair_carve_mirror=on):
            av = tiny.reconstruct(imgs, cams, surface=surface)
        shells[on] = av.gaussians.means[av.num_reconstructed : av.num_reconstructed + k]
    centre = np.linalg.inv(cams.w2c[0].double().numpy())[:3, 3]
    far = shells[False][:, 0] * float(centre[0]) < -0.03  # the side no view sees
    pulled = shells[False].norm(dim=-1) - shells[True].norm(dim=-1)
    assert int(far.sum()) > 50
    assert float((pulled[far] > 0.004).float().mean()) > 0.2  # a good part of the unseen side moves in
    assert float(pulled.min()) >= -1e-6  # nothing moves out
