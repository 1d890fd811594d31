"""``CanonicalAvatar``: the reconstructed, expression-free Gaussian head that animation deforms.

Saved with ``fastgha_core.io.save_avatar_file`` (safetensors + string metadata). The deformation
MLP's expression-independent first-layer terms (``deform_cache``) are a per-model cache: they are
never saved, and ``FastGHA.animate`` recomputes them on first use after loading or when another
model animates the avatar. Set ``avatar.deform_cache = None`` after changing the weights of the
model that filled it (e.g. between training steps).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from torch import Tensor

from ..gaussians import Gaussians

__all__ = ["CanonicalAvatar"]


@dataclass
class CanonicalAvatar:
    """Canonical Gaussians with per-Gaussian features, tagged with the model that made them.

    Attributes:
        gaussians: ``Gaussians`` with ``features [N, F]``.
        model_name: name of the model config (``"tiny"``, ``"paper"`` or a trained variant).
        expression_space: the model's expression space (``"ict53"`` / ``"flame120"``).
        deform_cache: ``[N, H]`` first-layer partial of the deformation MLP (not saved).
        deform_cache_owner: ``id`` of the deformation MLP that filled the cache.
    """

    gaussians: Gaussians
    model_name: str
    expression_space: str
    deform_cache: Tensor | None = field(default=None, repr=False, compare=False)
    deform_cache_owner: int | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.gaussians.features is None:
            raise ValueError("CanonicalAvatar needs Gaussians with per-Gaussian features, got features=None")

    def __len__(self) -> int:
        return len(self.gaussians)

    @property
    def nbytes(self) -> int:
        """Bytes held by the Gaussians (the cache not counted)."""
        return self.gaussians.nbytes()

    def metadata(self) -> dict[str, str]:
        return {"model_name": self.model_name, "expression_space": self.expression_space}

    def save(self, path: str | Path) -> None:
        from ..io import save_avatar_file

        save_avatar_file(path, self.gaussians.detach().to("cpu"), self.metadata())

    @classmethod
    def load(cls, path: str | Path) -> "CanonicalAvatar":
        from ..io import load_avatar_file

        g, meta, _extra = load_avatar_file(path)
        missing = [k for k in ("model_name", "expression_space") if k not in meta]
        if missing:
            raise ValueError(f"avatar file {str(path)!r} lacks metadata {missing}; was it written by CanonicalAvatar.save?")
        return cls(g, meta["model_name"], meta["expression_space"])

    def to_ply(self, path: str | Path) -> None:
        """Export the canonical Gaussians as a standard 3DGS PLY (features are not part of that layout)."""
        from ..io import save_ply

        save_ply(path, self.gaussians.detach().to("cpu"))

    def to(self, device) -> "CanonicalAvatar":
        return CanonicalAvatar(self.gaussians.to(device), self.model_name, self.expression_space)
