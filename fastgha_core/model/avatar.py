"""``CanonicalAvatar``: the reconstructed, expression-free Gaussian head that animation deforms.

Saved with ``fastgha_core.io.save_avatar_file`` (safetensors + string metadata). The deformation
MLP's expression-independent first-layer terms (``deform_cache``) are a per-model cache: they are
never saved, and ``FastGHA.animate`` recomputes them on first use after loading or when another
model animates the avatar. Set ``avatar.deform_cache = None`` after changing the weights of the
model that filled it (e.g. between training steps).

With the expression prior (``DeformConfig.prior``, issue 16) the avatar also carries ``prior``: each
Gaussian's binding to a head surface fitted to it (nearest triangle's vertex ids, barycentric
coordinates, fade weight, the fit's transform and identity; ``model/prior.py``), saved as extra
``prior.*`` tensors of the avatar file, and ``num_interior`` mouth-interior Gaussians (teeth, gums,
mouth socket) at the end of ``gaussians``: part of the file, the PLY export and every render.

``view_blend`` (``model/viewblend.py``): each reconstructed Gaussian's source input view and the
mask of input views that see its point, with the input cameras' directions, saved as ``view.*``
tensors; frames then weight each view's Gaussians by its camera's angle to the render camera
(``GaussianHeadConfig.view_blend_tau_deg``), and, with the input views' expressions (``view.expr``),
by how far each view's expression puts the Gaussian's bound surface point from the frame's
(``view_blend_expr_mm``). Files written without them load with ``None`` (frames unweighted; without
``view.expr``: by the angle alone). The PLY export is a static file: it holds the unweighted opacities.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from torch import Tensor

from ..gaussians import Gaussians
from .prior import PriorBinding
from .viewblend import ViewBlend

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
        deform_cache_source: the ``gaussians`` object the cache was computed from (assigning new
            Gaussians to the avatar recomputes it; changing its tensors in place does not).
        prior: ``PriorBinding`` of every Gaussian (``None`` without the expression prior).
        num_interior: mouth-interior Gaussians at the end of ``gaussians`` (no MLP residual; their
            opacity follows how far the lips are open).
        prior_runtime: the binding's per-frame compact basis (a cache, not saved; ``FastGHA.animate``
            rebuilds it when ``prior`` is replaced, the Gaussian count or device changes, or the
            model's ``prior_shading`` differs).
        view_blend: ``ViewBlend`` of the first ``num_reconstructed`` Gaussians (``None``: no per-view
            data, frames are not view-weighted).
    """

    gaussians: Gaussians
    model_name: str
    expression_space: str
    prior: PriorBinding | None = None
    num_interior: int = 0
    view_blend: ViewBlend | None = None
    deform_cache: Tensor | None = field(default=None, repr=False, compare=False)
    deform_cache_owner: int | None = field(default=None, repr=False, compare=False)
    deform_cache_source: Gaussians | None = field(default=None, repr=False, compare=False)
    prior_runtime: object | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.gaussians.features is None:
            raise ValueError("CanonicalAvatar needs Gaussians with per-Gaussian features, got features=None")
        if self.prior is not None and len(self.prior) != len(self.gaussians):
            raise ValueError(f"CanonicalAvatar: prior binds {len(self.prior)} Gaussians, the avatar has {len(self.gaussians)}")
        if not 0 <= self.num_interior <= len(self.gaussians):
            raise ValueError(f"CanonicalAvatar: num_interior must lie in [0, {len(self.gaussians)}], got {self.num_interior}")
        if self.view_blend is not None and len(self.view_blend) != self.num_reconstructed:
            raise ValueError(f"CanonicalAvatar: view_blend covers {len(self.view_blend)} Gaussians, the avatar has {self.num_reconstructed} reconstructed ones")

    @property
    def num_reconstructed(self) -> int:
        """Gaussians made by the network (the first ones; the mouth interior follows)."""
        return len(self.gaussians) - self.num_interior

    def __len__(self) -> int:
        return len(self.gaussians)

    @property
    def nbytes(self) -> int:
        """Bytes held by the Gaussians (the cache not counted)."""
        return self.gaussians.nbytes()

    def metadata(self) -> dict[str, str]:
        meta = {"model_name": self.model_name, "expression_space": self.expression_space}
        if self.num_interior:
            meta["num_interior"] = str(self.num_interior)
        return meta

    def save(self, path: str | Path) -> None:
        from ..io import save_avatar_file

        extra = dict(self.prior.to("cpu").tensors()) if self.prior is not None else {}
        if self.view_blend is not None:
            extra.update(self.view_blend.to("cpu").tensors())
        extra = extra or None
        save_avatar_file(path, self.gaussians.detach().to("cpu"), self.metadata(), extra)

    @classmethod
    def load(cls, path: str | Path) -> "CanonicalAvatar":
        from ..io import load_avatar_file

        g, meta, extra = load_avatar_file(path)
        missing = [k for k in ("model_name", "expression_space") if k not in meta]
        if missing:
            raise ValueError(f"avatar file {str(path)!r} lacks metadata {missing}; was it written by CanonicalAvatar.save?")
        try:
            prior = PriorBinding.from_tensors(extra, meta["expression_space"], len(g))
            n_int = int(meta.get("num_interior", "0"))
            blend = ViewBlend.from_tensors(extra, len(g) - n_int)
        except ValueError as e:
            raise ValueError(f"avatar file {str(path)!r}: {e}") from None
        return cls(g, meta["model_name"], meta["expression_space"], prior, n_int, blend)

    def to_ply(self, path: str | Path) -> None:
        """Export the canonical Gaussians as a standard 3DGS PLY (features are not part of that layout).

        A PLY is static: it cannot depend on the render camera, so it holds the unweighted opacities
        (no view blending, ``model/viewblend.py``)."""
        from ..io import save_ply

        save_ply(path, self.gaussians.detach().to("cpu"))

    def to(self, device) -> "CanonicalAvatar":
        prior = self.prior.to(device) if self.prior is not None else None
        blend = self.view_blend.to(device) if self.view_blend is not None else None
        return CanonicalAvatar(self.gaussians.to(device), self.model_name, self.expression_space, prior, self.num_interior, blend)
