"""The FastGHA reconstruction network and deformation MLP (paper §3.2), one module per stage.

Importing this package is light; the heavy classes load on first attribute access.
"""

from __future__ import annotations

__all__ = ["FastGHA", "FastGHAOutput", "CanonicalAvatar", "DeformationMLP", "load_model"]


def __getattr__(name: str):
    if name in ("FastGHA", "FastGHAOutput", "load_model"):
        from . import fastgha

        return getattr(fastgha, name)
    if name == "CanonicalAvatar":
        from .avatar import CanonicalAvatar

        return CanonicalAvatar
    if name == "DeformationMLP":
        from .deform import DeformationMLP

        return DeformationMLP
    raise AttributeError(f"module 'fastgha_core.model' has no attribute {name!r}")
