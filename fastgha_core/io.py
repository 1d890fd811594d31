"""Gaussian files: PLY in the standard 3DGS layout, and FastGHA avatar files (safetensors).

PLY (one ``vertex`` element, float32 properties, binary little-endian), as written by the
original 3DGS code and read by SuperSplat, gsplat and three.js splat viewers::

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  [f_rest_0 ...]  opacity  scale_0 scale_1 scale_2  rot_0 rot_1 rot_2 rot_3

- ``f_dc`` = degree-0 SH coefficient: ``rgb = 0.5 + SH_C0 * f_dc``, ``SH_C0 = 0.28209479177387814``;
- ``opacity`` = logit of the opacity; ``scale_*`` = log of the standard deviations;
- ``rot_*`` = quaternion w x y z (not necessarily normalised in files from other tools);
- normals are written as zeros; per-Gaussian features are *not* stored in a PLY.

We write SH degree 0 (no ``f_rest``). Reading accepts degrees 0..3 (0, 9, 24 or 45 ``f_rest``
values) and drops the view-dependent part with a warning; imported colours are clamped to [0, 1].

Avatar file (safetensors): tensors ``gaussians.means``, ``gaussians.quats``, ``gaussians.scales``,
``gaussians.opacities``, ``gaussians.colors`` (activated values), ``gaussians.features`` when
present, and ``extra.<name>`` for caller-defined tensors; string metadata with at least
``format_version`` (= ``constants.AVATAR_FORMAT_VERSION``), ``model_name`` and
``expression_space``.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .constants import AVATAR_FORMAT_VERSION
from .gaussians import Gaussians

__all__ = [
    "SH_C0",
    "save_ply",
    "load_ply",
    "save_avatar_file",
    "load_avatar_file",
    "REQUIRED_METADATA",
]

logger = logging.getLogger(__name__)

SH_C0 = 0.28209479177387814
# Opacities are clamped to [eps, 1 - eps] (in float64) before the logit so that 0 and 1 stay finite;
# sigmoid(logit(1 - 1e-12)) rounds back to exactly 1.0 in float32.
_OPACITY_EPS = 1e-12
# Number of f_rest values (3 channels x ((d+1)^2 - 1) coefficients) -> SH degree d.
_REST_TO_DEGREE = {0: 0, 9: 1, 24: 2, 45: 3}

_GAUSSIAN_FIELDS = ("means", "quats", "scales", "opacities", "colors")
_FEATURES_KEY = "gaussians.features"
_EXTRA_PREFIX = "extra."
REQUIRED_METADATA = ("model_name", "expression_space")


# ---------------------------------------------------------------- PLY
def _ply_properties() -> list[str]:
    return ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
            "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]  # fmt: skip


def save_ply(path: str | Path, g: Gaussians) -> None:
    """Write ``g`` as a 3DGS PLY (SH degree 0). Features are not written."""
    from plyfile import PlyData, PlyElement

    g.validate_values()
    n = len(g)
    gd = g.detach().to("cpu", torch.float64)
    f_dc = (gd.colors - 0.5) / SH_C0  # [N, 3]
    o = gd.opacities.clamp(_OPACITY_EPS, 1.0 - _OPACITY_EPS)
    logit = torch.log(o) - torch.log1p(-o)  # [N]
    log_scales = torch.log(gd.scales)  # [N, 3]
    cols = [gd.means, torch.zeros(n, 3, dtype=torch.float64), f_dc, logit[:, None], log_scales, gd.quats]
    data = torch.cat(cols, dim=1).numpy().astype(np.float32)  # [N, 17]
    props = _ply_properties()
    arr = np.empty(n, dtype=[(p, "<f4") for p in props])
    for j, p in enumerate(props):
        arr[p] = data[:, j]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(arr, "vertex")], text=False, byte_order="<").write(str(path))
    logger.debug("wrote %d Gaussians to %s", n, path)


def load_ply(path: str | Path) -> Gaussians:
    """Read a 3DGS PLY (SH degree 0..3) into activated ``Gaussians`` (float32, no features).

    Higher-order SH coefficients are dropped with a ``UserWarning``; quaternions are
    normalised; colours ``0.5 + SH_C0 * f_dc`` are clamped to [0, 1].
    """
    from plyfile import PlyData

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PLY: no such file {path}")
    try:
        ply = PlyData.read(str(path))
    except Exception as e:  # plyfile raises several exception types for malformed files
        raise ValueError(f"PLY {path}: cannot parse ({type(e).__name__}: {e})") from None
    names = [el.name for el in ply.elements]
    if "vertex" not in names:
        raise ValueError(f"PLY {path}: expected a 'vertex' element, got elements {names}")
    v = ply["vertex"].data
    have = set(v.dtype.names or ())
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3"]  # fmt: skip
    missing = [p for p in need if p not in have]
    if missing:
        raise ValueError(
            f"PLY {path}: not a 3DGS Gaussian PLY, missing properties {missing}; expected the standard layout "
            "(x y z, f_dc_0..2, opacity, scale_0..2, rot_0..3)"
        )
    n_rest = sum(1 for p in have if p.startswith("f_rest_"))
    if n_rest not in _REST_TO_DEGREE:
        raise ValueError(f"PLY {path}: expected 0, 9, 24 or 45 f_rest_* properties (SH degree 0..3), got {n_rest}")
    degree = _REST_TO_DEGREE[n_rest]
    if degree > 0:
        warnings.warn(
            f"PLY {path}: SH degree {degree}; dropping the {n_rest} higher-order coefficients "
            "(view-dependent colour is lost, only the DC colour is kept)",
            UserWarning,
            stacklevel=2,
        )

    def cols(props: list[str]) -> Tensor:
        return torch.from_numpy(np.stack([np.asarray(v[p], dtype=np.float64) for p in props], axis=1))

    means = cols(["x", "y", "z"])
    f_dc = cols(["f_dc_0", "f_dc_1", "f_dc_2"])
    logit = cols(["opacity"])[:, 0]
    log_scales = cols(["scale_0", "scale_1", "scale_2"])
    quats = cols(["rot_0", "rot_1", "rot_2", "rot_3"])
    for what, t in (("positions", means), ("colours", f_dc), ("opacities", logit), ("scales", log_scales), ("rotations", quats)):
        if not torch.isfinite(t).all():
            raise ValueError(f"PLY {path}: {what} contain non-finite values")
    qn = quats.norm(dim=-1, keepdim=True)
    if (qn < 1e-12).any():
        raise ValueError(f"PLY {path}: {int((qn < 1e-12).sum())} Gaussians have a zero quaternion")
    g = Gaussians(
        means=means,
        quats=quats / qn,
        scales=torch.exp(log_scales),
        opacities=torch.sigmoid(logit),
        colors=(0.5 + SH_C0 * f_dc).clamp(0.0, 1.0),
    )
    return g.to(dtype=torch.float32)


# ---------------------------------------------------------------- avatar files
def save_avatar_file(
    path: str | Path,
    g: Gaussians,
    metadata: dict[str, str],
    extra: dict[str, Tensor] | None = None,
) -> None:
    """Write an avatar file (safetensors): Gaussians, their features, extra tensors, string metadata.

    ``metadata`` must hold ``model_name`` and ``expression_space`` (strings); ``format_version``
    is added (``constants.AVATAR_FORMAT_VERSION``).
    """
    from safetensors.torch import save_file

    if not isinstance(metadata, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in metadata.items()):
        raise ValueError(f"avatar metadata must be a dict of str -> str, got {metadata!r}")
    missing = [k for k in REQUIRED_METADATA if k not in metadata]
    if missing:
        raise ValueError(f"avatar metadata must contain {list(REQUIRED_METADATA)}, missing {missing}")
    version = str(AVATAR_FORMAT_VERSION)
    if metadata.get("format_version", version) != version:
        raise ValueError(f"avatar metadata format_version must be {version} (or absent), got {metadata['format_version']!r}")
    meta = {**metadata, "format_version": version}

    tensors: dict[str, Tensor] = {}
    for name in _GAUSSIAN_FIELDS:
        tensors[f"gaussians.{name}"] = getattr(g, name)
    if g.features is not None:
        tensors[_FEATURES_KEY] = g.features
    for name, t in (extra or {}).items():
        if not isinstance(name, str) or not name:
            raise ValueError(f"extra tensor names must be non-empty strings, got {name!r}")
        if not isinstance(t, Tensor):
            raise ValueError(f"extra tensor {name!r} must be a torch.Tensor, got {type(t).__name__}")
        tensors[_EXTRA_PREFIX + name] = t
    tensors = {k: t.detach().to("cpu").contiguous().clone() for k, t in tensors.items()}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_file(tensors, str(path), metadata=meta)
    logger.debug("wrote avatar (%d Gaussians) to %s", len(g), path)


def load_avatar_file(path: str | Path, device: Any = "cpu") -> tuple[Gaussians, dict[str, str], dict[str, Tensor]]:
    """Read an avatar file -> ``(Gaussians with features, metadata, extra tensors)``.

    Raises ``FileNotFoundError`` for a missing file and ``ValueError`` for a file that is not a
    FastGHA avatar, has another format version, or lacks Gaussian tensors.
    """
    from safetensors import safe_open

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"avatar file: no such file {path}")
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            meta = dict(f.metadata() or {})
            keys = list(f.keys())
            if "format_version" not in meta:
                raise ValueError(f"avatar file {path}: no format_version in its metadata; not a FastGHA avatar file")
            if meta["format_version"] != str(AVATAR_FORMAT_VERSION):
                raise ValueError(
                    f"avatar file {path}: format version {meta['format_version']!r}, this FastGHA reads version "
                    f"{AVATAR_FORMAT_VERSION}; re-export the avatar with a matching FastGHA version"
                )
            missing = [f"gaussians.{n}" for n in _GAUSSIAN_FIELDS if f"gaussians.{n}" not in keys]
            if missing:
                raise ValueError(f"avatar file {path}: missing tensors {missing}")
            tensors = {k: f.get_tensor(k) for k in keys}
    except ValueError:
        raise
    except Exception as e:  # safetensors raises SafetensorError / OSError on corrupt headers
        raise ValueError(f"avatar file {path}: cannot read as safetensors ({type(e).__name__}: {e})") from None
    kw = {n: tensors[f"gaussians.{n}"].to(device) for n in _GAUSSIAN_FIELDS}
    feats = tensors.get(_FEATURES_KEY)
    try:
        g = Gaussians(**kw, features=None if feats is None else feats.to(device))
    except ValueError as e:
        raise ValueError(f"avatar file {path}: {e}") from None
    extra = {k[len(_EXTRA_PREFIX) :]: t.to(device) for k, t in tensors.items() if k.startswith(_EXTRA_PREFIX)}
    return g, meta, extra
