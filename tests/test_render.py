"""Rasterizer: numba CPU kernels and pure-torch tiles against the dense reference, plus
analytic cases (single Gaussian, occlusion, depth of a plane, empty scenes)."""

from __future__ import annotations


import pytest
import torch

from fastgha_core import Cameras, Gaussians
from fastgha_core.render import RenderOutput, render
from fastgha_core.render.projection import ALPHA_MAX, ALPHA_MIN, EPS2D, project_gaussians
from fastgha_core.render.reference import rasterize_reference
from fastgha_core.render.torch_tiles import rasterize_torch_tiles


def random_scene(seed: int, n: int = 160, dtype=torch.float64) -> Gaussians:
    """Anisotropic rotated Gaussians with heavy overlap around the origin, plus some far
    off-screen, some behind the cameras and some (nearly) opaque ones."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * 0.08
    means[: n // 10] += torch.tensor([0.0, 0.0, 1.6])  # behind the cameras (cameras at z ~ 1)
    means[n // 10 : n // 5, 0] += 0.6  # off-screen to the side (some footprints still reach in)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    scales = torch.exp(torch.rand(n, 3, generator=g) * 2.5 - 5.0)  # 7 mm .. 8 cm, anisotropic
    opac = torch.rand(n, generator=g) * 0.95 + 0.04
    opac[n // 5 : n // 5 + 10] = 1.0  # clamped at ALPHA_MAX near their centres
    colors = torch.rand(n, 3, generator=g)
    return Gaussians(means, quats, scales, opac, colors).to(dtype=dtype)


def cameras(width: int = 45, height: int = 37, dtype=torch.float64) -> Cameras:
    eye = torch.tensor([[0.0, 0.0, 1.0], [0.35, 0.15, 0.9], [-0.2, -0.3, 0.95]])
    return Cameras.look_at(eye, fov_deg=30.0, width=width, height=height).to(dtype=dtype)


def leaves(g: Gaussians) -> dict[str, torch.Tensor]:
    return {k: getattr(g, k).detach().clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "colors")}


def run(g: Gaussians, cams: Cameras, backend: str, background=None):
    """Outputs and gradients of a loss touching rgb, alpha and depth."""
    x = leaves(g)
    out = render(Gaussians(**x), cams, background=background, backend=backend)
    gen = torch.Generator().manual_seed(123)
    w = [torch.rand(t.shape, generator=gen, dtype=t.dtype) for t in (out.rgb, out.alpha, out.depth)]
    loss = (out.rgb * w[0]).sum() + (out.alpha * w[1]).sum() + (out.depth * w[2]).sum()
    loss.backward()
    return out, {k: v.grad for k, v in x.items()}


def assert_same(a, b, rtol, atol):
    out_a, grad_a = a
    out_b, grad_b = b
    for name in ("rgb", "alpha", "depth"):
        torch.testing.assert_close(getattr(out_a, name), getattr(out_b, name), rtol=rtol, atol=atol, msg=name)
    for name in grad_a:
        torch.testing.assert_close(grad_a[name], grad_b[name], rtol=rtol, atol=atol, msg=f"grad {name}")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cpu_matches_reference_float64(seed):
    g, cams = random_scene(seed), cameras()
    bg = torch.tensor([[0.2, 0.5, 0.9], [1.0, 1.0, 1.0], [0.0, 0.3, 0.1]], dtype=torch.float64)
    ref = run(g, cams, "reference", bg)
    cpu = run(g, cams, "cpu", bg)
    # the scene really exercises the interesting paths
    assert (ref[0].alpha > 0.5).float().mean() > 0.2
    assert (ref[0].alpha == 0).any()
    assert_same(cpu, ref, rtol=1e-9, atol=1e-9)


def test_cpu_matches_reference_float32_square_image():
    g, cams = random_scene(7, n=120, dtype=torch.float32), cameras(32, 32, torch.float32)
    assert_same(run(g, cams, "cpu"), run(g, cams, "reference"), rtol=2e-4, atol=2e-4)


@pytest.mark.parametrize("seed", [3, 4])
def test_torch_tiles_matches_reference(seed):
    g, cams = random_scene(seed), cameras()
    assert_same(run(g, cams, "torch_tiles", (0.3, 0.3, 0.3)), run(g, cams, "reference", (0.3, 0.3, 0.3)), rtol=1e-9, atol=1e-9)


def test_torch_tiles_small_chunks_carry_the_stop_state():
    g, cams = random_scene(5), cameras()
    C = cams.K.shape[0]
    proj = project_gaussians(g.means, g.quats, g.scales, cams.K, cams.w2c, cams.width, cams.height)
    values = torch.cat([g.colors.expand(C, -1, 3), proj.depths[..., None]], dim=-1)
    acc_r, alpha_r = rasterize_reference(proj, g.opacities, values, cams.width, cams.height)
    acc_t, alpha_t = rasterize_torch_tiles(proj, g.opacities, values, cams.width, cams.height, chunk=3)
    acc_c, alpha_c = rasterize_reference(proj, g.opacities, values, cams.width, cams.height, pixel_chunk=100)
    assert (alpha_r > 0.999).any()  # some pixels stop early
    for acc, alpha in ((acc_t, alpha_t), (acc_c, alpha_c)):
        torch.testing.assert_close(acc, acc_r, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(alpha, alpha_r, rtol=1e-10, atol=1e-10)


def test_gradcheck_cpu_float64():
    torch.manual_seed(0)
    n = 4
    means = torch.tensor([[0.0, 0.0, 0.0], [0.02, -0.01, 0.05], [-0.03, 0.02, -0.04], [0.01, 0.03, 0.02]], dtype=torch.float64)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, dtype=torch.float64), dim=-1)
    scales = torch.tensor([[0.02, 0.01, 0.015], [0.015, 0.02, 0.01], [0.03, 0.01, 0.02], [0.01, 0.01, 0.02]], dtype=torch.float64)
    opac = torch.tensor([0.6, 0.5, 0.7, 0.4], dtype=torch.float64)
    colors = torch.rand(n, 3, dtype=torch.float64)
    cams = Cameras.look_at(torch.tensor([[0.0, 0.0, 0.5]]), fov_deg=25.0, width=18, height=17).to(dtype=torch.float64)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)

    def f(m, q, s, o, c):
        out = render(Gaussians(m, q, s, o, c), cams, background=bg, backend="cpu")
        return out.rgb, out.alpha, out.depth

    inputs = tuple(t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors))
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_single_isotropic_gaussian_matches_analytic():
    f, W, H, z, s, o = 40.0, 32, 32, 2.0, 0.15, 0.8
    K = torch.tensor([[[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]]], dtype=torch.float64)
    cams = Cameras(K, torch.eye(4, dtype=torch.float64)[None], W, H)
    color = torch.tensor([[0.2, 0.7, 0.4]], dtype=torch.float64)
    g = Gaussians(
        torch.tensor([[0.0, 0.0, z]], dtype=torch.float64), torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
        torch.full((1, 3), s, dtype=torch.float64), torch.tensor([o], dtype=torch.float64), color,
    )
    var = (f * s / z) ** 2 + EPS2D  # pixels^2, footprint radius ceil(3 sqrt(var)) covers the image
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5, indexing="ij")
    a = o * torch.exp(-0.5 * ((xs - W / 2) ** 2 + (ys - H / 2) ** 2) / var)
    a = torch.where(a >= ALPHA_MIN, a.clamp(max=ALPHA_MAX), torch.zeros_like(a))
    for backend in ("cpu", "reference"):
        out = render(g, cams, backend=backend)
        torch.testing.assert_close(out.alpha[0, 0], a, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(out.rgb[0], color[0, :, None, None] * a, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(out.depth[0, 0], torch.where(a > 0, z, 0.0).double(), rtol=1e-12, atol=1e-12)


def test_near_opaque_splat_hides_far_one():
    W = H = 25  # odd: the centre pixel's centre is exactly on the splats' means
    cams = Cameras.look_at(torch.tensor([0.0, 0.0, 1.0]), fov_deg=30.0, width=W, height=H).to(dtype=torch.float64)
    # index 0 is the far one: the order must come from depth, not from the array
    means = torch.tensor([[0.0, 0.0, -0.5], [0.0, 0.0, 0.3]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=torch.float64)
    scales = torch.tensor([[0.05] * 3, [0.05] * 3], dtype=torch.float64)
    colors = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    g = Gaussians(means, quats, scales, torch.tensor([0.9, 1.0], dtype=torch.float64), colors)
    for backend in ("cpu", "reference", "torch_tiles"):
        out = render(g, cams, backend=backend)
        c = out.rgb[0, :, H // 2, W // 2]
        # the near splat saturates at ALPHA_MAX; the far one only gets the 1% left over
        T = 1.0 - ALPHA_MAX
        torch.testing.assert_close(c, torch.tensor([0.9 * T, 0.0, ALPHA_MAX], dtype=torch.float64))
        z = (ALPHA_MAX * 0.7 + 0.9 * T * 1.5) / (ALPHA_MAX + 0.9 * T)
        torch.testing.assert_close(out.depth[0, 0, H // 2, W // 2], torch.tensor(z, dtype=torch.float64))


def test_depth_of_fronto_parallel_sheet_equals_its_z():
    z0, n = 0.8, 21
    u = torch.linspace(-0.15, 0.15, n, dtype=torch.float64)
    gx, gy = torch.meshgrid(u, u, indexing="ij")
    means = torch.stack([gx.flatten(), gy.flatten(), torch.full((n * n,), z0, dtype=torch.float64)], dim=-1)
    N = means.shape[0]
    scales = torch.tensor([0.012, 0.012, 1e-4], dtype=torch.float64).expand(N, 3).clone()
    g = Gaussians(means, torch.tensor([1.0, 0, 0, 0], dtype=torch.float64).expand(N, 4).clone(), scales,
                  torch.full((N,), 0.7, dtype=torch.float64), torch.rand(N, 3, dtype=torch.float64))
    cams = Cameras(torch.tensor([[[60.0, 0, 24], [0, 60.0, 20], [0, 0, 1]]], dtype=torch.float64),
                   torch.eye(4, dtype=torch.float64)[None], 48, 40)
    for backend in ("cpu", "reference"):
        out = render(g, cams, backend=backend)
        covered = out.alpha[0, 0] > 0.5
        assert covered.float().mean() > 0.2
        torch.testing.assert_close(out.depth[0, 0][covered], torch.full_like(out.depth[0, 0][covered], z0), rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(out.depth[0, 0][out.alpha[0, 0] > 0], torch.full_like(out.depth[0, 0][out.alpha[0, 0] > 0], z0))


@pytest.mark.parametrize("backend", ["cpu", "reference", "torch_tiles"])
def test_empty_and_all_culled_scenes_give_background(backend):
    cams = cameras(20, 12)
    bg = torch.tensor([0.9, 0.1, 0.4], dtype=torch.float64)
    behind = random_scene(0, n=20)
    behind = behind.replace(means=behind.means * 0.01 + torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64))
    for g in (Gaussians.empty(dtype=torch.float64), behind):
        out = render(g, cams, background=bg, backend=backend)
        assert isinstance(out, RenderOutput)
        assert out.rgb.shape == (3, 3, 12, 20) and out.alpha.shape == out.depth.shape == (3, 1, 12, 20)
        torch.testing.assert_close(out.rgb, bg[None, :, None, None].expand(3, 3, 12, 20))
        assert (out.alpha == 0).all() and (out.depth == 0).all()


def test_cpu_is_deterministic_across_runs_and_thread_counts(monkeypatch):
    g, cams = random_scene(11, n=200, dtype=torch.float32), cameras(64, 48, torch.float32)
    a = run(g, cams, "cpu")
    b = run(g, cams, "cpu")
    monkeypatch.setenv("FASTGHA_NUMBA_THREADS", "1")
    c = run(g, cams, "cpu")
    for other in (b, c):
        for name in ("rgb", "alpha", "depth"):
            assert torch.equal(getattr(a[0], name), getattr(other[0], name))
        for name in a[1]:
            assert torch.equal(a[1][name], other[1][name]), name


def test_camera_batch_shapes_and_size_override():
    g = random_scene(2, n=60)
    cams = cameras(30, 20)
    full = render(g, cams, backend="cpu")
    for single in (cams[1], cams[1:2]):
        out = render(g, single, backend="cpu")
        assert out.rgb.shape == (1, 3, 20, 30)
        torch.testing.assert_close(out.rgb[0], full.rgb[1])
    half = render(g, cams.resize(15, 10), backend="cpu")
    torch.testing.assert_close(render(g, cams, width=15, height=10, backend="cpu").rgb, half.rgb)


def test_bad_arguments_raise_clear_errors():
    g, cams = random_scene(0, n=5), cameras(8, 8)
    with pytest.raises(ValueError, match="backend must be one of"):
        render(g, cams, backend="vulkan")
    with pytest.raises(ValueError, match="background must be"):
        render(g, cams, background=(1.0, 0.0))


def test_no_grad_numba_projection_matches_torch_projection():
    from fastgha_core.render.cpu_backend import project_cpu
    from fastgha_core.render.projection import tile_rects

    g, cams = random_scene(9, n=300), cameras()
    ref = project_gaussians(g.means, g.quats, g.scales, cams.K, cams.w2c, cams.width, cams.height)
    fast, rects = project_cpu(g.means, g.quats, g.scales, cams.K, cams.w2c, cams.width, cams.height)
    assert torch.equal(fast.radii, ref.radii)
    assert torch.equal(rects, tile_rects(ref.means2d, ref.radii, cams.width, cams.height))
    vis = ref.radii > 0
    assert vis.any() and (~vis).any()
    torch.testing.assert_close(fast.depths, ref.depths, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(fast.means2d[vis], ref.means2d[vis], rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(fast.conics[vis], ref.conics[vis], rtol=1e-10, atol=1e-10)
    # and the whole render: no_grad (numba projection) == with grad (torch projection)
    with torch.no_grad():
        a = render(g, cams, backend="cpu")
    b, _ = run(g, cams, "cpu")
    for name in ("rgb", "alpha", "depth"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=1e-10, atol=1e-10)


def test_cpu_float32_gradient_path_matches_reference(monkeypatch):
    """Float32 with gradients takes the fast kernels (raster_forward_fast + raster_backward_fast) and
    matches the dense reference on outputs and on the gradients of every Gaussian parameter."""
    from fastgha_core.render import cpu_kernels

    calls = []
    real = cpu_kernels.raster_backward_fast
    monkeypatch.setattr(cpu_kernels, "raster_backward_fast", lambda *a: calls.append(1) or real(*a))
    g = random_scene(5, n=400, dtype=torch.float32)
    cams = cameras(70, 52, dtype=torch.float32)  # several tiles, partial edge tiles
    fast = run(g, cams, "cpu", (0.2, 0.5, 0.9))
    assert len(calls) == 3  # one backward per camera
    ref = run(g, cams, "reference", (0.2, 0.5, 0.9))  # same float32 inputs: same culling and stop decisions
    out_f, grad_f = fast
    out_r, grad_r = ref
    for name in ("rgb", "alpha", "depth"):
        torch.testing.assert_close(getattr(out_f, name), getattr(out_r, name), rtol=1e-4, atol=2e-5, msg=name)
    for name, gr in grad_r.items():
        scale = gr.abs().max()
        torch.testing.assert_close(grad_f[name] / scale, gr / scale, rtol=0, atol=5e-5, msg=f"grad {name}")


def test_cpu_float32_gradient_path_can_be_turned_off(monkeypatch):
    """FASTGHA_RASTER_FAST=0 gives the float64 kernels, which agree with the fast path."""
    g = random_scene(6, n=200, dtype=torch.float32)
    cams = cameras(dtype=torch.float32)
    fast = run(g, cams, "cpu")
    monkeypatch.setenv("FASTGHA_RASTER_FAST", "0")
    slow = run(g, cams, "cpu")
    assert_same(fast, slow, rtol=2e-4, atol=2e-4)


def _wall_scene() -> tuple[Gaussians, Cameras]:
    """Four layers of near-opaque splats over the left half of a 64x48 image (every pixel there stops)
    and small splats behind, over the whole image: behind the wall only, straddling its edge (inside
    one tile row) and in the open."""
    g = torch.Generator().manual_seed(21)
    xs, ys = torch.meshgrid(torch.linspace(-0.24, -0.005, 40), torch.linspace(-0.2, 0.2, 36), indexing="ij")
    wall = torch.stack([xs.flatten(), ys.flatten(), torch.zeros(xs.numel())], -1)
    wall = torch.cat([wall + torch.tensor([0.0, 0.0, -0.005 * k]) for k in range(4)])
    n_w, n_b = len(wall), 80
    behind = torch.cat([torch.rand(n_b, 2, generator=g) * torch.tensor([0.5, 0.4]) - torch.tensor([0.25, 0.2]), torch.full((n_b, 1), -0.1)], -1)
    means = torch.cat([wall, behind])
    n = len(means)
    scales = torch.cat([torch.full((n_w, 3), 0.01), torch.rand(n_b, 1, generator=g).expand(n_b, 3) * 0.008 + 0.002])
    opac = torch.cat([torch.full((n_w,), 1.0), torch.rand(n_b, generator=g) * 0.8 + 0.2])
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4).contiguous()
    cams = Cameras.look_at((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), fov_deg=30.0, width=64, height=48)
    return Gaussians(means, quats, scales, opac, torch.rand(n, 3, generator=g)), cams


def test_fast_path_skips_rows_only_where_no_pixel_of_the_splat_is_live():
    """The no-gradient kernel skips a tile row when none of the live pixels lies in a splat's box
    columns: pixels that stopped behind an opaque wall, next to live ones in the same row. Same image
    as the dense reference."""
    g, cams = _wall_scene()
    with torch.no_grad():
        fast = render(g, cams, background=(0.3, 0.6, 0.9), backend="cpu")
        ref = render(g, cams, background=(0.3, 0.6, 0.9), backend="reference")
    left, right = ref.alpha[0, 0, 12:36, 14:32], ref.alpha[0, 0, 8:40, 38:56]
    assert (left > 0.995).all()  # the wall stops every pixel there
    assert (right < 0.999).any() and (right > 0.1).any()  # behind splats show in the open half
    for name in ("rgb", "alpha", "depth"):
        torch.testing.assert_close(getattr(fast, name), getattr(ref, name), rtol=1e-4, atol=2e-5, msg=name)


def test_fast_gradients_match_reference_where_pixels_stop(monkeypatch):
    """The float32 backward (whole 16-column rows, the colour behind each splat carried as one
    running sum per pixel) against the dense reference on the wall scene: pixels that stop behind
    near-opaque splats, small splats behind the wall and straddling its edge, and splats clamped at
    ALPHA_MAX (opacity 1)."""
    from fastgha_core.render import cpu_kernels

    g, cams = _wall_scene()
    assert g.means.dtype == cams.K.dtype == torch.float32
    calls = []
    real = cpu_kernels.raster_backward_fast
    monkeypatch.setattr(cpu_kernels, "raster_backward_fast", lambda *a: calls.append(1) or real(*a))
    out_f, grad_f = run(g, cams, "cpu", (0.3, 0.6, 0.9))
    out_r, grad_r = run(g, cams, "reference", (0.3, 0.6, 0.9))
    assert calls == [1]
    assert (out_r.alpha[0, 0, 12:36, 14:32] > 0.995).all()  # the wall stops those pixels
    for name in ("rgb", "alpha", "depth"):
        torch.testing.assert_close(getattr(out_f, name), getattr(out_r, name), rtol=1e-4, atol=2e-5, msg=name)
    n_wall = 4 * 40 * 36
    behind = grad_r["colors"][n_wall:].abs().sum(-1)
    assert (behind == 0).any() and (behind > 0).any()  # some splats behind are hidden, some show
    assert not grad_r["quats"].any() and not grad_f["quats"].any()  # isotropic splats: rotation changes nothing
    for name in ("means", "scales", "opacities", "colors"):
        scale = grad_r[name].abs().max()
        torch.testing.assert_close(grad_f[name] / scale, grad_r[name] / scale, rtol=0, atol=5e-5, msg=f"grad {name}")
    assert torch.equal(grad_f["colors"][n_wall:].abs().sum(-1) == 0, behind == 0)  # the same splats are hidden


def test_gaussians_below_the_alpha_threshold_are_not_projected():
    """``project_cpu(..., opacities)`` skips Gaussians the compositing would skip anyway: they get no
    radius and no tiles, the others are projected as before, and the image is bit-identical to the
    one rendered without those Gaussians."""
    from fastgha_core.render.cpu_backend import project_cpu

    g, cams = random_scene(13, n=300, dtype=torch.float32), cameras(64, 48, torch.float32)
    faint = torch.arange(len(g)) % 3 == 0
    g = g.replace(opacities=torch.where(faint, torch.rand(len(g)) * ALPHA_MIN * 0.999, g.opacities))
    a, ra = project_cpu(g.means, g.quats, g.scales, cams.K, cams.w2c, cams.width, cams.height, g.opacities)
    b, rb = project_cpu(g.means, g.quats, g.scales, cams.K, cams.w2c, cams.width, cams.height)
    assert (a.radii[:, faint] == 0).all() and (ra[:, faint] == 0).all() and (b.radii[:, faint] > 0).any()
    assert torch.equal(a.radii[:, ~faint], b.radii[:, ~faint]) and torch.equal(ra[:, ~faint], rb[:, ~faint])
    assert torch.equal(a.means2d[:, ~faint], b.means2d[:, ~faint]) and torch.equal(a.conics[:, ~faint], b.conics[:, ~faint])
    with torch.no_grad():
        with_faint = render(g, cams, background=(1.0, 1.0, 1.0), backend="cpu")
        without = render(g[~faint], cams, background=(1.0, 1.0, 1.0), backend="cpu")
    for name in ("rgb", "alpha", "depth"):
        assert torch.equal(getattr(with_faint, name), getattr(without, name)), name
