"""Deformation MLP D (paper §3.2): per-Gaussian offsets for a target expression.

``D([f, PE(x), z]) -> (dxyz, drgb)`` with ``f [N, F]`` the per-Gaussian feature, ``PE`` a sinusoidal
encoding of the canonical centre and ``z`` the expression code. ``num_layers`` hidden layers
(Linear + LeakyReLU), then a zero-initialised output layer, so the MLP is the identity deformation
at initialisation.

Real-time split: the first layer is ``W_f f + W_pe PE(x) + b + W_z z``. The first three terms do not
depend on the expression, so ``precompute(features, xyz) -> partial [N, H]`` runs once per avatar and
``forward_split(partial, expr)`` adds ``W_z z`` (one small mat-vec) per frame. ``forward`` is the plain
reference path; a test proves both agree on outputs and gradients.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..config import DeformConfig

__all__ = ["DeformationMLP", "positional_encoding"]


def positional_encoding(xyz: Tensor, num_freqs: int, scale: float) -> Tensor:
    """``[N, 3]`` -> ``[N, 3 + 6*num_freqs]``: ``(s*x, sin(2^k pi s x), cos(2^k pi s x))`` for ``k < num_freqs``."""
    x = xyz * scale  # [N, 3]
    freqs = (2.0 ** torch.arange(num_freqs, dtype=x.dtype, device=x.device)) * math.pi  # [L]
    ang = (x[..., None] * freqs).flatten(-2)  # [N, 3*L]
    return torch.cat([x, torch.sin(ang), torch.cos(ang)], dim=-1)


class DeformationMLP(nn.Module):
    """Per-Gaussian deformation MLP.

    Args:
        feature_dim: F, per-Gaussian feature width.
        expr_dim: E, expression code length.
        cfg: widths, depth and positional encoding.
    """

    def __init__(self, feature_dim: int, expr_dim: int, cfg: DeformConfig):
        super().__init__()
        if cfg.num_layers < 1:
            raise ValueError(f"DeformationMLP needs at least one hidden layer, got num_layers={cfg.num_layers}")
        self.cfg = cfg
        self.feature_dim = feature_dim
        self.expr_dim = expr_dim
        self.pe_dim = 3 + 6 * cfg.pe_freqs
        hdim = cfg.hidden_size
        # Input order of the first layer: [feature F, PE(xyz), expression E].
        self.first = nn.Linear(feature_dim + self.pe_dim + expr_dim, hdim)
        self.hidden = nn.ModuleList(nn.Linear(hdim, hdim) for _ in range(cfg.num_layers - 1))
        self.out = nn.Linear(hdim, 6)  # dxyz 3 + drgb 3
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)
        self._tail_compiled = None  # set by compile_tail(): torch.compile of _tail_raw on [chunk, H]

    # ------------------------------------------------------------ helpers
    def _act(self, x: Tensor) -> Tensor:
        # In place: every input is a fresh layer output (autograd supports it for slope > 0).
        return F.leaky_relu(x, self.cfg.negative_slope, inplace=True)

    def _check(self, features: Tensor, xyz: Tensor) -> None:
        if features.ndim != 2 or features.shape[1] != self.feature_dim:
            raise ValueError(f"DeformationMLP: features must have shape [N, {self.feature_dim}], got {list(features.shape)}")
        if xyz.shape != (features.shape[0], 3):
            raise ValueError(f"DeformationMLP: xyz must have shape [{features.shape[0]}, 3], got {list(xyz.shape)}")

    def _expr(self, expr: Tensor) -> Tensor:
        if expr.ndim not in (1, 2) or expr.shape[-1] != self.expr_dim:
            raise ValueError(f"DeformationMLP: expression must have shape [{self.expr_dim}] or [B, {self.expr_dim}], got {list(expr.shape)}")
        return expr

    def _tail_raw(self, h: Tensor) -> Tensor:
        """Hidden layers 2.. and the output layer on first-layer pre-activations ``[..., N, H]`` -> ``[..., N, 6]``."""
        h = self._act(h)
        for lin in self.hidden:
            h = self._act(lin(h))
        return self.out(h)

    def _tail(self, h: Tensor) -> tuple[Tensor, Tensor]:
        o = self._tail_raw(h)  # [..., N, 6]
        return o[..., :3], o[..., 3:]

    # ------------------------------------------------------------ plain path
    def forward(self, features: Tensor, xyz: Tensor, expr: Tensor) -> tuple[Tensor, Tensor]:
        """Reference path.

        Args:
            features: ``[N, F]``; xyz: ``[N, 3]`` canonical centres; expr: ``[E]`` or ``[B, E]``.
        Returns:
            ``(dxyz, drgb)``, each ``[N, 3]`` (or ``[B, N, 3]`` for a batch of expressions).
        """
        self._check(features, xyz)
        expr = self._expr(expr)
        pe = positional_encoding(xyz, self.cfg.pe_freqs, self.cfg.pe_scale)  # [N, P]
        n = features.shape[0]
        if expr.ndim == 1:
            inp = torch.cat([features, pe, expr.expand(n, -1)], dim=-1)  # [N, F+P+E]
        else:
            b = expr.shape[0]
            base = torch.cat([features, pe], dim=-1).expand(b, n, -1)
            inp = torch.cat([base, expr[:, None, :].expand(b, n, -1)], dim=-1)  # [B, N, F+P+E]
        return self._tail(self.first(inp))

    # ------------------------------------------------------------ torch.compile
    def compile_tail(self, enabled: bool = True, mode: str | None = None) -> None:
        """Run the per-chunk tail of ``forward_split`` through ``torch.compile`` when there is no autograd.

        Every chunk, the last one included, is zero-padded to ``chunk_size`` rows, so that one compiled
        graph (per precision) serves avatars of any size. Compilation happens on the first call: call
        once at start-up (the server's warm-up does). Inductor needs a C++ compiler on CPU.
        ``mode="reduce-overhead"`` (CUDA only) replays the chunk as a CUDA graph; its outputs live in
        the graph's memory pool, which is why every chunk is copied out before the next call.
        """
        self._tail_compiled = torch.compile(self._tail_raw, dynamic=False, mode=mode) if enabled else None

    @property
    def compiled(self) -> bool:
        return self._tail_compiled is not None

    def _chunks_compiled(self, partial: Tensor, ez: Tensor, chunk_size: int) -> Tensor:
        """Padded fixed-size chunks through the compiled tail: ``partial [N, H]``, ``ez [H]`` -> ``[N, 6]``."""
        n = partial.shape[0]
        out = None  # [N, 6], in the dtype the tail returns (bf16 under autocast)
        for s in range(0, n, chunk_size):
            h = partial[s : s + chunk_size] + ez  # [c, H]
            c = h.shape[0]
            if c < chunk_size:
                h = F.pad(h, (0, 0, 0, chunk_size - c))
            o = self._tail_compiled(h)  # [chunk, 6]
            if out is None:
                out = o.new_empty(n, o.shape[1])
            out[s : s + c] = o[:c]  # one copy per chunk, before the next call can reuse o's memory
        return out

    # ------------------------------------------------------------ real-time split
    def precompute(self, features: Tensor, xyz: Tensor) -> Tensor:
        """Expression-independent first-layer terms ``W_f f + W_pe PE(x) + b``: ``[N, H]``."""
        self._check(features, xyz)
        pe = positional_encoding(xyz, self.cfg.pe_freqs, self.cfg.pe_scale)
        w = self.first.weight[:, : self.feature_dim + self.pe_dim]  # [H, F+P]
        return F.linear(torch.cat([features, pe], dim=-1), w, self.first.bias)  # [N, H]

    def forward_split(self, partial: Tensor, expr: Tensor, chunk_size: int = 8192) -> tuple[Tensor, Tensor]:
        """Per-frame path: ``partial [N, H]`` from ``precompute`` plus ``W_z z``. Same outputs as ``forward``.

        Without autograd, Gaussians are processed ``chunk_size`` at a time so that the hidden
        activations stay in cache (the per-frame cost on CPU is memory-bound otherwise).
        """
        expr = self._expr(expr)
        if partial.ndim != 2 or partial.shape[1] != self.cfg.hidden_size:
            raise ValueError(f"DeformationMLP: partial must have shape [N, {self.cfg.hidden_size}], got {list(partial.shape)}")
        w_z = self.first.weight[:, self.feature_dim + self.pe_dim :]  # [H, E]
        ez = F.linear(expr, w_z)  # [H] or [B, H]
        if expr.ndim == 2:
            ez = ez[:, None, :]  # [B, 1, H]
            partial = partial[None]  # [1, N, H]
        n = partial.shape[-2]
        if self._tail_compiled is not None and not torch.is_grad_enabled() and expr.ndim == 1:
            o = self._chunks_compiled(partial, ez, chunk_size)  # [N, 6]
            return o[:, :3], o[:, 3:]
        if torch.is_grad_enabled() or n <= chunk_size:
            return self._tail(partial + ez)  # [N, H] or [B, N, H] pre-activations
        chunks = [self._tail_raw(partial[..., s : s + chunk_size, :] + ez) for s in range(0, n, chunk_size)]
        o = torch.cat(chunks, dim=-2)  # [..., N, 6]
        return o[..., :3], o[..., 3:]
