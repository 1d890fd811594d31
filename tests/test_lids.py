"""Closed-eyed input photos (fastgha_core/model/lids.py, issue 16)."""

import numpy as np
import pytest
import torch

from prior_frames import fast_and_plain

from fastgha_core.data.headmodel import HeadModel
from fastgha_core.model.prior import load_basis


@pytest.fixture(scope="module")
def basis():
    return load_basis("ict53")


def _one(names):
    return lambda **w: torch.tensor([w.get(n, 0.0) for n in names])  # noqa: E731


def test_closed_lid_views_marks_each_eye_closed_in_a_view_only_where_another_view_shows_it_open(basis):
    from fastgha_core.model.lids import closed_lid_views

    names = HeadModel.load().expression_names
    one = _one(names)
    k_l = int(np.flatnonzero(basis.gates[:, names.index("eyeBlink_L")])[0])
    k_r = int(np.flatnonzero(basis.gates[:, names.index("eyeBlink_R")])[0])
    assert {k_l, k_r} == {1, 2}
    ve = torch.stack([torch.zeros(53), one(eyeBlink_L=1.0), one(eyeBlink_L=0.3, eyeBlink_R=0.9), one(eyeBlink_R=0.6)])
    got = closed_lid_views(ve, basis)
    assert got.shape == (4, 2)
    assert got[:, k_l - 1].tolist() == [False, True, False, False]  # 0.3: the lid gate hardly moves
    assert got[:, k_r - 1].tolist() == [False, False, True, True]
    # an eye that no view shows open is left alone (the neutral avatar keeps an eye)
    both = torch.stack([one(eyeBlink_L=1.0, eyeBlink_R=1.0), one(eyeBlink_L=1.0)])
    got = closed_lid_views(both, basis)
    assert not got[:, k_l - 1].any() and got[:, k_r - 1].tolist() == [True, False]
    with pytest.raises(ValueError, match="view expressions"):
        closed_lid_views(torch.zeros(2, 7), basis)


def test_a_blinking_photos_closed_lids_are_hidden_at_neutral_and_appear_as_the_avatar_blinks(basis):
    """Two photos of the same eye region: view 0 with the eyes open, view 1 blinking (its Gaussians
    where the closed lid is). The closed-lid Gaussians of view 1 that undoing its blink leaves over
    the eye (bound to the eyeball, which a blink does not move) draw nothing at the neutral expression
    and fully at a blink, on the frame path and the plain path alike; view 0's Gaussians and view 1's
    away from the eyes are drawn as before."""
    from fastgha_core.config import get_preset
    from fastgha_core.gaussians import Gaussians
    from fastgha_core.model.avatar import CanonicalAvatar
    from fastgha_core.model.fastgha import FastGHA

    hm = HeadModel.load()
    names = hm.expression_names
    one = _one(names)
    torch.manual_seed(0)
    model = FastGHA(get_preset("tiny")).eval()
    v = torch.from_numpy(hm.neutral[:11248:2].copy())
    n = len(v)
    g1 = Gaussians(v, torch.tensor([1.0, 0, 0, 0]).expand(n, 4).clone(), torch.full((n, 3), 0.002), torch.full((n,), 0.9), torch.full((n, 3), 0.6), torch.randn(n, 32) * 0.1)
    blink = one(eyeBlink_L=1.0, eyeBlink_R=1.0)
    d = torch.from_numpy(np.tensordot(blink.numpy(), hm.expression_basis[:, :11248:2], axes=1).astype(np.float32))
    g = Gaussians.concat([g1, g1.replace(means=v + d)])  # view 1 as photographed: eyes closed
    vi = torch.arange(2).repeat_interleave(n)
    g2, binding, n_int = model.build_prior(g, vi, torch.stack([torch.zeros(53), blink]))
    # view 1's closed upper lid over the eye, left there by the undone blink (moved < 1 mm back)
    over = (np.linalg.norm(d.numpy(), axis=1) > 0.006) & (np.linalg.norm(g2.means[n : 2 * n].numpy() - (v + d).numpy(), axis=1) < 0.001)
    eyes = hm.neutral[hm.landmarks68[36:48]]
    far = np.linalg.norm(v.numpy()[:, None] - eyes[None], axis=-1).min(1) > 0.03
    grp = binding.groups()[: 2 * n]
    G = basis.gates.shape[0]
    # none of them fades out as the lid closes (the eyeball's groups G, G + 1: shown on the open eye)
    assert not (grp[n:][torch.from_numpy(over)] >= G).any()
    over &= np.isin(grp[n:].numpy(), [1, 2])  # those that appear with the lid (the rest: bound to the lids)
    assert over.sum() > 10 and far.sum() > 1000
    over, far = torch.from_numpy(over), torch.from_numpy(far)
    assert (grp[n:][far] < 0).all() and not ((grp[:n] == 1) | (grp[:n] == 2)).any()
    avatar = CanonicalAvatar(g2, "tiny", "ict53", binding, n_int)
    for z, shown in ((torch.zeros(53), 0.0), (one(jawOpen=1.0), 0.0), (blink, 1.0)):
        fast, plain = fast_and_plain(model, avatar, z)
        for out in (fast, plain):
            op = out.opacities[: 2 * n]
            assert torch.allclose(op[n:][over], torch.full((int(over.sum()),), 0.9 * shown))
            assert torch.allclose(op[n:][far], torch.full((int(far.sum()),), 0.9)) and torch.allclose(op[:n][far], torch.full((int(far.sum()),), 0.9))


