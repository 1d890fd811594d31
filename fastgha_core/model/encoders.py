"""Per-view image encoders (paper §3.2): DINOv3 semantic features and SD-VAE colour latents.

Both take images in [0, 1] and normalise them by hand (the ``transformers`` image processors need
torchvision, which this project does not install):

- ``SemanticEncoder``: a ``transformers.DINOv3ViTModel``; the patch tokens of several blocks (CLS and
  register tokens dropped, final LayerNorm applied as in DINOv3's ``get_intermediate_layers``) are
  projected by 1x1 convs, concatenated, resized from H/p to H/8 and fused by 3x3 convs into
  ``F_dino [N, C_d, H/8, W/8]``.
- ``ColourEncoder``: the ``diffusers`` AutoencoderKL encoder + quant conv; ``F_enc`` is the latent
  mean times the VAE scaling factor, ``[N, 4, H/8, W/8]``.

Pretrained weights come from local Hugging Face-format folders (``load_pretrained``); nothing is
fetched over the network. A frozen encoder has ``requires_grad=False``, stays in eval mode and runs
under ``torch.no_grad``.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..config import DinoConfig, VAEConfig

__all__ = ["SemanticEncoder", "ColourEncoder", "IMAGENET_MEAN", "IMAGENET_STD"]

log = logging.getLogger(__name__)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _check_images(images: Tensor, who: str) -> None:
    if images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"{who}: images must have shape [N, 3, H, W], got {list(images.shape)}")


def _check_folder(folder: str | Path, what: str, option: str) -> Path:
    folder = Path(folder)
    if not (folder / "config.json").is_file():
        raise ValueError(
            f"{what} weights folder {str(folder)!r} (from {option}) must be a local Hugging Face-format folder "
            "with config.json and *.safetensors, written by save_pretrained(); it does not exist or has no config.json"
        )
    return folder


class _FrozenMixin(nn.Module):
    """Keeps a frozen module in eval mode and without gradients."""

    frozen: bool = False

    def freeze(self) -> None:
        self.frozen = True
        for p in self.parameters():
            p.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True):
        return super().train(mode and not self.frozen)


class SemanticEncoder(nn.Module):
    """DINOv3 ViT + multi-layer fusion: images ``[N, 3, H, W]`` in [0, 1] -> ``F_dino [N, C_d, H/8, W/8]``.

    Freezing affects the ViT only; the fusion convs are new layers and always train.
    ``cfg`` is shared with the model's ``FastGHAConfig`` so that loading weights records ``frozen``.
    """

    def __init__(self, cfg: DinoConfig):
        super().__init__()
        from transformers import DINOv3ViTModel

        self.cfg = cfg
        self.vit = DINOv3ViTModel(cfg.to_hf())
        c, d = cfg.out_channels, cfg.hidden_size
        self.proj = nn.ModuleList(nn.Conv2d(d, c, 1) for _ in cfg.feature_layers)
        self.fuse = nn.Sequential(
            nn.Conv2d(c * len(cfg.feature_layers), c, 3, padding=1), nn.GELU(), nn.Conv2d(c, c, 3, padding=1)
        )
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        if cfg.frozen:
            self.freeze_backbone()

    def freeze_backbone(self) -> None:
        """Freeze the ViT (the fusion convs always train)."""
        self.cfg.frozen = True
        for p in self.vit.parameters():
            p.requires_grad_(False)
        self.vit.eval()

    def train(self, mode: bool = True):
        super().train(mode)
        if self.cfg.frozen:
            self.vit.eval()
        return self

    def load_pretrained(self, folder: str | Path, option: str = "dino_weights") -> None:
        """Load a local ``DINOv3ViTModel`` folder into the ViT and freeze it."""
        from transformers import DINOv3ViTConfig, DINOv3ViTModel

        folder = _check_folder(folder, "DINOv3", option)
        try:
            hf = DINOv3ViTConfig.from_pretrained(str(folder), local_files_only=True)
        except Exception as e:  # noqa: BLE001 - transformers raises many types
            raise ValueError(f"DINOv3 weights folder {str(folder)!r} ({option}): config.json does not load: {e}") from None
        want = self.cfg
        pairs = {
            "hidden_size": (hf.hidden_size, want.hidden_size),
            "num_hidden_layers": (hf.num_hidden_layers, want.num_layers),
            "num_attention_heads": (hf.num_attention_heads, want.num_heads),
            "intermediate_size": (hf.intermediate_size, want.intermediate_size),
            "patch_size": (hf.patch_size, want.patch_size),
            "num_register_tokens": (hf.num_register_tokens, want.num_register_tokens),
            "use_gated_mlp": (hf.use_gated_mlp, want.use_gated_mlp),
        }
        bad = {k: v for k, v in pairs.items() if v[0] != v[1]}
        if bad:
            desc = ", ".join(f"{k}={a} (model expects {b})" for k, (a, b) in bad.items())
            raise ValueError(f"DINOv3 weights folder {str(folder)!r} ({option}) does not fit this model: {desc}")
        try:
            pre = DINOv3ViTModel.from_pretrained(str(folder), local_files_only=True)
        except Exception as e:  # noqa: BLE001
            raise ValueError(f"DINOv3 weights folder {str(folder)!r} ({option}) does not load: {e}") from None
        missing, unexpected = self.vit.load_state_dict(pre.state_dict(), strict=False)
        if missing:
            raise ValueError(f"DINOv3 weights folder {str(folder)!r} ({option}) lacks weights {missing[:5]}")
        if unexpected:
            log.warning("DINOv3 weights: ignoring unexpected keys %s", unexpected[:5])
        self.freeze_backbone()

    def _tokens(self, x: Tensor) -> list[Tensor]:
        """Patch-token maps ``[N, D, H/p, W/p]`` of the configured blocks."""
        n, _, h, w = x.shape
        p = self.cfg.patch_size
        out = self.vit(pixel_values=x, output_hidden_states=True)
        prefix = 1 + self.cfg.num_register_tokens  # CLS + registers
        maps = []
        for i in self.cfg.feature_layers:
            t = self.vit.norm(out.hidden_states[i][:, prefix:])  # [N, h/p * w/p, D]
            maps.append(t.transpose(1, 2).reshape(n, -1, h // p, w // p))  # [N, D, h/p, w/p]
        return maps

    def forward(self, images: Tensor) -> Tensor:
        _check_images(images, "SemanticEncoder")
        n, _, h, w = images.shape
        if h % self.cfg.patch_size or w % self.cfg.patch_size:
            raise ValueError(f"SemanticEncoder: image size {h}x{w} must be divisible by the patch size {self.cfg.patch_size}")
        x = (images - self.mean) / self.std
        if self.cfg.frozen:
            with torch.no_grad():
                maps = self._tokens(x)
        else:
            maps = self._tokens(x)
        f = torch.cat([proj(m) for proj, m in zip(self.proj, maps)], dim=1)  # [N, L*C_d, h/p, w/p]
        if f.shape[-2:] != (h // 8, w // 8):
            f = F.interpolate(f, size=(h // 8, w // 8), mode="bilinear", align_corners=False)
        return self.fuse(f)  # [N, C_d, H/8, W/8]


class ColourEncoder(_FrozenMixin):
    """SD-VAE encoder: images ``[N, 3, H, W]`` in [0, 1] -> scaled latent mean ``[N, 4, H/8, W/8]``."""

    def __init__(self, cfg: VAEConfig):
        super().__init__()
        from diffusers.models.autoencoders.vae import Encoder

        self.cfg = cfg
        n = len(cfg.block_out_channels)
        self.encoder = Encoder(
            in_channels=3,
            out_channels=cfg.latent_channels,
            down_block_types=("DownEncoderBlock2D",) * n,
            block_out_channels=tuple(cfg.block_out_channels),
            layers_per_block=cfg.layers_per_block,
            norm_num_groups=cfg.norm_num_groups,
            double_z=True,
        )
        self.quant_conv = nn.Conv2d(2 * cfg.latent_channels, 2 * cfg.latent_channels, 1)
        if cfg.frozen:
            self.freeze()

    def freeze(self) -> None:
        self.cfg.frozen = True
        super().freeze()

    def load_pretrained(self, folder: str | Path, option: str = "vae_weights") -> dict[str, Tensor]:
        """Load a local ``AutoencoderKL`` folder into the encoder, freeze it, and return the VAE
        decoder's state dict (for the Gaussian decoder's initialisation)."""
        from diffusers import AutoencoderKL

        folder = _check_folder(folder, "VAE", option)
        try:
            raw = json.loads((folder / "config.json").read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"VAE weights folder {str(folder)!r} ({option}): config.json does not parse: {e}") from None
        want = self.cfg
        pairs = {
            "block_out_channels": (list(raw.get("block_out_channels", [])), list(want.block_out_channels)),
            "layers_per_block": (raw.get("layers_per_block"), want.layers_per_block),
            "latent_channels": (raw.get("latent_channels"), want.latent_channels),
            "norm_num_groups": (raw.get("norm_num_groups"), want.norm_num_groups),
        }
        bad = {k: v for k, v in pairs.items() if v[0] != v[1]}
        if bad:
            desc = ", ".join(f"{k}={a} (model expects {b})" for k, (a, b) in bad.items())
            raise ValueError(f"VAE weights folder {str(folder)!r} ({option}) does not fit this model: {desc}")
        try:
            vae = AutoencoderKL.from_pretrained(str(folder), local_files_only=True)
        except Exception as e:  # noqa: BLE001
            raise ValueError(f"VAE weights folder {str(folder)!r} ({option}) does not load: {e}") from None
        if vae.quant_conv is None:
            raise ValueError(f"VAE weights folder {str(folder)!r} ({option}): use_quant_conv=False is not supported")
        self.encoder.load_state_dict(vae.encoder.state_dict())
        self.quant_conv.load_state_dict(vae.quant_conv.state_dict())
        self.cfg.scaling_factor = float(vae.config.scaling_factor)
        self.freeze()
        return vae.decoder.state_dict()

    def _encode(self, x: Tensor) -> Tensor:
        moments = self.quant_conv(self.encoder(x))  # [N, 2*4, H/8, W/8] = mean ++ logvar
        return moments[:, : self.cfg.latent_channels] * self.cfg.scaling_factor

    def forward(self, images: Tensor) -> Tensor:
        _check_images(images, "ColourEncoder")
        x = images * 2.0 - 1.0  # [0, 1] -> [-1, 1]
        if self.cfg.frozen:
            with torch.no_grad():
                return self._encode(x)
        return self._encode(x)
