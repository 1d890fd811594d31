"""Multi-view transformer (paper §3.2, following GRM): pre-norm self-attention over the tokens of all
views jointly.

Input tokens ``[B, V, C_in, h, w]`` (``C_in = C_d + C_e + 6``, ``h = H/8``) are flattened to
``[B, V*h*w, C_in]``, projected to the hidden width, passed through ``num_layers`` pre-norm blocks
(``x + attn(LN(x))``, ``x + mlp(LN(x))``) and a final LayerNorm, and returned as maps
``[B, V, D, h, w]``. Nothing depends on V, so any number of views works. Positions are carried by
the Plücker channels of the tokens (no learned position embedding).
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn

from ..config import TransformerConfig

__all__ = ["MultiViewTransformer", "SelfAttention", "TransformerBlock"]


class SelfAttention(nn.Module):
    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"attention width {dim} must be divisible by num_heads {num_heads}")
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor) -> Tensor:  # [B, T, D] -> [B, T, D]
        b, t, d = x.shape
        nh = self.num_heads
        q, k, v = self.qkv(x).view(b, t, 3, nh, d // nh).permute(2, 0, 3, 1, 4)  # 3 x (B, nh, T, hs)
        y = F.scaled_dot_product_attention(q, k, v)  # (B, nh, T, hs)
        return self.proj(y.transpose(1, 2).reshape(b, t, d))


class TransformerBlock(nn.Module):
    def __init__(self, dim: int, num_heads: int, mlp_ratio: float):
        super().__init__()
        hidden = int(dim * mlp_ratio)
        self.norm1 = nn.LayerNorm(dim)
        self.attn = SelfAttention(dim, num_heads)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim))

    def forward(self, x: Tensor) -> Tensor:  # [B, T, D]
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


class MultiViewTransformer(nn.Module):
    """Tokens ``[B, V, C_in, h, w]`` -> ``[B, V, D, h, w]``."""

    def __init__(self, in_channels: int, cfg: TransformerConfig):
        super().__init__()
        self.cfg = cfg
        d = cfg.hidden_size
        self.embed = nn.Linear(in_channels, d)
        self.blocks = nn.ModuleList(TransformerBlock(d, cfg.num_heads, cfg.mlp_ratio) for _ in range(cfg.num_layers))
        self.norm = nn.LayerNorm(d)

    def forward(self, tokens: Tensor) -> Tensor:
        if tokens.ndim != 5 or tokens.shape[2] != self.embed.in_features:
            raise ValueError(
                f"MultiViewTransformer: tokens must have shape [B, V, {self.embed.in_features}, h, w], got {list(tokens.shape)}"
            )
        b, v, c, h, w = tokens.shape
        x = tokens.permute(0, 1, 3, 4, 2).reshape(b, v * h * w, c)  # [B, V*h*w, C_in]
        x = self.embed(x)  # [B, T, D]
        for blk in self.blocks:
            x = blk(x)
        x = self.norm(x)
        return x.view(b, v, h, w, -1).permute(0, 1, 4, 2, 3)  # [B, V, D, h, w]
