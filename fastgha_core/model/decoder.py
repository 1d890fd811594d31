"""Gaussian decoder (paper §3.2 and appendix): the SD VAE decoder, modified.

- ``conv_in`` takes the transformer width (512 in the paper) instead of the 4 latent channels;
- the mid-block attention is *cross-view*: the tokens of all V views of a sample attend to each
  other jointly (GroupNorm stays per view, as in the pretrained layer);
- ``conv_out`` emits the Gaussian channels (44 = depth 1 + rgb 3 + quat 4 + scale 3 + opacity 1 +
  feature 32) instead of RGB.

The module is a ``diffusers`` ``Decoder`` (so pretrained SD-VAE decoder weights load by name); only
its forward is ours. ``load_vae_decoder`` copies a pretrained decoder's weights in, and copies
``conv_in``/``conv_out`` into the slices where shapes allow (latent input channels -> the first
input channels; RGB output -> the rgb channels of the Gaussian maps). The whole decoder is trained.
"""

from __future__ import annotations

import logging

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..config import DecoderConfig
from .gaussian_head import GaussianLayout

__all__ = ["GaussianDecoder", "cross_view_attention"]

log = logging.getLogger(__name__)


def cross_view_attention(attn: nn.Module, x: Tensor, num_views: int) -> Tensor:
    """A ``diffusers`` spatial self-attention layer applied across views.

    Args:
        attn: ``diffusers.models.attention_processor.Attention`` (with group_norm, to_q/k/v, to_out).
        x: ``[B*V, C, h, w]`` feature maps, views of one sample adjacent.
        num_views: V.
    Returns:
        ``[B*V, C, h, w]``: residual + attention over all ``V*h*w`` tokens of each sample.
        With ``num_views=1`` this equals ``attn(x)``.
    """
    bv, c, h, w = x.shape
    if bv % num_views:
        raise ValueError(f"cross_view_attention: batch {bv} is not a multiple of num_views {num_views}")
    b, v = bv // num_views, num_views
    residual = x
    if attn.group_norm is not None:
        x = attn.group_norm(x)  # per view, as pretrained
    t = x.view(b, v, c, h * w).permute(0, 1, 3, 2).reshape(b, v * h * w, c)  # [B, V*h*w, C]
    nh = attn.heads
    q = attn.to_q(t).view(b, -1, nh, c // nh).transpose(1, 2)  # (B, nh, T, hs)
    k = attn.to_k(t).view(b, -1, nh, c // nh).transpose(1, 2)
    val = attn.to_v(t).view(b, -1, nh, c // nh).transpose(1, 2)
    y = F.scaled_dot_product_attention(q, k, val, scale=attn.scale)  # (B, nh, T, hs)
    y = y.transpose(1, 2).reshape(b, v * h * w, c)
    y = attn.to_out[1](attn.to_out[0](y))  # linear + dropout
    y = y.view(b, v, h * w, c).permute(0, 1, 3, 2).reshape(bv, c, h, w)
    if attn.residual_connection:
        y = y + residual
    return y / attn.rescale_output_factor


class GaussianDecoder(nn.Module):
    """Transformer maps ``[B, V, D, h, w]`` -> raw Gaussian maps ``[B, V, 12+F, 8h, 8w]``."""

    def __init__(self, in_channels: int, layout: GaussianLayout, cfg: DecoderConfig):
        super().__init__()
        from diffusers.models.autoencoders.vae import Decoder

        self.cfg = cfg
        self.layout = layout
        n = len(cfg.block_out_channels)
        self.decoder = Decoder(
            in_channels=in_channels,
            out_channels=layout.channels,
            up_block_types=("UpDecoderBlock2D",) * n,
            block_out_channels=tuple(cfg.block_out_channels),
            layers_per_block=cfg.layers_per_block,
            norm_num_groups=cfg.norm_num_groups,
            mid_block_add_attention=True,
        )

    def forward(self, x: Tensor) -> Tensor:
        if x.ndim != 5 or x.shape[2] != self.decoder.conv_in.in_channels:
            raise ValueError(
                f"GaussianDecoder: input must have shape [B, V, {self.decoder.conv_in.in_channels}, h, w], got {list(x.shape)}"
            )
        b, v = x.shape[:2]
        dec = self.decoder
        y = dec.conv_in(x.flatten(0, 1))  # [B*V, C, h, w]
        mid = dec.mid_block
        y = mid.resnets[0](y, None)
        for attn, resnet in zip(mid.attentions, mid.resnets[1:]):
            if attn is not None:
                y = cross_view_attention(attn, y, v if self.cfg.cross_view_attention else 1)
            y = resnet(y, None)
        for up in dec.up_blocks:
            y = up(y, None)
        y = dec.conv_out(dec.conv_act(dec.conv_norm_out(y)))  # [B*V, 12+F, H, W]
        return y.view(b, v, *y.shape[1:])

    @torch.no_grad()
    def load_vae_decoder(self, state: dict[str, Tensor]) -> None:
        """Initialise from a pretrained SD-VAE decoder state dict (keys of ``AutoencoderKL.decoder``)."""
        own = self.decoder.state_dict()
        loaded, sliced, skipped = 0, [], []
        for key, src in state.items():
            if key not in own:
                skipped.append(key)
                continue
            dst = own[key]
            if dst.shape == src.shape:
                dst.copy_(src)
                loaded += 1
            elif key == "conv_in.weight" and dst.shape[0] == src.shape[0] and dst.shape[1] >= src.shape[1]:
                dst[:, : src.shape[1]].copy_(src)  # latent channels -> first input channels
                sliced.append(key)
            elif key.startswith("conv_out.") and src.shape[0] == 3:
                dst[self.layout.rgb].copy_(src)  # RGB head -> the rgb channels
                sliced.append(key)
            else:
                skipped.append(key)
        if skipped:
            raise ValueError(f"VAE decoder weights do not fit the Gaussian decoder: {skipped[:5]}")
        self.decoder.load_state_dict(own)
        log.info("Gaussian decoder: %d tensors copied from the VAE decoder, %s copied into slices", loaded, sliced)
