"""The gsplat (CUDA) backend against the CPU kernels. Needs CUDA and gsplat (extra ``cuda``)."""

from __future__ import annotations

import importlib.util

import pytest
import torch

pytestmark = pytest.mark.skipif(
    not (torch.cuda.is_available() and importlib.util.find_spec("gsplat") is not None), reason="needs CUDA and gsplat"
)


def test_gsplat_matches_cpu_on_a_soft_scene():
    from fastgha_core import Cameras, Gaussians
    from fastgha_core.render import render

    g = torch.Generator().manual_seed(0)
    n = 300
    # opacities <= 0.9 keep away from the alpha clamp, where gsplat (0.999) and we (0.99) differ
    gs = Gaussians(
        torch.randn(n, 3, generator=g) * 0.08,
        torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1),
        torch.exp(torch.rand(n, 3, generator=g) * 2 - 5),
        torch.rand(n, generator=g) * 0.6 + 0.2,
        torch.rand(n, 3, generator=g),
    )
    cams = Cameras.look_at(torch.tensor([[0.0, 0.0, 1.0], [0.3, 0.1, 0.9]]), fov_deg=30.0, width=64, height=48)
    cpu = render(gs, cams, background=(1.0, 1.0, 1.0), backend="cpu")
    gpu = render(gs.to("cuda"), cams.to("cuda"), background=(1.0, 1.0, 1.0), backend="auto")
    for name in ("rgb", "alpha", "depth"):
        torch.testing.assert_close(getattr(gpu, name).cpu(), getattr(cpu, name), rtol=1e-2, atol=1e-2, msg=name)