def test_show_closed_lids_leaves_other_groups_and_checks_shapes(basis):
    from fastgha_core.model.lids import show_closed_lids
    from fastgha_core.model.prior import PriorBinding, bind, generic_fit, lip_hide_group

    hm = HeadModel.load()
    names = hm.expression_names
    one = _one(names)
    fit = generic_fit(basis)
    blink = one(eyeBlink_L=1.0, eyeBlink_R=1.0).numpy()
    lid = basis.interior_vertices[(basis.interior_group >= 1) & (basis.interior_group < basis.gates.shape[0]) & ~basis.lash]
    closed = fit.vertices[lid] + np.tensordot(blink, basis.expression_basis[:, lid], axes=1)  # [L, 3]: the closed lids
    pts = np.concatenate([closed, closed]).astype(np.float32)
    b = bind(pts, fit, basis)
    L = len(closed)
    vi = torch.cat([torch.zeros(L, dtype=torch.long), torch.ones(L, dtype=torch.long)])
    grp = b.groups().numpy().copy()
    grp[L : L + 5] = lip_hide_group(basis)  # another gate's Gaussians keep their group
    b = PriorBinding(b.vertex_ids, b.bary, b.weight, b.transform, b.identity, b.space, torch.from_numpy(grp))
    out = show_closed_lids(b, pts, vi, np.stack([np.zeros(53), blink]), fit, basis).groups().numpy()
    G = basis.gates.shape[0]
    eyeball = (np.arange(2 * L) >= L) & np.isin(grp, [G, G + 1])  # view 1's, bound to an eyeball
    assert eyeball.sum() > 10 and ((grp[L:] < 0).sum() > 10)
    want = grp.copy()
    want[eyeball] = grp[eyeball] - (G - 1)  # that eye's lid gate: 1, 2
    assert (out == want).all()  # view 0 (eyes open), the other gate's and the lid-bound ones unchanged
    # only the closed-eyed view draws that eye (a side view sees it, the open one does not): left as
    # it was, no hole in the neutral eye
    far_away = pts.copy()
    far_away[:L] += np.float32([0.0, 0.0, -0.08])  # view 0's Gaussians nowhere near the eyes
    alone = show_closed_lids(b, far_away, vi, np.stack([np.zeros(53), blink]), fit, basis).groups().numpy()
    assert (alone == grp).all()
    # no closed-eyed view: the same binding back
    assert show_closed_lids(b, pts, vi, np.zeros((2, 53)), fit, basis) is b
    with pytest.raises(ValueError, match="shapes"):
        show_closed_lids(b, pts[:-1], vi, np.stack([np.zeros(53), blink]), fit, basis)
