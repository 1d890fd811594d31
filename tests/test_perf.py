"""fastgha_core.perf (thread settings, machine description) and the rasterizer's no-gradient
float32 fast path against the dense reference."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest
import torch

from fastgha_core import perf
from fastgha_core.render import render
from fastgha_core.render import cpu_kernels as K
from fastgha_core.render.projection import ALPHA_MIN, project_gaussians

sys.path.insert(0, os.path.dirname(__file__))
from test_render import cameras, random_scene  # noqa: E402


def test_apply_env_defaults_sets_only_missing_values():
    env: dict[str, str] = {}
    assert perf.apply_env_defaults(env) == perf.ENV_DEFAULTS
    assert env == perf.ENV_DEFAULTS
    env = {"GOMP_SPINCOUNT": "5"}
    assert perf.apply_env_defaults(env) == {} and env["GOMP_SPINCOUNT"] == "5"
    env = {"OMP_WAIT_POLICY": "ACTIVE"}  # the user's policy wins: nothing added that would override it
    assert perf.apply_env_defaults(env) == {} and "GOMP_SPINCOUNT" not in env


def test_wait_policy_effective_reads_the_environment():
    assert perf.wait_policy_effective({"OMP_WAIT_POLICY": "passive"})
    assert perf.wait_policy_effective({"GOMP_SPINCOUNT": "10000"})
    assert not perf.wait_policy_effective({"GOMP_SPINCOUNT": "300000"})
    assert not perf.wait_policy_effective({})


def test_cpu_flags_parses_cpuinfo_text():
    text = "processor\t: 0\nmodel name\t: Test CPU 9000\nflags\t\t: fpu avx2 avx512f avx512_bf16\n\nprocessor\t: 1\nflags\t: fpu\n"
    model, flags = perf.cpu_flags(text)
    assert model == "Test CPU 9000"
    assert {"avx2", "avx512f", "avx512_bf16"} <= flags and "amx_bf16" not in flags


def test_configure_threads_sets_torch_and_numba_threads(monkeypatch):
    before = torch.get_num_threads()
    monkeypatch.delenv("FASTGHA_NUMBA_THREADS", raising=False)
    try:
        cfg = perf.configure_threads(1, numba_threads=1)
        assert cfg.torch_threads == 1 and torch.get_num_threads() == 1
        assert cfg.numba_threads == 1 and os.environ["FASTGHA_NUMBA_THREADS"] == "1"
        with pytest.raises(ValueError, match="threads must be >= 1"):
            perf.configure_threads(0)
    finally:
        torch.set_num_threads(before)
        os.environ.pop("FASTGHA_NUMBA_THREADS", None)


def test_describe_machine_has_the_documented_fields():
    d = perf.describe_machine()
    assert d["cores"] >= 1 and isinstance(d["cpu_model"], str)
    assert set(perf.ISA_FLAGS) == set(d["isa_flags"])
    assert {"torch_threads", "numba_threads", "numba_layer"} <= set(d["threads"])


# ------------------------------------------------------------------ fast raster path
def test_polynomial_exp_matches_exp():
    s = np.linspace(0.0, 12.0, 20001, dtype=np.float32)
    np.testing.assert_allclose(K.exp_neg32(s), np.exp(-s.astype(np.float64)), rtol=2e-6, atol=0)


def _boundary_pixels(g, cams, rel=1e-4):
    """Pixels where some splat's alpha lies within ``rel`` of the ALPHA_MIN cut (float64): there a
    float32 evaluation may legitimately fall on the other side of the cut than a float64 one."""
    gd, cd = g.to(dtype=torch.float64), cams.to(dtype=torch.float64)
    p = project_gaussians(gd.means, gd.quats, gd.scales, cd.K, cd.w2c, cams.width, cams.height)
    ys, xs = torch.meshgrid(torch.arange(cams.height, dtype=torch.float64) + 0.5, torch.arange(cams.width, dtype=torch.float64) + 0.5, indexing="ij")
    out = []
    for c in range(p.means2d.shape[0]):
        dx = p.means2d[c, :, 0] - xs[..., None]  # [H, W, N]
        dy = p.means2d[c, :, 1] - ys[..., None]
        co = p.conics[c]
        sig = 0.5 * (co[:, 0] * dx * dx + co[:, 2] * dy * dy) + co[:, 1] * dx * dy
        al = gd.opacities * torch.exp(-sig)
        near = ((al / ALPHA_MIN - 1.0).abs() < rel) & (p.radii[c] > 0)
        out.append(near.any(-1))
    return torch.stack(out)[:, None]  # [C, 1, H, W]


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_fast_path_matches_reference(seed, monkeypatch):
    monkeypatch.delenv("FASTGHA_RASTER_FAST", raising=False)
    g, cams = random_scene(seed, n=300, dtype=torch.float32), cameras(64, 48, torch.float32)
    bg = (0.2, 0.3, 0.4)
    with torch.no_grad():
        fast = render(g, cams, background=bg, backend="cpu")  # float32, no grad: the fast path
        ref = render(g.to(dtype=torch.float64), cams.to(dtype=torch.float64), background=bg, backend="reference")
    keep = ~_boundary_pixels(g, cams)  # [C, 1, H, W]
    assert keep.float().mean() > 0.99
    for name in ("rgb", "alpha", "depth"):
        a, b = getattr(fast, name), getattr(ref, name).float()
        m = keep.expand_as(a)
        torch.testing.assert_close(a[m], b[m], rtol=2e-4, atol=2e-4, msg=name)


def test_fast_path_is_taken_only_without_gradients(monkeypatch):
    from fastgha_core.render import cpu_backend

    calls = []
    real = cpu_backend.rasterize_fast
    monkeypatch.setattr(cpu_backend, "rasterize_fast", lambda *a, **k: calls.append(1) or real(*a, **k))
    g, cams = random_scene(4, n=80, dtype=torch.float32), cameras(32, 24, torch.float32)
    with torch.no_grad():
        a = render(g, cams, backend="cpu")
    assert calls == [1]
    x = {k: getattr(g, k).detach().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "colors")}
    b = render(type(g)(**x), cams, backend="cpu")
    b.rgb.sum().backward()
    assert calls == [1] and x["means"].grad is not None
    torch.testing.assert_close(a.rgb, b.rgb.detach(), rtol=2e-4, atol=2e-4)
    monkeypatch.setenv("FASTGHA_RASTER_FAST", "0")
    with torch.no_grad():
        render(g, cams, backend="cpu")
    assert calls == [1]


def test_fast_path_empty_and_culled_scenes_give_background():
    from fastgha_core import Gaussians

    cams = cameras(20, 12, torch.float32)
    bg = torch.tensor([0.9, 0.1, 0.4])
    behind = random_scene(0, n=20, dtype=torch.float32)
    behind = behind.replace(means=behind.means * 0.01 + torch.tensor([0.0, 0.0, 3.0]))
    for g in (Gaussians.empty(dtype=torch.float32), behind):
        with torch.no_grad():
            out = render(g, cams, background=bg, backend="cpu")
        torch.testing.assert_close(out.rgb, bg[None, :, None, None].expand(3, 3, 12, 20))
        assert (out.alpha == 0).all() and (out.depth == 0).all()


def test_fast_path_is_deterministic_across_thread_counts(monkeypatch):
    g, cams = random_scene(11, n=200, dtype=torch.float32), cameras(64, 48, torch.float32)
    with torch.no_grad():
        a = render(g, cams, backend="cpu")
        monkeypatch.setenv("FASTGHA_NUMBA_THREADS", "1")
        b = render(g, cams, backend="cpu")
    for name in ("rgb", "alpha", "depth"):
        assert torch.equal(getattr(a, name), getattr(b, name))
