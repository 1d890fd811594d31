"""The tracked head of a request folder (``head.json`` of ``fastgha track``), read one way everywhere.

``fastgha track`` writes ``head.json`` = ``{"model": "ict_facekit", "identity": [100 floats],
"frames": {crop file name: [left, top, right, bottom]}}`` (the person's ICT-FaceKit identity
coefficients, modes ~ N(0, 1); each crop's photo as fractions of the crop, whose padding beyond the
photo's edge is then not read as background, ``HeadSurface.frames``) and ``expressions.json`` (each
photo's ``ict53`` expression, weights in [0, 1]). ``fastgha reconstruct`` and the server's ``head`` part of
``POST /v1/avatars`` (``docs/protocol.md``) both turn them into a
``fastgha_core.model.surface.HeadSurface`` with :func:`head_surface_from_json` and reconstruct with
every pixel's Gaussian on it (``surface_mode="replace"``) and the photos' expressions undone
(:func:`head_expressions`). The head frame is the world of the folder's ``cameras.json`` (the
tracker's head-centric cameras), so the surface has no ``head_to_world``.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["HEAD_MODEL", "MAX_ABS_IDENTITY", "head_surface_from_json", "head_expressions"]

HEAD_MODEL = "ict_facekit"  # the only head model head.json names
MAX_ABS_IDENTITY = 10.0  # identity modes are ~N(0, 1) (the fit's prior); 10 sigma is no head


def _numbers(value: Any, what: str) -> np.ndarray:
    if not isinstance(value, list) or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        got = type(value).__name__ if not isinstance(value, list) else "a list holding " + ", ".join(
            sorted({type(v).__name__ for v in value if not isinstance(v, (int, float)) or isinstance(v, bool)})
        )
        raise ValueError(f"{what} must be a list of numbers, got {got}")
    arr = np.asarray(value, dtype=np.float64)
    if not np.isfinite(arr).all() or not all(math.isfinite(float(v)) for v in value):
        raise ValueError(f"{what} must hold finite numbers")
    return arr


def head_surface_from_json(data: Any, expressions: Any, num_views: int | None = None, source: str = "head.json", names: list[str] | None = None):
    """``HeadSurface`` of head.json's content ``data`` and the photos' expressions.

    Args:
        data: the parsed JSON object ``{"model": "ict_facekit" (optional), "identity": [1..100 numbers]}``;
            other keys (``expressions``, ``frames``, see below) are allowed.
        expressions: ``[V, 53]`` ``ict53`` weights of the photos in [0, 1], in the order of the
            photos (array or nested lists); None takes ``data["expressions"]``.
        num_views: the number of photos the expressions must cover, or None.
        source: how messages name the JSON (a path, or ``"head"`` for the server's part).
        names: the photos' file names, in their order: ``data["frames"]`` as head.json holds it, an
            object by crop file name, is read for them (none used when a name has no entry, as the
            Python client and the browser demo do). Without names, ``frames`` must be a list, one
            ``[left, top, right, bottom]`` per photo in their order (the server's ``head`` part).
            Optional either way (absent: no padding known).
    Returns:
        ``fastgha_core.model.surface.HeadSurface`` (identity ``[K <= 100]``, expressions ``[V, 53]``,
        ``frames`` ``[V, 4]`` or None).
    Raises:
        ValueError: naming ``source`` and what was expected vs what came (not an object, another
            model, identity not 1..100 numbers within +-MAX_ABS_IDENTITY, expressions not [V, 53] in
            [0, 1], V != ``num_views``, or frames that are not one ``[left, top, right, bottom]``
            with right > left and bottom > top per photo).
    """
    from .model.surface import HeadSurface

    if not isinstance(data, dict):
        raise ValueError(f"{source}: expected a JSON object {{\"model\": \"{HEAD_MODEL}\", \"identity\": [...]}}, got {type(data).__name__}")
    model = data.get("model", HEAD_MODEL)
    if model != HEAD_MODEL:
        raise ValueError(f"{source}: expected \"model\": \"{HEAD_MODEL}\" (the head `fastgha track` fits), got {model!r}")
    if "identity" not in data:
        raise ValueError(f"{source}: expected an 'identity' list (ICT-FaceKit identity coefficients), got keys {sorted(data)}")
    ident = _numbers(data["identity"], f"{source}: identity")
    if not 1 <= len(ident) <= 100:
        raise ValueError(f"{source}: identity must hold 1 to 100 ICT-FaceKit coefficients, got {len(ident)}")
    if np.abs(ident).max() > MAX_ABS_IDENTITY:
        raise ValueError(f"{source}: identity coefficients must lie in [-{MAX_ABS_IDENTITY:g}, {MAX_ABS_IDENTITY:g}] (modes ~ N(0, 1)), "
                         f"got {float(np.abs(ident).max()):.4g}")  # fmt: skip
    if expressions is None:
        if "expressions" not in data:
            raise ValueError(f"{source}: expected an 'expressions' list, one list of 53 ict53 weights per photo (expressions.json of `fastgha track`)")
        rows = data["expressions"]
        if not isinstance(rows, list) or not rows:
            raise ValueError(f"{source}: expressions must be a non-empty list (one list of 53 weights per photo), got {type(rows).__name__}")
        for i, r in enumerate(rows):
            if not isinstance(r, list) or len(r) != 53:
                got = f"{len(r)} values" if isinstance(r, list) else type(r).__name__
                raise ValueError(f"{source}: expressions[{i}] must be a list of 53 ict53 weights, got {got}")
        expr = np.stack([_numbers(r, f"{source}: expressions[{i}]") for i, r in enumerate(rows)])
    else:
        expr = np.asarray(expressions, dtype=np.float64)
        if expr.ndim != 2 or expr.shape[1] != 53:
            raise ValueError(f"{source}: expressions must be [V, 53] ict53 weights, got shape {list(expr.shape)}")
    if not np.isfinite(expr).all():
        raise ValueError(f"{source}: expressions must hold finite numbers")
    if expr.min() < 0.0 or expr.max() > 1.0:
        raise ValueError(f"{source}: ict53 expression weights must lie in [0, 1], got [{expr.min():.4g}, {expr.max():.4g}]")
    if num_views is not None and expr.shape[0] != num_views:
        raise ValueError(f"{source}: expressions for {expr.shape[0]} photo(s), but {num_views} photo(s) came; send one per photo, in their order")
    return HeadSurface(ident.astype(np.float32), expr.astype(np.float32), None, _frames(data.get("frames"), len(expr), names, source))


def _frames(value: Any, views: int, names: list[str] | None, source: str) -> np.ndarray | None:
    """``[views, 4]`` frames of head.json's ``frames`` (module doc), or None when absent.

    A frame's values may lie outside [0, 1]: where the photo reaches past the crop's edge (a
    tight crop inside a big photo) it is, e.g., ``[-0.5, 0.1, 1.7, 2.3]``, and only the
    part of the crop beyond it is padding (``HeadSurface.padding``)."""
    if value is None:
        return None
    labels = [f"frames[{i}]" for i in range(views)]
    if isinstance(value, dict):
        if names is None:
            raise ValueError(f"{source}: frames by file name need the photos' names; send a list, one [left, top, right, bottom] per photo in their order")
        missing = [n for n in names if n not in value]
        if missing:  # a photo added after tracking: no frame known for it, so none used
            log.warning("%s: frames has no entry for %s (of %s); the crops' padding reads as background", source, ", ".join(missing[:4]), ", ".join(sorted(value)[:4]))
            return None
        value, labels = [value[n] for n in names], [f"frames[{n!r}]" for n in names]
    if not isinstance(value, list) or len(value) != views:
        got = f"{len(value)} entries" if isinstance(value, list) else type(value).__name__
        raise ValueError(f"{source}: frames must hold one [left, top, right, bottom] per photo ({views}), got {got}")
    rows = []
    for label, r in zip(labels, value):
        r = _numbers(r, f"{source}: {label}")
        if len(r) != 4:
            raise ValueError(f"{source}: {label} must be [left, top, right, bottom] (4 numbers, fractions of the crop), got {len(r)} value(s)")
        if r[2] <= r[0] or r[3] <= r[1]:
            raise ValueError(f"{source}: {label} = {r.tolist()} must have right > left and bottom > top (fractions of the crop)")
        rows.append(r)
    return np.stack(rows)


def head_expressions(surface, model):
    """``[V, 53]`` float32 tensor of the head's expressions for ``model.reconstruct(expressions=...)``
    when the model's expression space is ``ict53`` (they are then undone for a neutral canonical
    head), else None (a model in another space has nothing to undo)."""
    import torch

    if getattr(model.config, "expression_space", None) != "ict53":
        return None
    return torch.from_numpy(np.asarray(surface.expressions, dtype=np.float32))
