"""The expression prior's per-avatar caches and fast paths (``PriorRuntime``): each against its plain
reference (``prior.shading_basis``, ``fastgha._combine``), and rebuilt when the avatar changes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastgha_core.data.headmodel import HeadModel
from fastgha_core.model.prior import PriorRuntime, _moving_vertices, bind, fit_head, load_basis, shading_at, shading_basis


@pytest.fixture(scope="module")
def basis():
    return load_basis("ict53")


@pytest.fixture(scope="module")
def identity(basis):
    rng = np.random.default_rng(5)
    ident = np.zeros(basis.identity_basis.shape[0], np.float32)
    ident[:12] = rng.standard_normal(12).astype(np.float32) * 0.8
    return ident


def test_shading_at_matches_shading_basis(basis, identity):
    """``shading_at`` (normals on only the triangles around the wanted vertices, one numba call) gives
    ``shading_basis``'s columns: moving vertices, vertices no blendshape moves (0) and repeats."""
    ref = shading_basis(identity, basis)  # [E, Nv]
    moving = _moving_vertices(basis)
    rng = np.random.default_rng(0)
    verts = np.concatenate([rng.choice(np.flatnonzero(moving), 500, replace=False), np.flatnonzero(~moving)[:20]])
    verts = np.concatenate([verts, verts[:7]])  # a vertex asked for twice
    got = shading_at(identity, basis, verts)
    assert got.shape == (basis.num_expression, len(verts)) and got.dtype == np.float32
    np.testing.assert_allclose(got, ref[:, verts], rtol=0, atol=1e-6)
    assert np.abs(ref[:, verts]).max() > 0.3  # real relighting among them, not all zeros
    assert np.all(got[:, ~moving[verts]] == 0)
    assert shading_at(identity, basis, np.zeros(0, np.int64)).shape == (basis.num_expression, 0)


def test_runtime_shading_reads_only_what_the_binding_uses(basis):
    """``PriorRuntime.shade_u`` fills the slots its binding reads (``shading_at``); the colour factor
    ``shading(z)`` equals the one from the full ``shading_basis`` for any expression."""
    hm = HeadModel.load()
    rng = np.random.default_rng(2)
    ident = np.zeros(hm.num_identity, np.float32)
    ident[:8] = rng.standard_normal(8) * 0.6
    pts = hm.vertices(ident)[:11248].astype(np.float32)
    fit = fit_head(pts, basis)
    sub = pts[rng.choice(len(pts), 3000, replace=False)] + rng.normal(0, 0.002, (3000, 3)).astype(np.float32)
    b = bind(torch.from_numpy(sub), fit, basis)
    rt = PriorRuntime(b, basis)
    full = np.zeros_like(rt.shade_u.numpy())
    full[:, 1:] = shading_basis(rt.identity, basis)[:, _moving_vertices(basis)]
    used = np.unique(rt.local.numpy())
    np.testing.assert_allclose(rt.shade_u.numpy()[:, used], full[:, used], rtol=0, atol=1e-6)
    assert len(used) < full.shape[1] // 2  # a few thousand points read a fraction of the slots
    w = rt.W
    for k in range(3):
        z = torch.rand(53, generator=torch.Generator().manual_seed(k)) * 0.8
        want = (1.0 + w @ (z @ torch.from_numpy(full))[:, None])[:, 0].clamp(0.5, 1.5)
        torch.testing.assert_close(rt.shading(z), want, rtol=0, atol=1e-5)
        assert float((want - 1).abs().max()) > 0.02
