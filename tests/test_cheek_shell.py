"""The cheek shell (``deform.cheek_shell``, ``model/prior.py`` ``cheek_shell``): an opaque skin under the
cheeks and around the mouth, so that a cheek the reconstruction left (or refinement made) see-through
shows skin from the side instead of the mouth interior behind it."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from face_avatars import SKIN, face_avatars
from prior_frames import fast_and_plain

from fastgha_core.data.headmodel import HeadModel
from fastgha_core.model.prior import CHEEK_SHELL_INNER, CHEEK_SHELL_LIP, back_shell_vertices, cheek_shell_vertices, chin_shell_vertices, face_shell_vertices, load_basis


@pytest.fixture(scope="module")
def basis():
    return load_basis("ict53")


def test_cheek_shell_vertices_lie_beside_the_mouth_apart_from_the_other_shells(basis):
    ids = cheek_shell_vertices(basis)
    assert 100 <= len(ids) <= 600
    assert not set(ids.tolist()) & (set(back_shell_vertices(basis).tolist()) | set(chin_shell_vertices(basis).tolist()))
    lm = basis.neutral[HeadModel.load().landmarks68]
    p = basis.neutral[ids]
    assert np.all(p[:, 2] >= lm[0, 2] - 0.02)  # in front of the back shell
    assert np.all(p[:, 1] <= lm[33, 1] + 0.01 + 1e-6)  # not above the nose's base (+1 cm)
    d_lip = np.linalg.norm(p[:, None] - lm[None, 48:68], axis=-1).min(1)
    assert float(d_lip.min()) > CHEEK_SHELL_LIP  # the lips, and so the mouth's opening, stay free
    # beside the mouth, not in front of the teeth (philtrum, chin)
    assert np.all(np.abs(p[:, 0]) >= np.abs(lm[[48, 54], 0]).min() - CHEEK_SHELL_INNER - 1e-6)
    # both cheeks beside the mouth corners are there
    for corner in (48, 54):
        side = np.sign(lm[corner, 0])
        beside = (np.sign(p[:, 0]) == side) & (np.abs(p[:, 0]) > abs(lm[corner, 0])) & (np.abs(p[:, 1] - lm[corner, 1]) < 0.015)
        assert int(beside.sum()) >= 5, (corner, int(beside.sum()))
    from scipy.spatial import cKDTree

    d, _ = cKDTree(p).query(p, k=2)
    assert float(d[:, 1].min()) >= 0.0065 - 1e-6


@pytest.fixture(scope="module")
def opaque():
    return face_avatars("cheek_shell", 0.95)


@pytest.fixture(scope="module")
def thin():
    return face_avatars("cheek_shell", 0.5)


def test_cheek_shell_off_is_the_avatar_without_it(opaque):
    """The flag off builds the old avatar; on, it inserts its run after the chin shell and before the
    mouth interior, ungated and bound with weight 1."""
    out, n, _ = opaque
    (m_on, a_on), (m_off, a_off) = out["on"], out["off"]
    basis = m_on.head_basis()
    k_back, k_chin, k_cheek = (len(f(basis)) for f in (back_shell_vertices, chin_shell_vertices, cheek_shell_vertices))
    assert len(a_on.gaussians) == len(a_off.gaussians) + k_cheek
    assert a_on.num_interior == a_off.num_interior + k_cheek
    k_face = len(face_shell_vertices(basis, m_on.config.deform.face_shell))  # the face shell follows the cheek shell (test_face_shell)
    assert m_on._shell_count() == k_back + k_chin + k_cheek + k_face and m_off._shell_count() == k_back + k_chin + k_face
    head = n + k_back + k_chin
    for f in ("means", "colors", "opacities", "scales"):
        a, b = getattr(a_on.gaussians, f), getattr(a_off.gaussians, f)
        torch.testing.assert_close(a[:head], b[:head])
        torch.testing.assert_close(a[head + k_cheek :], b[head:])
    run = slice(head, head + k_cheek)
    assert torch.all(a_on.prior.groups()[run] == -1) and torch.all(a_on.prior.weight[run] == 1)
    assert torch.equal(a_on.prior.vertex_ids[run, 0], torch.from_numpy(cheek_shell_vertices(basis)))
    # the shell's colour is the avatar's skin nearby
    torch.testing.assert_close(a_on.gaussians.colors[run], torch.from_numpy(SKIN).expand(k_cheek, 3), atol=1e-4, rtol=0)


def _views(lm):
    from fastgha_core.cameras import Cameras

    mouth = torch.from_numpy(lm[62].copy())  # the upper inner lip's middle
    turned = Cameras.look_at((mouth + 0.6 * torch.tensor([np.sin(np.radians(55)), 0.0, np.cos(np.radians(55))]))[None], mouth[None], fov_deg=20.0, width=96, height=96)
    front = Cameras.look_at((mouth + torch.tensor([0.0, 0.0, 0.6]))[None], mouth[None], fov_deg=20.0, width=96, height=96)
    return turned, front


def _cheek_pixels(cam, lm) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel rows and columns of the near cheek (+x) beside the mouth corner and up to the nose, in ``cam``."""
    c = lm[54] if lm[54, 0] > 0 else lm[48]
    pts = torch.tensor([[c[0] + dx, c[1] + dy, c[2] - 0.25 * dx] for dx in (0.008, 0.016) for dy in (0.0, 0.01, 0.02)], dtype=torch.float32)
    w2c, K = cam.w2c[0].float(), cam.K[0].float()
    x = (w2c[:3, :3] @ pts.T + w2c[:3, 3:]).T
    uv = (K @ x.T).T
    return (uv[:, 1] / uv[:, 2]).long(), (uv[:, 0] / uv[:, 2]).long()


