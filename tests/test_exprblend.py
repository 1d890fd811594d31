"""Expression-aware view blending (``model/viewblend.py`` ``ExpressionPenalty``, ``expression_factors``;
``GaussianHeadConfig.view_blend_expr_mm``): each input view also penalised by how far its expression
puts a Gaussian's bound surface point from where the frame's expression puts it."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import torch
from PIL import Image

from fastgha_core.cameras import Cameras
from fastgha_core.expressions import ICT53_NAMES
from fastgha_core.model.viewblend import ExpressionPenalty, ViewBlend, angles_deg, expression_factors
import test_surface_hull

head_case = test_surface_hull.head_case  # the tracked head seen from 0 / +-60 degrees

SIGMA = 2.0


def _expr(**codes) -> torch.Tensor:
    z = torch.zeros(len(ICT53_NAMES))
    for k, w in codes.items():
        z[ICT53_NAMES.index(k)] = w
    return z


@pytest.fixture(scope="module")
def recon(head_case):
    """The tiny model's avatar of the tracked head's three views: view 0 (frontal) neutral, view 1
    (+60) with the jaw open, view 2 (-60) smiling."""
    from fastgha_core.model.fastgha import load_model

    surface, cams, sd, fg = head_case
    model = load_model("tiny")
    s = model.config.input_size
    gc = model.config.gaussians
    imgs = test_surface_hull.head_case_photos(fg, s)
    expr = torch.stack([_expr(), _expr(jawOpen=0.8), _expr(mouthSmile_L=0.9, mouthSmile_R=0.9)])
    saved = gc.mirror_views
    gc.mirror_views = False
    try:
        av = model.reconstruct(imgs, cams, expressions=expr, surface=surface)
    finally:
        gc.mirror_views = saved
    model.animate(av, torch.zeros(len(ICT53_NAMES)))  # builds the avatar's prior runtime
    return model, av, cams, expr


def _reference(av, model, camera, tau, z, sigma, idx):
    """Plain per-Gaussian loop: each Gaussian's displacement basis D_g from its binding and the head
    model's blendshapes, the per-view penalties and the factor (module doc of model/viewblend.py)."""
    vb, b = av.view_blend, av.prior
    eb = model.head_basis().expression_basis.astype(np.float64)  # [E, Nv, 3]
    m = b.transform[:3, :3].double().numpy()
    ang = angles_deg(vb.directions, camera, vb.offsets).double().numpy()
    ve = vb.expressions.double().numpy()
    out = []
    for i in idx.tolist():
        d = np.zeros((eb.shape[0], 3))
        for c in range(3):
            d += float(b.bary[i, c]) * float(b.weight[i]) * eb[:, int(b.vertex_ids[i, c])] @ m.T
        s = int(vb.source_view[i])
        covers = [v for v in range(len(ang)) if (int(vb.mask[i]) >> v) & 1]
        df = z.double().numpy() @ d
        p = {v: np.linalg.norm(df - ve[v] @ d) * 1000.0 / sigma for v in covers}
        if vb.sharp is not None and bool(vb.sharp[i]):
            out.append(math.exp(-ang[s] / (tau * vb.sharp_scale)) * math.exp(-(p[s] - min(p.values()))))
        else:
            cc = {v: ang[v] / tau + p[v] for v in covers}
            out.append(math.exp(-(cc[s] - min(cc.values()))))
    return torch.tensor(out, dtype=torch.float64)


