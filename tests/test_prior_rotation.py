"""Bound Gaussians turn with their triangle of the fitted head (``PriorRuntime.rotation``, issue 16).

A synthetic blendshape turns one triangle of the ICT head rigidly by 90 degrees about an axis
that is neither its normal nor an edge; a Gaussian bound to that triangle must have its
covariance turned by the same rotation, one half-way out of the fade by a part of it, and one far
from the surface (weight 0) must keep its rotation exactly. Both the plain torch path and the
numba frame path are checked, and the gradient that training takes through the rotated quaternions.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from fastgha_core.gaussians import Gaussians
from fastgha_core.model.prior import PriorRuntime, bind, generic_fit, load_basis
from fastgha_core.render.projection import quat_to_rotmat


def _axis_angle(axis, angle: float) -> np.ndarray:
    u = np.asarray(axis, np.float64)
    u = u / np.linalg.norm(u)
    k = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


@pytest.fixture(scope="module")
def turned():
    """(basis whose blendshape 0 turns one cheek triangle by ``R`` about its centroid, that triangle, R)."""
    ict = load_basis("ict53")
    faces = ict.bind_faces[~ict.mouth_faces]
    faces = faces[(faces < 11248).all(1)]  # the skin (ICT-FaceKit's first 11248 vertices)
    v = ict.neutral.astype(np.float64)
    cen = v[faces].mean(1)
    near = np.flatnonzero(np.abs(cen[:, :2] - np.array([0.05, -0.03])).max(1) < 0.006)
    f = faces[near[np.argmax(cen[near, 2])]]  # the outermost skin triangle there: the left cheek
    R = _axis_angle([1.0, 2.0, 0.5], math.pi / 2)
    m = v[f].mean(0)
    eb = np.zeros_like(ict.expression_basis)
    eb[0, f] = ((v[f] - m) @ R.T + m - v[f]).astype(np.float32)  # corners' displacement: a rigid turn
    return dataclasses.replace(ict, expression_basis=eb), f, R


def _gaussians(points: np.ndarray, seed: int = 0) -> Gaussians:
    n = len(points)
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g)
    q = q / q.norm(dim=1, keepdim=True)
    scales = torch.tensor([0.004, 0.002, 0.0005]).expand(n, 3).contiguous()  # flat: the orientation shows
    return Gaussians(torch.from_numpy(points.astype(np.float32)), q, scales, torch.full((n,), 0.9), torch.full((n, 3), 0.5))


def _cov(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    Rq = quat_to_rotmat(quats.double())
    return Rq @ torch.diag_embed(scales.double() ** 2) @ Rq.transpose(1, 2)


@pytest.fixture(scope="module")
def bound(turned):
    basis, f, R = turned
    fit = generic_fit(basis)
    v = basis.neutral.astype(np.float64)
    m = v[f].mean(0)
    nrm = np.cross(v[f[1]] - v[f[0]], v[f[2]] - v[f[0]])
    nrm *= np.sign(nrm[2]) / np.linalg.norm(nrm)  # outwards (+z: out of the face)
    # on the triangle (weight 1), 15 mm off it along its normal (inside the fade), and 10 cm off (weight 0)
    pts = np.stack([m, m + 0.015 * nrm, m + 0.1 * nrm])
    b = bind(pts, fit, basis)
    assert b.weight[0] == 1.0 and 0.05 < float(b.weight[1]) < 0.95 and b.weight[2] == 0.0, b.weight
    assert sorted(b.vertex_ids[0].tolist()) == sorted(f.tolist()) and sorted(b.vertex_ids[1].tolist()) == sorted(f.tolist())
    return basis, b, pts, R


def _rotation_angle(q: torch.Tensor) -> float:
    return 2.0 * math.atan2(float(q[1:].norm()), abs(float(q[0])))


def test_a_gaussian_on_a_turned_triangle_turns_with_it(bound):
    basis, b, pts, R = bound
    rt = PriorRuntime(b, basis, shading=False, rotate=True)
    z = torch.zeros(basis.num_expression)
    z[0] = 1.0
    rot = rt.rotation(z)  # [3, 4]
    Rt = torch.from_numpy(R)
    torch.testing.assert_close(quat_to_rotmat(rot[:1].double())[0], Rt, rtol=0, atol=1e-5)
    # half-way out of the fade: a part of the turn about the same axis (nlerp by the weight)
    w = float(b.weight[1])
    s, c = math.sin(math.pi / 4), math.cos(math.pi / 4)
    want = 2.0 * math.atan2(w * s, (1 - w) + w * c)
    assert _rotation_angle(rot[1]) == pytest.approx(want, abs=1e-5) and 0.1 < want < math.pi / 2 - 0.1
    torch.testing.assert_close(rot[1, 1:] / rot[1, 1:].norm(), rot[0, 1:] / rot[0, 1:].norm(), rtol=0, atol=1e-5)
    assert torch.equal(rot[2], torch.tensor([1.0, 0.0, 0.0, 0.0]))  # unbound
    assert torch.equal(rt.rotation(torch.zeros(basis.num_expression)), torch.tensor([[1.0, 0, 0, 0]]).expand(3, 4))
    # batched: the same per expression
    torch.testing.assert_close(rt.rotation(torch.stack([z, torch.zeros_like(z)]))[0], rot)


def test_frame_path_turns_the_covariance_and_leaves_unbound_ones(bound):
    basis, b, pts, R = bound
    g = _gaussians(pts)
    rt = PriorRuntime(b, basis, shading=False, rotate=True)
    z = torch.zeros(basis.num_expression)
    z[0] = 1.0
    zero3 = torch.zeros(3, 3)
    out = rt.frame(g, 0, zero3, zero3, z)
    Rt = torch.from_numpy(R)
    cov0, cov1 = _cov(g.quats, g.scales), _cov(out.quats, out.scales)
    torch.testing.assert_close(cov1[0], Rt @ cov0[0] @ Rt.T, rtol=0, atol=1e-10)  # covariances are ~1e-5 m^2
    assert float((cov1[0] - cov0[0]).abs().max()) > 1e-6  # it did turn
    assert torch.equal(out.quats[2], g.quats[2])  # weight 0: exactly the canonical rotation
    # the frame path against the plain path (quaternion_multiply of rotation(z)), every Gaussian
    from fastgha_core.model.gaussian_head import quaternion_multiply

    torch.testing.assert_close(out.quats, quaternion_multiply(rt.rotation(z), g.quats), rtol=0, atol=2e-6)
    # off, the prior moves centres only
    off = PriorRuntime(b, basis, shading=False, rotate=False).frame(g, 0, zero3, zero3, z)
    assert torch.equal(off.quats, g.quats) and torch.equal(off.means, out.means)


def test_training_gradient_reaches_the_gaussians_rotation(bound):
    """``fastgha._combine`` (the training path) applies ``rot`` after the Gaussians' own rotation; the
    gradient of a loss on the result's quaternions reaches ``g.quats`` turned back by ``rot``'s
    conjugate (the Hamilton product by a unit quaternion is orthogonal), and none flows to ``rot``."""
    from fastgha_core.model.fastgha import _combine

    basis, b, pts, R = bound
    rt = PriorRuntime(b, basis, shading=False, rotate=True)
    z = torch.zeros(basis.num_expression)
    z[0] = 0.7
    g = _gaussians(pts, seed=1)
    q = g.quats.clone().requires_grad_(True)
    g = g.replace(quats=q)
    rot = rt.rotation(z)
    assert not rot.requires_grad
    c = torch.randn(3, 4, generator=torch.Generator().manual_seed(2))
    out = _combine(g, torch.zeros(3, 3), torch.zeros(3, 3), rt.displacement(z), 0, None, rot=rot)
    (out.quats * c).sum().backward()
    conj = rot * torch.tensor([1.0, -1.0, -1.0, -1.0])
    from fastgha_core.model.gaussian_head import quaternion_multiply

    torch.testing.assert_close(q.grad, quaternion_multiply(conj, c), rtol=0, atol=1e-6)
    assert float((q.grad - c).abs().max()) > 1e-3  # the turned Gaussians' gradient is turned too
    torch.testing.assert_close(q.grad[2], c[2])  # unbound: unchanged


def test_an_input_photos_expression_is_undone_in_the_rotations_too():
    """``build_prior`` with the photos' expressions subtracts each photo's displacement from its
    Gaussians (a neutral canonical head); with ``prior_rotate`` it also turns them back by that
    expression's surface rotation, so animating the avatar to the photo's own expression gives the
    photographed rotations back, and a neutral photo's Gaussians keep theirs."""
    from fastgha_core.config import get_preset
    from fastgha_core.data.headmodel import HeadModel
    from fastgha_core.model.avatar import CanonicalAvatar
    from fastgha_core.model.fastgha import FastGHA

    hm = HeadModel.load()
    names = hm.expression_names
    jaw_z = torch.zeros(53)
    jaw_z[names.index("jawOpen")] = 0.7
    torch.manual_seed(0)
    cfg = get_preset("tiny")
    cfg.deform.prior_rotate = True
    model = FastGHA(cfg).eval()
    v = torch.from_numpy(hm.neutral[:11248:2].copy())
    n = len(v)
    jaw = torch.from_numpy(hm.expression_basis[names.index("jawOpen"), :11248:2].copy())
    q = torch.randn(2 * n, 4, generator=torch.Generator().manual_seed(3))
    q = q / q.norm(dim=1, keepdim=True)
    g = Gaussians(torch.cat([v, v + 0.7 * jaw]), q, torch.full((2 * n, 3), 0.002), torch.full((2 * n,), 0.9), torch.full((2 * n, 3), 0.6), torch.randn(2 * n, 32) * 0.1)
    vi = torch.arange(2).repeat_interleave(n)  # view 0 neutral, view 1 photographed with the jaw 0.7 open
    g2, binding, n_int = model.build_prior(g, vi, torch.stack([torch.zeros(53), jaw_z]))
    assert torch.equal(g2.quats[:n], q[:n])  # the neutral photo: untouched
    turned = (g2.quats[n : 2 * n] - q[n:]).abs().max(1).values > 1e-3
    assert int(turned.sum()) > 500  # the jaw's Gaussians of the open photo were turned back
    avatar = CanonicalAvatar(g2, "tiny", "ict53", binding, n_int)
    again = model.animate(avatar, jaw_z)  # the photo's own expression: its rotations come back
    torch.testing.assert_close(again.quats[n : 2 * n], q[n:], rtol=0, atol=2e-5)
    cfg_off = get_preset("tiny")
    assert not cfg_off.deform.prior_rotate  # off by default: the prior moves centres only
    g3, _, _ = FastGHA(cfg_off).eval().build_prior(g, vi, torch.stack([torch.zeros(53), jaw_z]))
    assert torch.equal(g3.quats[: 2 * n], q)
