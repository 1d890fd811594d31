"""VGG16 ``features`` network (the perceptual loss and LPIPS backbone), defined here so that no
torchvision is needed.

The module layout is exactly torchvision's ``vgg16().features`` (indices 0..30), so a torchvision
``vgg16`` state dict (``.pth``, e.g. ``vgg16-397923af.pth``) or a safetensors file with the same
names loads into it. Weights always come from a file the user gives; nothing is downloaded.

Inputs are images in [0, 1]; :meth:`VGG16Features.normalize` applies the ImageNet mean/std that the
torchvision weights expect.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Sequence

import torch
from torch import Tensor, nn

__all__ = ["VGG16Features", "load_vgg16", "VGG16_CONFIG", "LPIPS_LAYERS", "load_state_dict_file"]

log = logging.getLogger(__name__)

# torchvision's vgg16 configuration "D": channel counts, "M" = 2x2 max pool.
VGG16_CONFIG: tuple[int | str, ...] = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M")

# indices in ``features`` of relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 (the LPIPS / perceptual taps)
LPIPS_LAYERS: tuple[int, ...] = (3, 8, 15, 22, 29)

_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)


def _make_features() -> nn.Sequential:
    layers: list[nn.Module] = []
    c_in = 3
    for v in VGG16_CONFIG:
        if v == "M":
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
        else:
            layers.append(nn.Conv2d(c_in, int(v), kernel_size=3, padding=1))
            layers.append(nn.ReLU(inplace=False))
            c_in = int(v)
    return nn.Sequential(*layers)


class VGG16Features(nn.Module):
    """torchvision-compatible ``vgg16().features``; frozen, eval mode.

    ``forward(x [N, 3, H, W] in [0, 1], layers) -> list of [N, C_l, H_l, W_l]`` feature maps taken
    after the given ``features`` indices (default: the five LPIPS ReLU taps).
    """

    def __init__(self) -> None:
        super().__init__()
        self.features = _make_features()
        self.register_buffer("mean", torch.tensor(_IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(_IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> "VGG16Features":  # always eval: no dropout/bn, frozen
        return super().train(False)

    def normalize(self, x: Tensor) -> Tensor:  # [N, 3, H, W] in [0, 1] -> ImageNet-normalised
        return (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)

    def forward(self, x: Tensor, layers: Sequence[int] = LPIPS_LAYERS, normalize: bool = True) -> list[Tensor]:
        if x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(f"VGG16Features expects images [N, 3, H, W], got {list(x.shape)}")
        wanted = sorted(set(int(i) for i in layers))
        if not wanted or wanted[0] < 0 or wanted[-1] >= len(self.features):
            raise ValueError(f"layer indices must lie in [0, {len(self.features) - 1}], got {list(layers)}")
        h = self.normalize(x) if normalize else x
        out: dict[int, Tensor] = {}
        for i, layer in enumerate(self.features):
            h = layer(h)
            if i in wanted:
                out[i] = h
            if i >= wanted[-1]:
                break
        return [out[int(i)] for i in layers]


def load_state_dict_file(path: str | Path) -> dict[str, Tensor]:
    """Read a ``.safetensors`` file or a torch pickle (``.pth``/``.pt``, loaded with ``weights_only``)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"weights file not found: {path}")
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        return load_file(str(path))
    obj = torch.load(str(path), map_location="cpu", weights_only=True)
    if isinstance(obj, dict) and "state_dict" in obj and isinstance(obj["state_dict"], dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict):
        raise ValueError(f"{path}: expected a state dict (name -> tensor), got {type(obj).__name__}")
    return {k: v for k, v in obj.items() if isinstance(v, Tensor)}


def _features_state(sd: dict[str, Tensor]) -> dict[str, Tensor]:
    """Map names of a torchvision vgg16 state dict (or its ``features`` part, with or without
    ``module.``/``vgg.``/``net.`` prefixes) onto ``features.<i>.<weight|bias>``."""
    out: dict[str, Tensor] = {}
    for k, v in sd.items():
        parts = k.split(".")
        if "classifier" in parts or "avgpool" in parts:
            continue
        # strip wrapper prefixes until we reach "<int>.<weight|bias>" optionally preceded by "features"
        while parts and not parts[0].isdigit() and parts[0] != "features":
            parts = parts[1:]
        if parts and parts[0] == "features":
            parts = parts[1:]
        if len(parts) == 2 and parts[0].isdigit() and parts[1] in ("weight", "bias"):
            out[f"features.{parts[0]}.{parts[1]}"] = v
    return out


def load_vgg16(path: str | Path, device: str | torch.device = "cpu") -> VGG16Features:
    """Build :class:`VGG16Features` and load the convolution weights from ``path``.

    Accepts a full torchvision ``vgg16`` state dict (``features.*`` and ``classifier.*``; the
    classifier is ignored) or a features-only one, as ``.pth`` or ``.safetensors``. Raises
    ``ValueError`` naming the missing or mis-shaped tensors.
    """
    net = VGG16Features()
    sd = _features_state(load_state_dict_file(path))
    expected = net.state_dict()
    missing = [k for k in expected if k not in sd]
    if missing:
        raise ValueError(
            f"{path}: not a VGG16 state dict: missing {len(missing)} of {len(expected)} tensors "
            f"(first: {missing[:3]}); expected torchvision names like 'features.0.weight'"
        )
    bad = [f"{k} {list(sd[k].shape)} != {list(v.shape)}" for k, v in expected.items() if sd[k].shape != v.shape]
    if bad:
        raise ValueError(f"{path}: VGG16 tensor shapes do not match: {bad[:3]}")
    net.load_state_dict({k: sd[k].float() for k in expected}, strict=True)
    log.info("loaded VGG16 features from %s", path)
    return net.to(device)