def test_factors_match_a_plain_per_gaussian_loop(recon):
    model, av, cams, _ = recon
    vb, rt = av.view_blend, av.prior_runtime
    n = len(vb)
    cam = Cameras.look_at(torch.tensor([[0.35, 0.05, 0.6]]), fov_deg=20.0, width=cams.width, height=cams.height)
    z = _expr(jawOpen=0.4, mouthSmile_L=0.3, eyeBlink_R=0.5)
    tau = 20.0
    g = torch.Generator().manual_seed(1)
    pen = ExpressionPenalty.build(vb, rt, spread_min_m=-1.0)  # every Gaussian with a source view: exact
    assert len(pen) == int((vb.source_view >= 0).sum())
    pick = torch.randperm(len(pen), generator=g)[:300]
    ang = angles_deg(vb.directions, cam, vb.offsets)
    got = pen.factors(ang, z, tau, SIGMA, vb.sharp_scale)[pick]
    ref = _reference(av, model, cam, tau, z, SIGMA, pen.idx[pick])
    assert torch.allclose(got.double(), ref, rtol=1e-4, atol=1e-5)
    # the default path (only the Gaussians whose views disagree) is within the documented bound of it
    full = vb.factors(cam, tau, z, SIGMA, rt)
    assert full.shape == (n,)
    ref_all = torch.ones(n, dtype=torch.float64)
    ref_all[pen.idx] = pen.factors(ang, z, tau, SIGMA, vb.sharp_scale).double()
    from fastgha_core.model.viewblend import EXPR_SPREAD_FRAC

    bound = 1 - math.exp(-EXPR_SPREAD_FRAC)
    assert vb.__dict__["_expr"].spread_min_m == pytest.approx(EXPR_SPREAD_FRAC * SIGMA * 1e-3) and len(vb.__dict__["_expr"]) < len(pen)
    own = vb.source_view >= 0
    assert float(((full.double() - ref_all).abs() - bound * ref_all)[own].max()) <= 1e-5
    # every Gaussian keeps 0 < f <= 1 and the angle factor alone is unchanged without an expression
    assert float(full.min()) > 0 and float(full.max()) <= 1 + 1e-6
    assert torch.equal(vb.factors(cam, tau), vb.factors(cam, tau, None, SIGMA, rt))


def test_expression_factors_keep_the_best_covering_view_and_reduce_to_the_angle():
    ang = torch.tensor([10.0, 30.0])
    p = torch.tensor([[0.0, 10.0]] * 2)  # a neutral frame: view 1's expression moved the point 10 mm
    cover = torch.ones(2, 2, dtype=torch.bool)
    src = torch.tensor([0, 1])
    f0 = expression_factors(ang, p, src, cover, 20.0, SIGMA)
    assert f0[0] == 1.0 and abs(float(f0[1]) - math.exp(-(20.0 / 20.0 + 10.0 / SIGMA))) < 1e-6
    f1 = expression_factors(ang, p.flip(1), src, cover, 20.0, SIGMA)  # the frame has view 1's expression
    assert f1[1] == 1.0 and abs(float(f1[0]) - math.exp(-(10.0 / SIGMA - 1.0))) < 1e-6
    # equal penalties: the angle factor; a view that does not cover the point does not count
    same = expression_factors(ang, torch.full((2, 2), 3.0), src, cover, 20.0, SIGMA)
    assert torch.allclose(same, torch.tensor([1.0, math.exp(-1.0)]))
    only1 = expression_factors(ang, p, src, torch.tensor([[True, False], [False, True]]), 20.0, SIGMA)
    assert torch.equal(only1, torch.ones(2))
    # a view its gate hides does not count as the best one (its own Gaussians keep their factor)
    hid = expression_factors(ang, p.flip(1), src, cover, 20.0, SIGMA, hidden=torch.tensor([[0.0, 50.0]] * 2))
    assert hid[0] == 1.0 and hid[1] == 1.0
    with pytest.raises(ValueError):
        expression_factors(ang, p, src, cover, 20.0, 0.0)


def _mouth_pairs(av, z, views):
    """Reconstructed Gaussians whose point the expression ``z`` moves more than 4 mm (the jaw, the
    smile), covered by both ``views``."""
    vb = av.view_blend
    d = av.prior_runtime.displacement(z)[: len(vb)].norm(dim=-1)  # [N]
    both = ((vb.mask.long() >> views[0]) & 1).bool() & ((vb.mask.long() >> views[1]) & 1).bool()
    return (d > 0.004) & both


