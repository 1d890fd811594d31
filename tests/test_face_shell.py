"""The face shell (``deform.face_shell``, ``model/prior.py`` ``face_shell``): an opaque skin under the
forehead (``"forehead"``, the default) or the whole upper face (``"upper"``: nose, cheekbones, brows
and forehead), so that gaps between the reconstructed Gaussians seen from in front show skin instead
of the back-of-head shell behind them."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from face_avatars import SKIN, face_avatars
from prior_frames import fast_and_plain

from fastgha_core.data.headmodel import HeadModel
from fastgha_core.model.prior import (CHEEK_SHELL_TOP, FACE_SHELL_BROW, FACE_SHELL_EYE, FACE_SHELL_TOP, back_shell_vertices, cheek_shell_vertices,
                                      chin_shell_vertices, face_shell_vertices, load_basis)


HAIR = (0.12, 0.08, 0.06)  # the back of the head's colour in the see-through test: the back shell takes it


@pytest.fixture(scope="module")
def basis():
    return load_basis("ict53")


def test_face_shell_vertices_lie_under_the_face_apart_from_the_other_shells(basis):
    upper, forehead = face_shell_vertices(basis, "upper"), face_shell_vertices(basis, "forehead")
    assert 200 <= len(upper) <= 800 and 60 <= len(forehead) < len(upper)
    assert len(face_shell_vertices(basis, "off")) == 0
    with pytest.raises(ValueError, match="off, forehead or upper"):
        face_shell_vertices(basis, "nose")
    others = set(back_shell_vertices(basis).tolist()) | set(chin_shell_vertices(basis).tolist()) | set(cheek_shell_vertices(basis).tolist())
    lm = basis.neutral[HeadModel.load().landmarks68]
    brow = lm[17:27, 1].max()
    from scipy.spatial import cKDTree

    for ids, low in ((upper, lm[33, 1] + CHEEK_SHELL_TOP), (forehead, brow + FACE_SHELL_BROW)):
        assert not set(ids.tolist()) & others
        p = basis.neutral[ids]
        assert np.all(p[:, 2] >= lm[0, 2] - 0.02)  # in front of the back shell
        assert np.all(p[:, 1] > low) and np.all(p[:, 1] <= brow + FACE_SHELL_TOP + 1e-6)
        assert float(np.linalg.norm(p[:, None] - lm[None, 36:48], axis=-1).min()) > FACE_SHELL_EYE  # the eyes stay free
        assert int(((np.abs(p[:, 0]) < 0.02) & (p[:, 1] > brow + 0.02)).sum()) >= 3  # the forehead's middle
        d, _ = cKDTree(p).query(p, k=2)
        assert float(d[:, 1].min()) >= 0.0065 - 1e-6
    # "upper" also lies under the nose's ridge and both brows
    p = basis.neutral[upper]
    for point in (27, 29, 19, 24):
        assert int((np.linalg.norm(p - lm[point], axis=1) < 0.015).sum()) >= 2, point


@pytest.fixture(scope="module")
def opaque():
    return face_avatars("face_shell", 0.95, on="upper", off="off")


@pytest.fixture(scope="module")
def thin():
    return {region: face_avatars("face_shell", 0.4, back_color=HAIR, on=region, off="off") for region in ("upper", "forehead")}  # solid enough (> 0.3) to colour the shells


def test_face_shell_off_is_the_avatar_without_it(opaque):
    """Off builds the old avatar; on, it inserts its run after the other shells and before the mouth
    interior, ungated, bound with weight 1 and coloured like the skin around it."""
    out, n, _ = opaque
    (m_on, a_on), (m_off, a_off) = out["on"], out["off"]
    basis = m_on.head_basis()
    k_face = len(face_shell_vertices(basis, "upper"))
    k_before = m_off._shell_count()
    assert len(a_on.gaussians) == len(a_off.gaussians) + k_face
    assert a_on.num_interior == a_off.num_interior + k_face
    assert m_on._shell_count() == k_before + k_face
    head = n + k_before
    for f in ("means", "colors", "opacities", "scales"):
        a, b = getattr(a_on.gaussians, f), getattr(a_off.gaussians, f)
        torch.testing.assert_close(a[:head], b[:head])
        torch.testing.assert_close(a[head + k_face :], b[head:])
    run = slice(head, head + k_face)
    assert torch.all(a_on.prior.groups()[run] == -1) and torch.all(a_on.prior.weight[run] == 1)
    assert torch.equal(a_on.prior.vertex_ids[run, 0], torch.from_numpy(face_shell_vertices(basis, "upper")))
    torch.testing.assert_close(a_on.gaussians.colors[run], torch.from_numpy(SKIN).expand(k_face, 3), atol=1e-4, rtol=0)


def _front(lm):
    from fastgha_core.cameras import Cameras

    target = torch.from_numpy(lm[27].copy())  # the bridge of the nose
    return Cameras.look_at((target + torch.tensor([0.0, 0.0, 0.6]))[None], target[None], fov_deg=20.0, width=96, height=96)


def _pixels(cam, pts: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    w2c, K = cam.w2c[0].float(), cam.K[0].float()
    x = (w2c[:3, :3] @ torch.from_numpy(pts).float().T + w2c[:3, 3:]).T
    uv = (K @ x.T).T
    return (uv[:, 1] / uv[:, 2]).long(), (uv[:, 0] / uv[:, 2]).long()


def test_a_see_through_face_shows_skin_from_the_front_where_its_shell_lies(thin, opaque):
    """A face at opacity 0.4 before dark hair seen from the front: without the shell, the forehead (and
    nose and brows) are a mix of skin and the dark back of the head behind them; with the shell they
    are skin where it lies ("upper": all of them; "forehead": the forehead, the nose as without it).
    The opaque face's front view does not change."""
    from fastgha_core.expressions import ICT53_NAMES
    from fastgha_core.render import render

    skin = torch.from_numpy(SKIN)
    z = torch.zeros(53)
    for region, (out, n, lm) in thin.items():
        cam = _front(lm)
        points = [(lm[19] + lm[24]) / 2 + [0, 0.025, 0], lm[19] + [0, 0.025, 0], lm[24] + [0, 0.025, 0]]  # the forehead
        if region == "upper":
            points += [lm[27], lm[29], lm[19] + [0, 0.012, 0], lm[24] + [0, 0.012, 0]]  # the nose's ridge, above the brows
        rows, cols = _pixels(cam, np.stack(points))
        r = {name: render(m.animate(av, z), cam, background=(1.0, 1.0, 1.0)) for name, (m, av) in out.items()}
        err = {k: float((v.rgb[0][:, rows, cols] - skin[:, None]).abs().amax(0).mean()) for k, v in r.items()}
        assert err["off"] > 0.08 and err["on"] < 0.5 * err["off"], (region, err)
        assert float(r["on"].alpha[0, 0, rows, cols].min()) > 0.95
        if region == "forehead":  # the nose keeps what showed through it: the forehead shell is not there
            nr, nc = _pixels(cam, np.stack([lm[29]]))
            torch.testing.assert_close(r["on"].rgb[0][:, nr, nc], r["off"].rgb[0][:, nr, nc], atol=0.02, rtol=0)
    lm = opaque[2]
    cam = _front(lm)
    # the opaque face from the front: where it covers, the shell changes nothing visible
    ro = {name: render(m.animate(av, z), cam, background=(1.0, 1.0, 1.0)) for name, (m, av) in opaque[0].items()}
    seen = ro["off"].alpha[0, 0] > 0.99
    assert float((ro["on"].rgb[0] - ro["off"].rgb[0]).abs()[:, seen].mean()) < 5e-3
    # it follows the brows (bound with weight 1), and the CPU frame path draws it as the plain torch path
    m, av = opaque[0]["on"]
    basis = m.head_basis()
    k0 = m._shell_count() - len(face_shell_vertices(basis, "upper"))
    run = slice(opaque[1] + k0, opaque[1] + m._shell_count())
    up = torch.zeros(53)
    up[ICT53_NAMES.index("browInnerUp_L")] = up[ICT53_NAMES.index("browInnerUp_R")] = 1.0
    moved = (m.animate(av, up).means[run] - m.animate(av, z).means[run]).norm(dim=-1)
    assert float(moved.max()) > 0.003, float(moved.max())
    fast, plain = fast_and_plain(m, av, up)
    torch.testing.assert_close(fast.means[run], plain.means[: len(fast)][run], atol=1e-5, rtol=0)