def test_a_see_through_cheek_shows_skin_from_the_side_and_the_mouth_stays_open(thin, opaque):
    """Half-transparent face, mouth open (jawOpen 1: the interior is drawn), seen from 55 degrees: without
    the shell the near cheek beside the mouth is a mix of skin and what lies behind it (the mouth
    interior, the far side); with it the cheek is skin. From the front, the mouth's opening shows the
    interior as before, and nowhere does the shell draw further from skin than the face without it."""
    from fastgha_core.expressions import ICT53_NAMES
    from fastgha_core.render import render

    out, _, lm = thin
    turned, front = _views(lm)
    z = torch.zeros(53)
    z[ICT53_NAMES.index("jawOpen")] = 1.0
    skin = torch.from_numpy(SKIN)
    rows, cols = _cheek_pixels(turned, lm)
    err = {}
    for name, (m, av) in out.items():
        rgb = render(m.animate(av, z), turned, background=(1.0, 1.0, 1.0)).rgb[0]
        err[name] = float((rgb[:, rows, cols] - skin[:, None]).abs().amax(0).mean())
    assert err["off"] > 0.08 and err["on"] < 0.5 * err["off"], err
    # the opening: the interior shows between the lips from the front, with the shell as without it
    r = {name: render(m.animate(av, z), front, background=(1.0, 1.0, 1.0)).rgb[0] for name, (m, av) in opaque[0].items()}
    mid = (slice(50, 56), slice(46, 52))
    assert float((r["on"][:, mid[0], mid[1]] - skin[:, None, None]).abs().amax(0).mean()) > 0.3  # not skin: the interior
    torch.testing.assert_close(r["on"][:, mid[0], mid[1]], r["off"][:, mid[0], mid[1]], atol=0.02, rtol=0)
    # and beside the opening the shell only takes away what showed through the face: nearer skin, never further
    dev = {k: (v - skin[:, None, None]).abs().amax(0) for k, v in r.items()}
    assert float((dev["on"] - dev["off"]).max()) < 0.02
    # the CPU frame path draws the shell as the plain torch path does, and the shell follows the cheeks
    m, av = opaque[0]["on"]
    n, basis = opaque[1], m.head_basis()
    k0 = len(back_shell_vertices(basis)) + len(chin_shell_vertices(basis))
    run = slice(n + k0, n + k0 + len(cheek_shell_vertices(basis)))
    fast, plain = fast_and_plain(m, av, z)
    torch.testing.assert_close(fast.means[run], plain.means[: len(fast)][run], atol=1e-5, rtol=0)
    smile = torch.zeros(53)
    smile[ICT53_NAMES.index("mouthSmile_L")] = smile[ICT53_NAMES.index("mouthSmile_R")] = 1.0
    moved = (m.animate(av, smile).means[run] - m.animate(av, torch.zeros(53)).means[run]).norm(dim=-1)
    assert float(moved.max()) > 0.004, float(moved.max())
