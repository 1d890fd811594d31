"""ICT-FaceKit head model: units, axes, centring, linear blending, visible surfaces."""

import numpy as np
import pytest
import torch

from fastgha_core.data.headmodel import SHADING_HELPER_MATERIALS, HeadModel, vertex_normals

FACE = slice(0, 9409)  # face vertex ids of ICT-FaceKit


@pytest.fixture(scope="module")
def hm():
    return HeadModel.load()


def test_shapes_and_names(hm):
    assert hm.neutral.shape == (26719, 3) and hm.neutral.dtype == np.float32
    assert hm.identity_basis.shape == (100, 26719, 3)
    assert hm.expression_basis.shape == (53, 26719, 3)
    assert len(hm.expression_names) == 53 and hm.expression_names[0] == "browDown_L"
    assert hm.expression_names[-1] == "noseSneer_R"
    assert hm.landmarks68.shape == (68,)
    assert "MIT" in hm.license
    assert HeadModel.load() is hm  # cached


def test_units_axes_and_centre(hm):
    v = hm.vertices()
    lm = v[hm.landmarks68]
    face = v[FACE]
    # nose tip (landmark 30) is the most forward face vertex (+z out of the face)
    assert np.isclose(lm[30, 2], face[:, 2].max(), atol=2e-3)
    # head height chin -> crown in metres
    crown = v[:11248, 1].max()
    assert 0.2 <= crown - lm[8, 1] <= 0.3
    # the subject's left eye (Multi-PIE points 42-47) is at +x, right eye (36-41) at -x
    assert lm[42:48, 0].mean() > 0.02 and lm[36:42, 0].mean() < -0.02
    # eyes above the mouth (+y up)
    assert lm[36:48, 1].mean() > lm[48:68, 1].mean() + 0.03
    # centred on the head: chin/crown and back/nose-tip symmetric about the origin
    assert abs(crown + lm[8, 1]) < 1e-5
    assert np.all(np.abs(lm[27:36].mean(0)) < 0.15)


def test_blending_matches_float64_reference(hm):
    rng = np.random.default_rng(0)
    ident = rng.normal(0, 1, 100).astype(np.float32)
    expr = rng.uniform(0, 1, 53).astype(np.float32)
    got = hm.vertices(ident, expr)
    ref = (
        hm.neutral.astype(np.float64)
        + np.einsum("k,kvd->vd", ident.astype(np.float64), hm.identity_basis.astype(np.float64))
        + np.einsum("k,kvd->vd", expr.astype(np.float64), hm.expression_basis.astype(np.float64))
    )
    np.testing.assert_allclose(got, ref, atol=2e-6, rtol=0)
    # torch path (differentiable) agrees and carries gradients
    e = torch.tensor(expr, requires_grad=True)
    vt = hm.vertices(torch.tensor(ident), e)
    torch.testing.assert_close(vt, torch.from_numpy(ref.astype(np.float32)), atol=2e-6, rtol=0)
    vt[hm.landmarks68[66], 1].backward()
    torch.testing.assert_close(e.grad, torch.tensor(hm.expression_basis[:, hm.landmarks68[66], 1]))


def test_jaw_open_moves_chin_down(hm):
    e = np.zeros(53, np.float32)
    e[hm.expression_names.index("jawOpen")] = 1.0
    d = hm.vertices(None, e)[hm.landmarks68[8]] - hm.vertices()[hm.landmarks68[8]]
    assert d[1] < -0.01  # more than a centimetre down


def test_bad_shapes(hm):
    with pytest.raises(ValueError, match=r"\[100\]"):
        hm.vertices(np.zeros(99))
    with pytest.raises(ValueError, match=r"\[53\]"):
        hm.vertices(None, torch.zeros(52))
    with pytest.raises(ValueError, match="unknown material"):
        hm.material_mask("M_Nope")


def test_visible_faces_exclude_helpers(hm):
    mask = hm.visible_face_mask()
    helpers = hm.material_mask(*SHADING_HELPER_MATERIALS)
    assert not (mask & helpers).any() and (mask | helpers).all()
    no_lash = hm.visible_faces(eyelashes=False)
    assert len(no_lash) == len(hm.visible_faces()) - int(hm.material_mask("M_EyeLashes").sum())


def test_normals_point_outward(hm):
    v = hm.vertices()
    n = vertex_normals(v, hm.visible_faces())
    assert n[hm.landmarks68[30], 2] > 0.9  # nose tip faces +z
    top = np.argmax(v[:11248, 1])
    assert n[top, 1] > 0.9  # crown faces up
