"""The deformation MLP: identity at initialisation, and the real-time split == the plain MLP."""

from __future__ import annotations

import math

import pytest
import torch
from torch.testing import assert_close

from fastgha_core.config import DeformConfig
from fastgha_core.model.deform import DeformationMLP, positional_encoding
from fastgha_core.perf import cpp_compiler

needs_compiler = pytest.mark.skipif(cpp_compiler() is None, reason="torch.compile (inductor) needs a C++ compiler on CPU")

F_DIM, E_DIM, N = 8, 11, 300


def _mlp(seed: int = 0, randomise_out: bool = True) -> DeformationMLP:
    torch.manual_seed(seed)
    mlp = DeformationMLP(F_DIM, E_DIM, DeformConfig(hidden_size=24, num_layers=3, pe_freqs=3))
    if randomise_out:
        torch.nn.init.normal_(mlp.out.weight, std=0.2)
        torch.nn.init.normal_(mlp.out.bias, std=0.2)
    return mlp


def _inputs(seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(N, F_DIM, generator=g), torch.rand(N, 3, generator=g) * 0.3 - 0.15, g


def test_identity_at_initialisation():
    mlp = _mlp(randomise_out=False)
    feats, xyz, g = _inputs()
    for expr in (torch.randn(E_DIM, generator=g), torch.randn(4, E_DIM, generator=g)):
        dxyz, drgb = mlp(feats, xyz, expr)
        assert torch.equal(dxyz, torch.zeros_like(dxyz)) and torch.equal(drgb, torch.zeros_like(drgb))
        assert dxyz.shape == (*expr.shape[:-1], N, 3)


def test_positional_encoding_values():
    xyz = torch.tensor([[0.1, -0.2, 0.05]])
    pe = positional_encoding(xyz, 2, 4.0)
    x = xyz * 4.0
    expect = torch.cat([x, torch.sin(x * math.pi), torch.sin(x * 2 * math.pi), torch.cos(x * math.pi), torch.cos(x * 2 * math.pi)], -1)
    # layout: [x (3), sin (3 coords x 2 freqs, coordinate-major), cos (same)]
    order = [0, 1, 2, 3, 6, 4, 7, 5, 8, 9, 12, 10, 13, 11, 14]
    assert_close(pe, expect[:, order])


@pytest.mark.parametrize("batched", [False, True])
def test_split_equals_plain_outputs_and_gradients(batched):
    mlp = _mlp()
    feats, xyz, g = _inputs()
    expr = torch.randn(3, E_DIM, generator=g) if batched else torch.randn(E_DIM, generator=g)
    w = torch.randn(*expr.shape[:-1], N, 6, generator=g)

    def run(split: bool):
        mlp.zero_grad()
        f, x, z = feats.clone().requires_grad_(), xyz.clone().requires_grad_(), expr.clone().requires_grad_()
        if split:
            dxyz, drgb = mlp.forward_split(mlp.precompute(f, x), z)
        else:
            dxyz, drgb = mlp(f, x, z)
        (torch.cat([dxyz, drgb], -1) * w).sum().backward()
        grads = {n: p.grad.clone() for n, p in mlp.named_parameters()}
        return dxyz, drgb, f.grad, x.grad, z.grad, grads

    plain, split = run(False), run(True)
    for a, b in zip(plain[:5], split[:5]):
        assert_close(b, a)
    for name in plain[5]:
        assert_close(split[5][name], plain[5][name], msg=name)
    assert plain[0].abs().max() > 0


@pytest.mark.parametrize("batched", [False, True])
def test_chunked_inference_split_equals_plain(batched):
    mlp = _mlp()
    feats, xyz, g = _inputs()
    expr = torch.randn(2, E_DIM, generator=g) if batched else torch.randn(E_DIM, generator=g)
    with torch.no_grad():
        ref = mlp(feats, xyz, expr)
        got = mlp.forward_split(mlp.precompute(feats, xyz), expr, chunk_size=64)  # N=300: 5 chunks, ragged last
    for a, b in zip(ref, got):
        assert_close(b, a)


def test_bf16_autocast_is_close_to_fp32():
    mlp = _mlp()
    feats, xyz, g = _inputs()
    expr = torch.randn(E_DIM, generator=g)
    with torch.no_grad():
        partial = mlp.precompute(feats, xyz)
        ref = mlp.forward_split(partial, expr)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = mlp.forward_split(partial, expr)
    for a, b in zip(ref, low):
        scale = a.abs().max()
        assert (b.float() - a).abs().max() <= 0.03 * scale


def test_shape_errors():
    mlp = _mlp()
    feats, xyz, _ = _inputs()
    with pytest.raises(ValueError, match=r"expression must have shape \[11\]"):
        mlp(feats, xyz, torch.zeros(12))
    with pytest.raises(ValueError, match=r"features must have shape \[N, 8\]"):
        mlp(feats[:, :4], xyz, torch.zeros(11))
    with pytest.raises(ValueError, match=r"partial must have shape \[N, 24\]"):
        mlp.forward_split(torch.zeros(N, 5), torch.zeros(11))


@needs_compiler
def test_compiled_tail_equals_eager_for_any_size_and_keeps_autograd_eager():
    mlp = _mlp()
    feats, xyz, g = _inputs()
    expr = torch.randn(E_DIM, generator=g)
    with torch.no_grad():
        partial = mlp.precompute(feats, xyz)
        ref = mlp.forward_split(partial, expr, chunk_size=64)
        ref_small = mlp.forward_split(partial[:37], expr, chunk_size=64)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            ref_bf16 = mlp.forward_split(partial, expr, chunk_size=64)
    mlp.compile_tail()
    assert mlp.compiled
    with torch.no_grad():
        got = mlp.forward_split(partial, expr, chunk_size=64)  # 5 chunks, the last padded from 44 to 64 rows
        got_small = mlp.forward_split(partial[:37], expr, chunk_size=64)  # fewer rows than one chunk: padded too
        with torch.autocast("cpu", dtype=torch.bfloat16):
            got_bf16 = mlp.forward_split(partial, expr, chunk_size=64)
    for a, b in [*zip(ref, got), *zip(ref_small, got_small)]:
        assert b.shape == a.shape
        assert_close(b, a, rtol=1e-5, atol=1e-6)
    for a, b in zip(ref_bf16, got_bf16):
        assert b.shape == a.shape
        assert (b.float() - a.float()).abs().max() <= 0.02 * a.float().abs().max()
    # with autograd the compiled tail is not used: gradients flow as in the plain MLP
    p = partial.clone().requires_grad_(True)
    dxyz, drgb = mlp.forward_split(p, expr, chunk_size=64)
    (dxyz.sum() + drgb.sum()).backward()
    assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
    mlp.compile_tail(False)
    assert not mlp.compiled


def test_cuda_graphs_need_a_cuda_device():
    from fastgha_core.config import get_preset
    from fastgha_core.model.fastgha import FastGHA

    cfg = get_preset("tiny")
    cfg.input_size = cfg.render_size = 32
    model = FastGHA(cfg).eval()
    with pytest.raises(ValueError, match="CUDA graphs need a CUDA device"):
        model.compile_deformation(cuda_graphs=True)
    assert not model.deform.compiled


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_graph_tail_equals_eager_across_calls():
    mlp = _mlp().cuda()
    feats, xyz, g = _inputs()
    feats, xyz = feats.cuda(), xyz.cuda()
    exprs = [torch.randn(E_DIM, generator=g).cuda() for _ in range(3)]
    with torch.no_grad():
        partial = mlp.precompute(feats, xyz)
        refs = [mlp.forward_split(partial, e, chunk_size=64) for e in exprs]
        mlp.compile_tail(mode="reduce-overhead")
        # several calls: each replay reuses the graph's output memory, earlier results must survive
        got = [mlp.forward_split(partial, e, chunk_size=64) for e in exprs * 2]
    for i, out in enumerate(got):
        for a, b in zip(refs[i % 3], out):
            assert_close(b, a, rtol=1e-4, atol=1e-5)


@needs_compiler
def test_compile_deformation_warms_up_the_graph_that_animate_uses():
    # the server compiles at start-up; a first frame that recompiled would stall a client for seconds
    from torch._dynamo.utils import counters

    from fastgha_core.cameras import orbit_cameras
    from fastgha_core.config import get_preset
    from fastgha_core.model.fastgha import FastGHA

    cfg = get_preset("tiny")
    cfg.input_size = cfg.render_size = 32
    cfg.deform.prior = False  # the compiled MLP alone (frames of a prior avatar leave out hidden mouth/lid Gaussians)
    torch.manual_seed(0)
    model = FastGHA(cfg).eval()
    torch.nn.init.normal_(model.deform.out.weight, std=0.2)  # a live deformation, not the identity
    with torch.no_grad():
        avatar = model.reconstruct(torch.rand(2, 3, 32, 32), orbit_cameras(2, width=32, height=32))
    expr = model.expression_space.neutral() + 0.2
    eager = model.animate(avatar, expr, bf16=True)
    model.compile_deformation(bf16=True)
    graphs = counters["stats"]["unique_graphs"]
    with torch.no_grad():
        a = model.animate(avatar, expr, bf16=True)
    with torch.inference_mode():
        b = model.animate(avatar, expr, bf16=True)
    c = model.animate(avatar, expr, bf16=True)
    assert (eager.means - avatar.gaussians.means).abs().max() > 1e-3  # the deformation is live
    assert counters["stats"]["unique_graphs"] == graphs  # no recompilation in any grad mode
    for g in (a, b, c):
        assert_close(g.means, eager.means, rtol=0, atol=1e-3)
        assert_close(g.colors, eager.colors, rtol=0, atol=1e-2)
    model.deform.compile_tail(False)
