"""`fastgha reconstruct` says whether the avatar it wrote is view-blended per frame
(``model/viewblend.py``): a user cannot otherwise tell a tracked-head avatar (blended in the server
and `fastgha animate`) from a network-depth one (unweighted), nor why."""

from __future__ import annotations

from types import SimpleNamespace

import torch

from fastgha_core.config import GaussianHeadConfig
from fastgha_core.model.viewblend import ViewBlend


def _model(**gaussians):
    return SimpleNamespace(config=SimpleNamespace(gaussians=GaussianHeadConfig(**gaussians)))


def _avatar(views: int | None):
    if views is None:
        return SimpleNamespace(view_blend=None)
    n = 6
    dirs = torch.nn.functional.normalize(torch.randn(views, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    return SimpleNamespace(view_blend=ViewBlend(torch.zeros(n, dtype=torch.int8), torch.ones(n, dtype=torch.uint8), dirs))


def test_the_note_says_on_with_tau_and_views_or_why_it_is_off():
    from fastgha_core.commands.reconstruct import _blend_note

    on = _blend_note(_model(), _avatar(4), on_surface=True)
    assert "on (tau 20 deg)" in on and "4 input views" in on and "not the PLY" in on
    net = _blend_note(_model(), _avatar(None), on_surface=False)
    assert "off" in net and "network's depth" in net and "head.json" in net and "unweighted" in net
    assert "network's depth" not in _blend_note(_model(), _avatar(None), on_surface=True)  # e.g. more than 8 views
    zero = _blend_note(_model(view_blend_tau_deg=0.0), _avatar(3), on_surface=True)
    assert "view_blend_tau_deg is 0" in zero and "unweighted" in zero
    assert "nothing to weight" in _blend_note(_model(), _avatar(1), on_surface=True)  # one photo: every factor is 1


def test_animate_says_how_the_views_were_drawn():
    """An avatar file from before view blending (no ``view.*`` tensors) still animates, unweighted;
    the summary line says so and why, so a user knows to reconstruct again."""
    from fastgha_core.commands.animate import blend_summary

    assert "blended by angle (tau 20 deg)" in blend_summary(_model(), _avatar(4))
    old = blend_summary(_model(), _avatar(None))
    assert "unweighted" in old and "before view blending" in old
    assert "view_blend_tau_deg is 0" in blend_summary(_model(view_blend_tau_deg=0.0), _avatar(4))
    assert blend_summary(_model(), _avatar(1)) == "one input view"


def test_the_note_counts_photos_and_mirrored_views_apart():
    """With mirrored views (``model/mirror.py``) an avatar of 5 photos blends 7 views: the note must
    not call them "7 input views" (a user who gave 5 photos reads that as a bug), but say where the
    extra 2 come from; one turned photo gives 2 views, which blend."""
    from fastgha_core.commands.reconstruct import _blend_note

    five = _blend_note(_model(), _avatar(7), on_surface=True, photos=5)
    assert "the 7 views (5 photos + 2 mirrored views of turned photos) by" in five and "7 input views" not in five
    one = _blend_note(_model(), _avatar(2), on_surface=True, photos=1)
    assert "on (tau 20 deg)" in one and "1 photo + 1 mirrored view of a turned photo" in one
    assert "4 input views" in _blend_note(_model(), _avatar(4), on_surface=True, photos=4)  # no mirrored view: as before