@pytest.mark.parametrize("view,kind", [(1, "jaw"), (2, "smile")])
def test_the_expressive_view_is_chosen_for_its_expression_and_not_for_the_neutral_frame(recon, view, kind):
    model, av, cams, expr = recon
    vb, rt = av.view_blend, av.prior_runtime
    sel = _mouth_pairs(av, expr[view], (0, view))
    assert int(sel.sum()) > 20
    sv = vb.source_view.long()
    # the render camera half-way between the frontal view and the expressive one: equal angles
    mid = torch.nn.functional.normalize(vb.directions[0] + vb.directions[view], dim=0)
    cam = Cameras.look_at((0.7 * mid)[None], fov_deg=20.0, width=cams.width, height=cams.height)
    ang = angles_deg(vb.directions, cam)
    assert abs(float(ang[0] - ang[view])) < 0.1
    tau = 20.0

    def mean_f(z, sigma):
        f = vb.factors(cam, tau, z, sigma, rt)
        return float(f[sel & (sv == 0)].mean()), float(f[sel & (sv == view)].mean())

    neutral, expressive = _expr(), expr[view]
    n0, n1 = mean_f(neutral, SIGMA)
    e0, e1 = mean_f(expressive, SIGMA)
    assert n0 > 0.9 and n1 < 0.3  # a neutral frame: the neutral photo's mouth
    assert e1 > 0.9 and e0 < 0.3  # the expressive frame: the expressive photo's mouth
    a0, a1 = mean_f(expressive, 0.0)  # off: angles alone, about equal here
    assert abs(a0 - a1) < 0.25 and min(a0, a1) > 0.6


def test_blend_views_applies_it_per_frame_and_old_files_draw_as_before(recon, tmp_path):
    from fastgha_core.model.avatar import CanonicalAvatar

    model, av, cams, expr = recon
    gc = model.config.gaussians
    cam = cams[1:2]
    z = expr[1]
    saved = gc.view_blend_expr_mm
    try:
        gc.view_blend_expr_mm = 0.0
        off = model.animate(av, z, camera=cam)
        gc.view_blend_expr_mm = SIGMA
        on = model.animate(av, z, camera=cam)
        # saved and loaded with the avatar: the same frame
        path = tmp_path / "a.fgha"
        av.save(path)
        back = CanonicalAvatar.load(path)
        assert torch.equal(back.view_blend.expressions, av.view_blend.expressions)
        on2 = model.animate(back, z, camera=cam)
        assert torch.allclose(on2.opacities, on.opacities, atol=1e-6)
        # a file without view.expr (written before this change) draws as with the penalty off
        t = av.view_blend.tensors()
        t.pop("view.expr")
        old = CanonicalAvatar(av.gaussians, av.model_name, av.expression_space, av.prior, av.num_interior, ViewBlend.from_tensors(t, len(av.view_blend)))
        assert old.view_blend.expressions is None
        assert torch.equal(model.animate(old, z, camera=cam).opacities, off.opacities)
    finally:
        gc.view_blend_expr_mm = saved
    n = av.num_reconstructed
    assert torch.equal(on.means, off.means) and torch.equal(on.opacities[n:], off.opacities[n:])
    changed = (on.opacities[:n] - off.opacities[:n]).abs() > 1e-6
    assert int(changed.sum()) > 0
    # what changed is where the views' expressions disagree: the mouth, not the forehead or the hair
    d = av.prior_runtime.displacement(expr)[:, :n]
    spread = (d - d[:1]).norm(dim=-1).amax(0)
    assert float(spread[changed].min()) > 1e-5
    assert not bool(changed[spread <= 1e-6].any())


def test_an_open_mouth_frame_keeps_the_lips_of_the_views_the_mouth_gate_does_not_hide(recon):
    """The open-mouthed view's lips fade as the mouth opens (``prior.hide_open_lips``): for a frame
    with its expression they must not count as the best view, or the other views' lips fade too and
    the mouth shows a hole (the synthetic check in docs/model-card-log.md before this was handled)."""
    from fastgha_core.model.prior import LIP_RADIUS

    model, av, cams, expr = recon
    vb, rt = av.view_blend, av.prior_runtime
    n = len(vb)
    means = av.gaussians.means[:n]
    b = av.prior
    lips = torch.from_numpy(b.fitted_vertices(model.head_basis())[model.head_basis().lip_landmarks])
    near = torch.cdist(means.float(), lips).amin(dim=1) < LIP_RADIUS * float(b.transform[:3, :3].det().abs() ** (1 / 3))
    sel = near & (vb.source_view.long() == 0) & ((vb.mask.long() >> 1) & 1).bool() & (b.weight[:n] > 0)
    assert int(sel.sum()) > 10
    cam = cams[0:1]
    z = expr[1]  # view 1's open jaw
    with_hide = vb.factors(cam, 20.0, z, SIGMA, rt, means)
    pen = vb.__dict__["_expr"]
    assert pen.hide is not None and bool(pen.hide[:, 1].any()) and not bool(pen.hide[:, 0].any())  # view 1 is open, view 0 (the least open) never
    without = vb.factors(cam, 20.0, z, SIGMA, rt)
    assert float(with_hide[sel].mean()) > 0.9 > float(without[sel].mean()) + 0.2
    # a neutral frame (the gate shut): the hidden views count as usual
    z0 = torch.zeros_like(z)
    assert torch.allclose(vb.factors(cam, 20.0, z0, SIGMA, rt, means), vb.factors(cam, 20.0, z0, SIGMA, rt))


