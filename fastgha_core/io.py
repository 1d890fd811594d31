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

Axes (``axes=``): ``"colmap"`` (the default) is the convention of standard 3DGS files, which come from
COLMAP scenes with y pointing *down*: file ``(x, y, z) = (-x, -y, z)`` of our head-centric world
(+x the subject's left, +y up, +z out of the face), i.e. a 180 degree rotation about z (quaternions
are rotated with it; handedness is kept). SuperSplat / PlayCanvas viewers rotate every PLY by 180
degrees about z when they load it, so they show a ``"colmap"`` file upright, facing +z.
``"fastgha"`` writes our world axes unchanged. The writer records its choice in a header comment
(``comment fastgha_axes <axes>``); the reader undoes it, and reads files without that comment (other
tools' files) as ``"colmap"`` unless told otherwise.

SuperSplat's *compressed* PLY (elements ``chunk`` + ``vertex`` with ``packed_position``,
``packed_rotation``, ``packed_scale``, ``packed_color`` and an optional ``sh``; 256 Gaussians per
chunk, each chunk storing min/max of positions, log-scales and colours; positions and scales packed
11-10-11 bits, rotations as the three smallest quaternion components in 10 bits each plus the index of
the largest in 2 bits, colour and opacity 8 bits each) is read too, as written by
``@playcanvas/splat-transform`` (``src/lib/readers``: ``readCompressedChunked``).

