"""Metrics (PSNR, SSIM, LPIPS) and the VGG16 loader against hand-computed values."""

from __future__ import annotations

import math

import numpy as np

import pytest
import torch
import torch.nn.functional as F

from fastgha_core.train.lpips import LPIPS, load_lpips
from fastgha_core.train.metrics import psnr, ssim
from fastgha_core.train.vgg import VGG16Features, load_vgg16


def test_psnr_known_noise_level():
    target = torch.full((2, 3, 16, 16), 0.5)
    sign = torch.where(torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(0)) > 0.5, 1.0, -1.0)
    pred = target + 0.1 * sign  # |error| = 0.1 everywhere -> MSE 0.01 -> 20 dB
    torch.testing.assert_close(psnr(pred, target), torch.full((2,), 20.0), atol=1e-4, rtol=0)
    pred2 = target.clone()
    pred2[1] += 0.05 * sign[1]  # MSE 0.0025 -> 26.0206 dB
    assert psnr(pred2, target)[1].item() == pytest.approx(10 * math.log10(1 / 0.0025), abs=1e-4)
    assert psnr(pred2, target)[0].item() > 100  # identical


def test_ssim_identical_is_one_and_constants_match_formula():
    img = torch.rand(2, 3, 24, 24, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(ssim(img, img), torch.ones(2), atol=1e-5, rtol=0)
    # constant images a, b: variances are 0, so SSIM = (2ab + C1) / (a² + b² + C1)
    a, b = 0.3, 0.7
    c1 = 0.01**2
    expected = (2 * a * b + c1) / (a * a + b * b + c1)
    got = ssim(torch.full((1, 3, 16, 16), a), torch.full((1, 3, 16, 16), b))
    assert got.item() == pytest.approx(expected, abs=1e-5)


def _ssim_reference(x, y, win=11, sigma=1.5):
    """Plain SSIM (Wang et al. 2004), Gaussian window, valid positions only."""
    g = torch.exp(-((torch.arange(win, dtype=torch.float64) - win // 2) ** 2) / (2 * sigma**2))
    g = g / g.sum()
    k = (g[:, None] * g[None, :]).expand(x.shape[1], 1, win, win)
    x, y = x.double(), y.double()
    f = lambda t: F.conv2d(t, k, groups=x.shape[1])  # noqa: E731
    mx, my = f(x), f(y)
    sxx, syy, sxy = f(x * x) - mx**2, f(y * y) - my**2, f(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    m = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))
    return m.flatten(1).mean(1)


def test_ssim_matches_plain_reference():
    gen = torch.Generator().manual_seed(2)
    x = torch.rand(3, 3, 20, 24, generator=gen)
    y = (x + 0.2 * torch.randn(3, 3, 20, 24, generator=gen)).clamp(0, 1)
    torch.testing.assert_close(ssim(x, y).double(), _ssim_reference(x, y), atol=1e-4, rtol=0)


def _fake_torchvision_vgg16(seed=0):
    """A state dict with torchvision's vgg16 names and shapes (random values)."""
    ref = VGG16Features()
    gen = torch.Generator().manual_seed(seed)
    sd = {k: torch.randn(v.shape, generator=gen) * 0.05 for k, v in ref.state_dict().items()}
    sd["classifier.0.weight"] = torch.randn(8, 8, generator=gen)  # ignored part of the full model
    return sd


@pytest.mark.parametrize("fmt", ["pth", "safetensors", "pth-features-only"])
def test_vgg_loader_maps_state_dict(tmp_path, fmt):
    sd = _fake_torchvision_vgg16()
    if fmt == "safetensors":
        from safetensors.torch import save_file

        path = tmp_path / "vgg16.safetensors"
        save_file(sd, str(path))
    elif fmt == "pth":
        path = tmp_path / "vgg16.pth"
        torch.save(sd, path)
    else:  # a DataParallel-wrapped features-only dict: "module.0.weight"
        path = tmp_path / "vgg16_features.pth"
        torch.save({"module." + k[len("features."):]: v for k, v in sd.items() if k.startswith("features.")}, path)
    net = load_vgg16(path)
    for idx in (0, 2, 5, 28):
        torch.testing.assert_close(net.features[idx].weight, sd[f"features.{idx}.weight"])
        torch.testing.assert_close(net.features[idx].bias, sd[f"features.{idx}.bias"])
    # the relu1_2 tap equals conv-relu-conv-relu written out by hand on normalised input
    x = torch.rand(1, 3, 8, 8)
    xn = (x - torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)) / torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    h = F.relu(F.conv2d(xn, sd["features.0.weight"], sd["features.0.bias"], padding=1))
    h = F.relu(F.conv2d(h, sd["features.2.weight"], sd["features.2.bias"], padding=1))
    torch.testing.assert_close(net(x, layers=(3,))[0], h, atol=1e-5, rtol=1e-5)


def test_vgg_loader_rejects_wrong_file(tmp_path):
    path = tmp_path / "bad.pth"
    torch.save({"features.0.weight": torch.zeros(64, 3, 3, 3)}, path)
    with pytest.raises(ValueError, match="missing"):
        load_vgg16(path)
    with pytest.raises(FileNotFoundError):
        load_vgg16(tmp_path / "nope.pth")


def test_lpips_matches_plain_formula(tmp_path):
    sd = _fake_torchvision_vgg16(seed=3)
    torch.save(sd, tmp_path / "vgg16.pth")
    gen = torch.Generator().manual_seed(4)
    heads = {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1, generator=gen) for i, c in enumerate((64, 128, 256, 512, 512))}
    torch.save(heads, tmp_path / "lpips_vgg.pth")
    model = load_lpips(tmp_path / "vgg16.pth", tmp_path / "lpips_vgg.pth")
    assert isinstance(model, LPIPS)
    x = torch.rand(2, 3, 32, 32, generator=gen)
    y = torch.rand(2, 3, 32, 32, generator=gen)
    torch.testing.assert_close(model(x, x), torch.zeros(2), atol=1e-7, rtol=0)
    # plain formula, written out layer by layer
    shift = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)

    def feats(t):
        h = (t * 2 - 1 - shift) / scale
        out = []
        for i, layer in enumerate(model.vgg.features):
            h = layer(h)
            if i in (3, 8, 15, 22, 29):
                out.append(h)
        return out

    expected = torch.zeros(2)
    for i, (a, b) in enumerate(zip(feats(x), feats(y))):
        a = a / (a.norm(dim=1, keepdim=True) + 1e-10)
        b = b / (b.norm(dim=1, keepdim=True) + 1e-10)
        w = heads[f"lin{i}.model.1.weight"].view(1, -1, 1, 1)
        expected += ((a - b) ** 2 * w).sum(1).mean(dim=(1, 2))
    torch.testing.assert_close(model(x, y), expected, atol=1e-5, rtol=1e-4)


def test_face_metrics_on_a_real_photo_identical_and_shifted():
    from fastgha_core.train.faces import load_face_metrics

    faces = load_face_metrics()
    if faces is None:
        pytest.skip("needs the 'faces' extra (dlib-bin, face-recognition-models)")
    import matplotlib.cbook
    from PIL import Image

    img = np.asarray(Image.open(matplotlib.cbook.get_sample_data("grace_hopper.jpg")).convert("RGB").resize((256, 320)))
    t = torch.from_numpy(img).permute(2, 0, 1).float() / 255.0  # [3, H, W], a non-contiguous view once converted back
    csim, akd = faces.compare(t, t)
    assert csim == pytest.approx(1.0, abs=1e-6) and akd == pytest.approx(0.0, abs=1e-9)
    shifted = torch.roll(t, shifts=6, dims=2)  # the face moves 6 px right
    csim2, akd2 = faces.compare(shifted, t)
    assert 3.0 < akd2 < 9.0 and csim2 > 0.8
