"""LPIPS-VGG (Zhang et al. 2018), the standard metric: VGG16 features at relu1_2 .. relu5_3 of the
input scaled to [-1, 1] and shifted/scaled by LPIPS' ScalingLayer, unit-normalised over channels,
squared differences weighted by learned 1x1 linear heads, averaged over space, summed over layers.

Needs two user-given files: the torchvision VGG16 weights and the LPIPS linear heads
(``lpips/weights/v0.1/vgg.pth`` of the ``lpips`` package: ``lin0.model.1.weight`` .. ``lin4``).
Without them LPIPS is unavailable (reported as null), never approximated.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor, nn

from .vgg import LPIPS_LAYERS, VGG16Features, load_state_dict_file, load_vgg16

__all__ = ["LPIPS", "load_lpips"]

_CHANNELS = (64, 128, 256, 512, 512)
# LPIPS ScalingLayer constants (applied to inputs in [-1, 1])
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)


class LPIPS(nn.Module):
    """``forward(pred [N,3,H,W], target [N,3,H,W]) -> [N]`` LPIPS distance, images in [0, 1]."""

    def __init__(self, vgg: VGG16Features) -> None:
        super().__init__()
        self.vgg = vgg
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, kernel_size=1, bias=False) for c in _CHANNELS)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> "LPIPS":
        return super().train(False)

    def _feats(self, x: Tensor) -> list[Tensor]:
        x = (x * 2 - 1 - self.shift) / self.scale
        return self.vgg(x, LPIPS_LAYERS, normalize=False)

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        if pred.shape != target.shape or pred.ndim != 4 or pred.shape[1] != 3:
            raise ValueError(f"LPIPS expects two images [N, 3, H, W] of one shape, got {list(pred.shape)} and {list(target.shape)}")
        total = pred.new_zeros(pred.shape[0])
        for f0, f1, lin in zip(self._feats(pred), self._feats(target), self.lins):
            n0 = f0 / (f0.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            n1 = f1 / (f1.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + lin((n0 - n1) ** 2).mean(dim=(1, 2, 3))
        return total


def load_lpips(vgg_path: str | Path, lpips_path: str | Path, device: str | torch.device = "cpu") -> LPIPS:
    """LPIPS-VGG from a torchvision VGG16 file and the LPIPS linear-head file."""
    model = LPIPS(load_vgg16(vgg_path))
    sd = load_state_dict_file(lpips_path)
    heads = {}
    for i, c in enumerate(_CHANNELS):
        for name in (f"lin{i}.model.1.weight", f"lins.{i}.model.1.weight", f"lin{i}.weight", f"lins.{i}.weight"):
            if name in sd:
                heads[f"lins.{i}.weight"] = sd[name].float().reshape(1, c, 1, 1)
                break
        else:
            raise ValueError(f"{lpips_path}: no LPIPS head for layer {i}: expected 'lin{i}.model.1.weight' [1, {c}, 1, 1]")
    model.lins.load_state_dict({k.split(".", 1)[1]: v for k, v in heads.items()}, strict=True)
    return model.to(device)
