"""The chin shell (``deform.chin_shell``, ``model/prior.py`` ``chin_shell``): an opaque skin under the
jaw and on the front of the neck, for the pitched-up views that see what no input does."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from face_avatars import SKIN, face_avatars
from prior_frames import fast_and_plain

from fastgha_core.data.headmodel import HeadModel, vertex_normals
from fastgha_core.model.prior import CHIN_SHELL_DOWN, back_shell_vertices, chin_shell_vertices, load_basis


@pytest.fixture(scope="module")
def basis():
    return load_basis("ict53")


def test_chin_shell_vertices_lie_under_the_jaw_apart_from_the_back_shell(basis):
    ids = chin_shell_vertices(basis)
    assert 200 <= len(ids) <= 800
    assert not set(ids.tolist()) & set(back_shell_vertices(basis).tolist())
    hm = HeadModel.load()
    v = basis.neutral
    lm = v[hm.landmarks68]
    p = v[ids]
    assert np.all(p[:, 1] < lm[57, 1])  # below the lower lip
    assert np.all(p[:, 2] >= lm[0, 2] - 0.02)  # in front of the back shell
    ny = vertex_normals(v, basis.bind_faces)[ids, 1]
    under = ny < CHIN_SHELL_DOWN
    assert np.all(under | (p[:, 1] < lm[8, 1]))
    # the jaw's underside is there: downward-facing points between the chin and the jaw's corners
    assert int((under & (p[:, 1] > lm[8, 1] - 0.03) & (np.abs(p[:, 0]) < 0.05)).sum()) >= 20
    # no two closer than the back shell's spacing
    from scipy.spatial import cKDTree

    d, _ = cKDTree(p).query(p, k=2)
    assert float(d[:, 1].min()) >= 0.0065 - 1e-6


@pytest.fixture(scope="module")
def avatars():
    out, n, lm = face_avatars("chin_shell")
    return out, n, lm, SKIN


def test_chin_shell_off_is_the_avatar_without_it(avatars):
    """The flag off builds the old avatar; on, it inserts its run after the back shell and before the
    mouth interior, ungated and bound with weight 1 (it follows the expression prior)."""
    out, n, _, _ = avatars
    (m_on, a_on), (m_off, a_off) = out["on"], out["off"]
    basis = m_on.head_basis()
    k_back, k_chin = len(back_shell_vertices(basis)), len(chin_shell_vertices(basis))
    assert len(a_on.gaussians) == len(a_off.gaussians) + k_chin
    assert a_on.num_interior == a_off.num_interior + k_chin
    k_cheek = m_on._shell_count() - k_back - k_chin  # the cheek shell follows the chin shell (test_cheek_shell)
    assert k_cheek >= 0 and m_off._shell_count() == k_back + k_cheek
    head = n + k_back
    for f in ("means", "colors", "opacities", "scales"):
        a, b = getattr(a_on.gaussians, f), getattr(a_off.gaussians, f)
        torch.testing.assert_close(a[:head], b[:head])
        torch.testing.assert_close(a[head + k_chin :], b[head:])
    run = slice(head, head + k_chin)
    assert torch.all(a_on.prior.groups()[run] == -1)
    assert torch.all(a_on.prior.weight[run] == 1) and torch.all(a_on.prior.weight[n:head] == 0)
    assert torch.equal(a_on.prior.vertex_ids[run, 0], torch.from_numpy(chin_shell_vertices(basis)))


def test_chin_shell_closes_the_jaw_underside_and_follows_jaw_open(avatars):
    """Seen from below, the face-only avatar is open under the jaw (the background, or the back shell
    far behind); the chin shell draws skin-coloured and near there, stays hidden from the front, and
    drops with the jaw (jawOpen) while the back shell stays."""
    from fastgha_core.cameras import Cameras
    from fastgha_core.expressions import ICT53_NAMES
    from fastgha_core.render import render

    out, n, lm, skin = avatars
    chin = torch.from_numpy(lm[8].copy())
    target = chin + torch.tensor([0.0, 0.0, -0.04])  # the jaw's underside
    below = Cameras.look_at((target + torch.tensor([0.0, -0.35, 0.2]))[None], target[None], fov_deg=20.0, width=96, height=96)
    front = Cameras.look_at(torch.tensor([[0.0, 0.0, 0.65]]), torch.zeros(1, 3), fov_deg=28.0, width=96, height=96)
    z = torch.zeros(53)
    r = {(name, cam): render(m.animate(av, z), c, background=(1.0, 1.0, 1.0)) for name, (m, av) in out.items() for cam, c in (("below", below), ("front", front))}
    mid = (slice(40, 56), slice(40, 56))  # the jaw's underside, in the middle of the view from below
    a_on, a_off = r["on", "below"].alpha[0, 0][mid], r["off", "below"].alpha[0, 0][mid]
    d_on, d_off = r["on", "below"].depth[0, 0][mid], r["off", "below"].depth[0, 0][mid]
    dist = float(torch.linalg.norm(torch.tensor([0.0, -0.35, 0.2])))
    assert float(a_on.min()) > 0.95
    assert float(d_on.median()) < dist + 0.02, float(d_on.median())
    assert float(a_off.mean()) < 0.9 or float(d_off.median()) > dist + 0.04, (float(a_off.mean()), float(d_off.median()))
    rgb = r["on", "below"].rgb[0][:, mid[0], mid[1]].reshape(3, -1)
    assert float((rgb - torch.from_numpy(skin)[:, None]).abs().max()) < 0.1
    seen = r["off", "front"].alpha[0, 0] > 0.9
    diff = (r["on", "front"].rgb[0] - r["off", "front"].rgb[0]).abs()[:, seen]
    assert float(diff.mean()) < 5e-3, float(diff.mean())
    # jawOpen: the chin shell moves down with the jaw, the back shell does not move
    m, av = out["on"]
    basis = m.head_basis()
    k_back, k_chin = len(back_shell_vertices(basis)), len(chin_shell_vertices(basis))
    zo = z.clone()
    zo[ICT53_NAMES.index("jawOpen")] = 1.0
    g0, g1 = m.animate(av, z), m.animate(av, zo)
    dy_chin = (g1.means[n + k_back : n + k_back + k_chin, 1] - g0.means[n + k_back : n + k_back + k_chin, 1])
    dy_back = (g1.means[n : n + k_back] - g0.means[n : n + k_back]).abs().max()
    near_chin = torch.from_numpy(basis.neutral[chin_shell_vertices(basis), 1] > lm[8, 1] - 0.02)
    # (about -10 mm median, -25 mm under the chin's point; a rigid binding would give 0)
    assert float(dy_chin[near_chin].median()) < -0.005 and float(dy_chin.min()) < -0.02, (float(dy_chin[near_chin].median()), float(dy_chin.min()))
    assert float(dy_back) < 1e-6
    # the CPU frame path (one numba pass) draws the chin shell as the plain torch path does
    fast, plain = fast_and_plain(m, av, zo)
    run = slice(n + k_back, n + k_back + k_chin)
    torch.testing.assert_close(fast.means[run], plain.means[:len(fast)][run], atol=1e-5, rtol=0)
    torch.testing.assert_close(fast.colors[run], plain.colors[:len(fast)][run], atol=1e-5, rtol=0)