def test_the_servers_frames_take_the_penalty(recon):
    """``server/frames.py`` draws through ``animate(..., camera=)``: its frames change with the setting."""
    from server.frames import FrameRenderer

    model, av, cams, expr = recon
    gc = model.config.gaussians
    cam = Cameras.look_at(torch.tensor([[0.35, 0.0, 0.6]]), fov_deg=20.0, width=64, height=64)
    saved = gc.view_blend_expr_mm
    frames = {}
    try:
        for sigma in (0.0, SIGMA):
            gc.view_blend_expr_mm = sigma
            r = FrameRenderer(model, "cpu").render(av, torch.zeros(len(ICT53_NAMES)), cam, 95)
            frames[sigma] = np.asarray(Image.open(io.BytesIO(r.jpeg)).convert("RGB"), np.float32)
    finally:
        gc.view_blend_expr_mm = saved
    assert float(np.abs(frames[0.0] - frames[SIGMA]).max()) > 8  # the jaw and smile views' mouths fade in a neutral frame


def test_the_avatar_budget_bounds_the_tables_before_the_first_frame_and_counts_them_after(recon):
    import dataclasses

    model, av, cams, expr = recon
    gc = model.config.gaussians
    fresh = dataclasses.replace(av, view_blend=dataclasses.replace(av.view_blend))  # no tables built yet
    saved = gc.view_blend_expr_mm
    try:
        gc.view_blend_expr_mm = 0.0
        off = model.serving_nbytes(fresh)
        gc.view_blend_expr_mm = SIGMA
        before = model.serving_nbytes(fresh)
        model.animate(fresh, expr[1], camera=cams[0:1])
        pen = fresh.view_blend.__dict__["_expr"]
        after = model.serving_nbytes(fresh)
    finally:
        gc.view_blend_expr_mm = saved
    assert len(pen) > 0
    assert after - off == pen.nbytes  # once built: what the tables hold
    assert before - off >= pen.nbytes  # before: a bound


def test_a_malformed_view_expr_is_refused_naming_the_file_or_the_shape(recon, tmp_path):
    """``view.expr`` with the wrong number of views or a non-finite code is refused when the avatar
    file loads (the file named); one with another expression dimension loads (frames with the
    penalty off never read it) and a frame with the penalty on is refused, naming the shape."""
    from fastgha_core.io import load_avatar_file, save_avatar_file
    from fastgha_core.model.avatar import CanonicalAvatar

    model, av, cams, expr = recon
    path = tmp_path / "a.fgha"
    av.save(path)
    g, meta, extra = load_avatar_file(path)
    good = extra["view.expr"]
    nan = good.clone()
    nan[0, 0] = float("nan")
    for bad in (good[:2], good[0], nan):
        save_avatar_file(tmp_path / "bad.fgha", g, meta, {**extra, "view.expr": bad})
        with pytest.raises(ValueError, match=r"bad\.fgha.*expressions must be \[V=3, E\] finite"):
            CanonicalAvatar.load(tmp_path / "bad.fgha")
    save_avatar_file(tmp_path / "short.fgha", g, meta, {**extra, "view.expr": good[:, :52]})
    short = CanonicalAvatar.load(tmp_path / "short.fgha")
    gc = model.config.gaussians
    saved = gc.view_blend_expr_mm
    try:
        gc.view_blend_expr_mm = 0.0
        model.animate(short, expr[1], camera=cams[1:2])
        gc.view_blend_expr_mm = SIGMA
        with pytest.raises(ValueError, match=r"view\.expr.*\[V=3, E=53\].*got \[3, 52\]"):
            model.animate(short, expr[1], camera=cams[1:2])
    finally:
        gc.view_blend_expr_mm = saved
