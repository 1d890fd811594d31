"""3D Gaussians with named, *activated* fields.

Raw network channels are sliced and activated in exactly one place (the decoder's Gaussian
head, ``fastgha_core/model/gaussian_head.py``); everything else sees this dataclass.
PLY and avatar-file I/O live in ``fastgha_core/io.py``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any, Sequence

import torch
from torch import Tensor

__all__ = ["Gaussians"]


@dataclass
class Gaussians:
    """A set of N 3D Gaussians in world space (metres).

    Attributes:
        means: ``[N, 3]`` centres.
        quats: ``[N, 4]`` unit quaternions, wxyz.
        scales: ``[N, 3]`` standard deviations along the local axes, > 0.
        opacities: ``[N]`` in (0, 1).
        colors: ``[N, 3]`` RGB in [0, 1].
        features: ``[N, F]`` optional per-Gaussian features (the deformation MLP's input).
    """

    means: Tensor  # [N, 3]
    quats: Tensor  # [N, 4] wxyz
    scales: Tensor  # [N, 3]
    opacities: Tensor  # [N]
    colors: Tensor  # [N, 3]
    features: Tensor | None = None  # [N, F]

    def __post_init__(self) -> None:
        self.validate_shapes()

    # ------------------------------------------------------------ checks
    def validate_shapes(self) -> None:
        n = self.means.shape[0] if self.means.ndim >= 1 else -1
        expect = {
            "means": (n, 3),
            "quats": (n, 4),
            "scales": (n, 3),
            "opacities": (n,),
            "colors": (n, 3),
        }
        for name, shape in expect.items():
            t = getattr(self, name)
            if not isinstance(t, Tensor):
                raise ValueError(f"Gaussians.{name} must be a tensor, got {type(t).__name__}")
            if tuple(t.shape) != shape:
                raise ValueError(f"Gaussians.{name} must have shape {list(shape)} for N={n}, got {list(t.shape)}")
        if self.features is not None:
            if self.features.ndim != 2 or self.features.shape[0] != n:
                raise ValueError(f"Gaussians.features must have shape [N={n}, F], got {list(self.features.shape)}")

    def validate_values(self) -> None:
        """Check activated ranges (slower than shapes; call on untrusted data)."""
        for f in fields(self):
            t = getattr(self, f.name)
            if t is not None and not torch.isfinite(t).all():
                raise ValueError(f"Gaussians.{f.name} has non-finite values")
        if (self.scales <= 0).any():
            raise ValueError(f"Gaussians.scales must be positive, got min {float(self.scales.min()):.3g}")
        if ((self.opacities < 0) | (self.opacities > 1)).any():
            raise ValueError("Gaussians.opacities must lie in [0, 1]")
        qn = self.quats.norm(dim=-1)
        if len(qn) and (qn - 1).abs().max() > 1e-3:
            raise ValueError(f"Gaussians.quats must be unit quaternions, got norms in [{float(qn.min()):.3g}, {float(qn.max()):.3g}]")

    # ------------------------------------------------------------ properties
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def num_features(self) -> int:
        return 0 if self.features is None else int(self.features.shape[1])

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    def nbytes(self) -> int:
        return sum(getattr(self, f.name).numel() * getattr(self, f.name).element_size() for f in fields(self) if getattr(self, f.name) is not None)

    # ------------------------------------------------------------ operations
    def _map(self, fn) -> "Gaussians":
        kw = {f.name: (None if getattr(self, f.name) is None else fn(getattr(self, f.name))) for f in fields(self)}
        return Gaussians(**kw)

    def to(self, device: Any = None, dtype: torch.dtype | None = None) -> "Gaussians":
        return self._map(lambda t: t.to(device=device, dtype=dtype))

    def detach(self) -> "Gaussians":
        return self._map(lambda t: t.detach())

    def clone(self) -> "Gaussians":
        return self._map(lambda t: t.clone())

    def __getitem__(self, idx: Tensor | slice) -> "Gaussians":
        """Select Gaussians with a boolean mask ``[N]``, an index tensor or a slice."""
        if isinstance(idx, Tensor) and idx.dtype == torch.bool and idx.shape != (len(self),):
            raise ValueError(f"boolean mask must have shape [{len(self)}], got {list(idx.shape)}")
        return self._map(lambda t: t[idx])

    def prune(self, min_opacity: float) -> "Gaussians":
        """Drop Gaussians with opacity below ``min_opacity``."""
        return self[self.opacities >= min_opacity]

    def replace(self, **changes: Any) -> "Gaussians":
        return replace(self, **changes)

    @staticmethod
    def concat(items: Sequence["Gaussians"]) -> "Gaussians":
        if not items:
            raise ValueError("Gaussians.concat needs at least one item, got none")
        has_feat = {g.features is not None for g in items}
        if len(has_feat) != 1:
            raise ValueError("Gaussians.concat: either all items have features or none do")
        kw = {}
        for f in fields(Gaussians):
            vals = [getattr(g, f.name) for g in items]
            kw[f.name] = None if vals[0] is None else torch.cat(vals, dim=0)
        return Gaussians(**kw)

    @staticmethod
    def empty(num_features: int = 0, dtype: torch.dtype = torch.float32, device: Any = None) -> "Gaussians":
        z = lambda *s: torch.zeros(*s, dtype=dtype, device=device)  # noqa: E731
        return Gaussians(z(0, 3), z(0, 4), z(0, 3), z(0), z(0, 3), z(0, num_features) if num_features else None)