Avatar file (safetensors): tensors ``gaussians.means``, ``gaussians.quats``, ``gaussians.scales``,
``gaussians.opacities``, ``gaussians.colors`` (activated values), ``gaussians.features`` when
present, and ``extra.<name>`` for caller-defined tensors; string metadata with at least
``format_version`` (= ``constants.AVATAR_FORMAT_VERSION``), ``model_name`` and
``expression_space``.
"""

from __future__ import annotations

import logging
import math
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
    "PLY_AXES",
    "drop_outliers",
    "save_ply",
    "viewer_settings",
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


PLY_AXES = ("colmap", "fastgha")
_AXES_COMMENT = "fastgha_axes"


def _check_axes(axes: str) -> None:
    if axes not in PLY_AXES:
        raise ValueError(f"PLY axes must be one of {list(PLY_AXES)}, got {axes!r}")


def _rotate_z180(means: Tensor, quats: Tensor, inverse: bool = False) -> tuple[Tensor, Tensor]:
    """Positions and wxyz quaternions rotated 180 degrees about z.

    ``q' = q_z ⊗ q`` with ``q_z = (0, 0, 0, 1)``: ``(w, x, y, z) -> (-z, -y, x, w)``; the inverse
    uses ``q_z^-1 = (0, 0, 0, -1)``, so that a write/read round trip returns the same quaternion
    (not only the same rotation).
    """
    m = means * torch.tensor([-1.0, -1.0, 1.0], dtype=means.dtype)
    w, x, y, z = quats.unbind(-1)
    q = torch.stack([-z, -y, x, w], dim=-1)
    return m, (-q if inverse else q)


def drop_outliers(g: Gaussians, *, quantile: float = 0.99, factor: float = 2.0) -> tuple[Gaussians, int]:
    """Drop stray Gaussians that would blow up a viewer's bounding box.

    With ``c`` the per-axis median of the means and ``r`` the ``quantile`` of the distances to
    ``c``, Gaussians farther than ``factor * r`` from ``c``, or with a standard deviation larger
    than ``r`` (one splat wider than the whole head), are dropped. For a head (r about 0.17 m) the
    cut is about 0.35 m from its centre. Returns ``(kept Gaussians, number dropped)``.
    """
    n = len(g)
    if n < 2:
        return g, 0
    means = g.means.detach().to(torch.float64)
    c = means.median(dim=0).values
    d = (means - c).norm(dim=-1)  # [N]
    r = float(torch.quantile(d, quantile))
    keep = d <= factor * r
    if r > 0:
        keep &= g.scales.detach().to(torch.float64).amax(dim=-1) <= r
    dropped = int(n - int(keep.sum()))
    if dropped == 0:
        return g, 0
    idx = keep.nonzero().squeeze(-1).to(g.means.device)
    return g[idx], dropped


def save_ply(path: str | Path, g: Gaussians, *, axes: str = "colmap", outliers: bool = True) -> int:
    """Write ``g`` as a 3DGS PLY (SH degree 0). Features are not written.

    Args:
        axes: ``"colmap"`` (default; y down, how SuperSplat and other viewers expect 3DGS files and
            show them upright) or ``"fastgha"`` (our world axes); see the module doc.
        outliers: when True (default), :func:`drop_outliers` removes stray Gaussians first.
    Returns:
        the number of Gaussians written.
    Raises:
        ValueError: unknown ``axes`` or invalid Gaussian values.
    """
    from plyfile import PlyData, PlyElement

    _check_axes(axes)
    g.validate_values()
    dropped = 0
    if outliers:
        g, dropped = drop_outliers(g)
        if dropped:
            logger.info("PLY %s: dropped %d stray Gaussians (drop_outliers)", path, dropped)
    n = len(g)
    gd = g.detach().to("cpu", torch.float64)
    means, quats = gd.means, gd.quats
    if axes == "colmap":
        means, quats = _rotate_z180(means, quats)
    f_dc = (gd.colors - 0.5) / SH_C0  # [N, 3]
    o = gd.opacities.clamp(_OPACITY_EPS, 1.0 - _OPACITY_EPS)
    logit = torch.log(o) - torch.log1p(-o)  # [N]
    log_scales = torch.log(gd.scales)  # [N, 3]
    cols = [means, torch.zeros(n, 3, dtype=torch.float64), f_dc, logit[:, None], log_scales, quats]
    data = torch.cat(cols, dim=1).numpy().astype(np.float32)  # [N, 17]
    props = _ply_properties()
    arr = np.empty(n, dtype=[(p, "<f4") for p in props])
    for j, p in enumerate(props):
        arr[p] = data[:, j]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    comments = [f"{_AXES_COMMENT} {axes}", "written by FastGHA (fastgha_core.io.save_ply)"]
    PlyData([PlyElement.describe(arr, "vertex")], text=False, byte_order="<", comments=comments).write(str(path))
    logger.debug("wrote %d Gaussians to %s (axes %s, %d outliers dropped)", n, path, axes, dropped)
    return n


def viewer_settings(g: Gaussians, *, axes: str = "colmap", fov_deg: float = 35.0) -> dict:
    """A SuperSplat viewer ``settings.json`` (version 2) whose camera frames the head from the front.

    ``@playcanvas/splat-transform`` puts its HTML viewer's camera at (2, 2, -2) looking at the
    origin with an 85 degree field of view: a 0.3 m head is a speck seen from behind. Pass this file
    with ``--viewer-settings`` (``fastgha export --viewer-settings`` writes it). The camera looks at
    the median of the means from the +z side (in front of the face) at the distance where a sphere
    of the 99th-percentile radius fills 80 % of the vertical field of view ``fov_deg``.
    Coordinates are the viewer's (the viewer rotates a PLY by 180 degrees about z; see the module doc).
    """
    _check_axes(axes)
    means = g.means.detach().to("cpu", torch.float64)
    if len(means) == 0:
        raise ValueError("viewer_settings: no Gaussians")
    c = means.median(dim=0).values
    r = max(float(torch.quantile((means - c).norm(dim=-1), 0.99)), 1e-3)
    if axes == "fastgha":  # the viewer's 180 degree turn is not undone by the file: it sees (-x, -y, z)
        c = c * torch.tensor([-1.0, -1.0, 1.0], dtype=c.dtype)
    dist = r / (0.8 * math.tan(math.radians(fov_deg) / 2.0))
    target = [round(float(v), 5) for v in c]
    position = [target[0], target[1], round(target[2] + dist, 5)]
    return {
        "version": 2,
        "tonemapping": "none",
        "highPrecisionRendering": False,
        "background": {"color": [0.0, 0.0, 0.0]},
        "postEffectSettings": {
            "sharpness": {"enabled": False, "amount": 0},
            "bloom": {"enabled": False, "intensity": 0.1, "blurLevel": 2},
            "grading": {"enabled": False, "brightness": 1, "contrast": 1, "saturation": 1, "tint": [1, 1, 1]},
            "vignette": {"enabled": False, "intensity": 0.5, "inner": 0.3, "outer": 0.75, "curvature": 1},
            "fringing": {"enabled": False, "intensity": 0.5},
        },
        "animTracks": [],
        "cameras": [{"initial": {"position": position, "target": target, "fov": float(fov_deg)}}],
        "annotations": [],
        "startMode": "default",
    }


_PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")
_CHUNK_BOUNDS = ("min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
                 "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z")  # fmt: skip
_ROT_NORM = 1.0 / (math.sqrt(2.0) * 0.5)


def _unorm(v: np.ndarray, shift: int, bits: int) -> np.ndarray:
    return ((v >> np.uint32(shift)) & np.uint32((1 << bits) - 1)).astype(np.float64) / ((1 << bits) - 1)


def _decode_compressed(ply, path: Path) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """SuperSplat compressed PLY -> (means, f_dc, opacity logits, log-scales, quats wxyz), float64."""
    chunk = ply["chunk"].data
    v = ply["vertex"].data
    have_c = set(chunk.dtype.names or ())
    missing = [p for p in _CHUNK_BOUNDS if p not in have_c] + [p for p in _PACKED if p not in set(v.dtype.names or ())]
    if missing:
        raise ValueError(f"PLY {path}: a SuperSplat compressed PLY, but missing properties {missing}")
    n = len(v)
    if len(chunk) < (n + 255) // 256:
        raise ValueError(f"PLY {path}: compressed PLY with {n} Gaussians needs {(n + 255) // 256} chunks, has {len(chunk)}")
    ci = np.arange(n) // 256

    def bound(name: str) -> np.ndarray:
        return np.asarray(chunk[name], dtype=np.float64)[ci]

    def lerp(lo: str, hi: str, t: np.ndarray) -> np.ndarray:
        a, b = bound(lo), bound(hi)
        return a * (1.0 - t) + b * t

    pp, pr, ps, pc = (np.asarray(v[k], dtype=np.uint32) for k in _PACKED)
    means = np.stack([lerp("min_x", "max_x", _unorm(pp, 21, 11)), lerp("min_y", "max_y", _unorm(pp, 11, 10)),
                      lerp("min_z", "max_z", _unorm(pp, 0, 11))], axis=1)  # fmt: skip
    log_scales = np.stack([lerp("min_scale_x", "max_scale_x", _unorm(ps, 21, 11)),
                           lerp("min_scale_y", "max_scale_y", _unorm(ps, 11, 10)),
                           lerp("min_scale_z", "max_scale_z", _unorm(ps, 0, 11))], axis=1)  # fmt: skip
    abc = np.stack([(_unorm(pr, s, 10) - 0.5) * _ROT_NORM for s in (20, 10, 0)], axis=1)  # [N, 3]
    largest = (pr >> np.uint32(30)).astype(np.int64)
    m = np.sqrt(np.clip(1.0 - (abc**2).sum(axis=1), 0.0, None))
    quats = np.empty((n, 4))
    for k in range(4):  # the largest component goes to slot k, the three others fill the rest in order
        sel = largest == k
        others = [j for j in range(4) if j != k]
        quats[sel, k] = m[sel]
        quats[np.ix_(sel, others)] = abc[sel]
    rgb = np.stack([_unorm(pc, 24, 8), _unorm(pc, 16, 8), _unorm(pc, 8, 8)], axis=1)
    if {"min_r", "min_g", "min_b", "max_r", "max_g", "max_b"} <= have_c:
        rgb = np.stack([lerp(f"min_{c}", f"max_{c}", rgb[:, i]) for i, c in enumerate("rgb")], axis=1)
    alpha = np.clip(_unorm(pc, 0, 8), 1e-6, 1.0 - 1e-6)
    f_dc = (rgb - 0.5) / SH_C0
    logit = np.log(alpha) - np.log1p(-alpha)
    t = torch.from_numpy
    return t(means), t(f_dc), t(logit), t(log_scales), t(quats)


def load_ply(path: str | Path, *, axes: str | None = None) -> Gaussians:
    """Read a 3DGS PLY (SH degree 0..3, or SuperSplat's compressed PLY) into activated ``Gaussians``.

    Higher-order SH coefficients are dropped with a ``UserWarning``; quaternions are
    normalised; colours ``0.5 + SH_C0 * f_dc`` are clamped to [0, 1]. The result is in our world
    axes: ``axes`` (``"colmap"`` or ``"fastgha"``) says how the file stores them; None = from
    the ``fastgha_axes`` header comment that :func:`save_ply` writes, else ``"colmap"`` (the
    standard 3DGS convention).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a PLY, not a Gaussian PLY (names the missing properties), non-finite values.
    """
    from plyfile import PlyData

    if axes is not None:
        _check_axes(axes)
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PLY: no such file {path}")
    try:
        ply = PlyData.read(str(path))
    except Exception as e:  # plyfile raises several exception types for malformed files
        raise ValueError(f"PLY {path}: cannot parse ({type(e).__name__}: {e})") from None
    if axes is None:
        axes = "colmap"
        for c in ply.comments:
            parts = c.split()
            if len(parts) == 2 and parts[0] == _AXES_COMMENT and parts[1] in PLY_AXES:
                axes = parts[1]
    names = [el.name for el in ply.elements]
    if "vertex" not in names:
        raise ValueError(f"PLY {path}: expected a 'vertex' element, got elements {names}")
    v = ply["vertex"].data
    have = set(v.dtype.names or ())
    if "chunk" in names and "packed_position" in have:
        if "sh" in names:
            warnings.warn(f"PLY {path}: compressed SH coefficients dropped (only the DC colour is kept)", UserWarning, stacklevel=2)
        means, f_dc, logit, log_scales, quats = _decode_compressed(ply, path)
    else:
        means, f_dc, logit, log_scales, quats = _read_plain(v, have, path)
    for what, t in (("positions", means), ("colours", f_dc), ("opacities", logit), ("scales", log_scales), ("rotations", quats)):
        if not torch.isfinite(t).all():
            raise ValueError(f"PLY {path}: {what} contain non-finite values")
    qn = quats.norm(dim=-1, keepdim=True)
    if (qn < 1e-12).any():
        raise ValueError(f"PLY {path}: {int((qn < 1e-12).sum())} Gaussians have a zero quaternion")
    quats = quats / qn
    if axes == "colmap":
        means, quats = _rotate_z180(means, quats, inverse=True)
    g = Gaussians(
        means=means,
        quats=quats,
        scales=torch.exp(log_scales),
        opacities=torch.sigmoid(logit),
        colors=(0.5 + SH_C0 * f_dc).clamp(0.0, 1.0),
    )
    return g.to(dtype=torch.float32)


def _read_plain(v, have: set, path: Path) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3"]  # fmt: skip
    missing = [p for p in need if p not in have]
    if missing:
        packed = sorted(have & set(_PACKED))
        hint = f" (it has {packed}: a compressed PLY needs its 'chunk' element)" if packed else ""
        raise ValueError(
            f"PLY {path}: not a 3DGS Gaussian PLY, missing properties {missing}; expected the standard layout "
            f"(x y z, f_dc_0..2, opacity, scale_0..2, rot_0..3) or SuperSplat's compressed PLY{hint}"
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
            stacklevel=3,
        )

    def cols(props: list[str]) -> Tensor:
        return torch.from_numpy(np.stack([np.asarray(v[p], dtype=np.float64) for p in props], axis=1))

    return (cols(["x", "y", "z"]), cols(["f_dc_0", "f_dc_1", "f_dc_2"]), cols(["opacity"])[:, 0],
            cols(["scale_0", "scale_1", "scale_2"]), cols(["rot_0", "rot_1", "rot_2", "rot_3"]))  # fmt: skip


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
    from safetensors.torch import save

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
    # bytes written by Python, not safetensors' save_file: that one creates the file with mode 0600,
    # where every other output (PLY, MP4, JSON) follows the user's umask
    path.write_bytes(save(tensors, metadata=meta))
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
    with open(path, "rb") as fh:
        if fh.read(4) == b"ply\n":  # the export, given back where the avatar is wanted
            raise ValueError(
                f"avatar file {path} is a PLY point cloud; expected the .safetensors avatar file written by "
                "`fastgha reconstruct` (a PLY keeps no per-Gaussian features or expression binding, so it cannot be animated)"
            )
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
