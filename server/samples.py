"""Read-only routes serving the shipped sample subjects, for the browser demo's one-click load.

``fastgha_core/assets/samples/<name>/`` holds ``request/`` (photos, ``cameras.json``, masks),
``expressions.npy`` (``[T, E]`` float32, the subject's expression sequence) and ``orbit.json``
(cameras of an orbit). Routes:

* ``GET /v1/samples`` -> ``{"samples": [{"name", "images": [file names], "masks": [file names],
  "has_expressions", "num_expression_frames", "has_orbit"}]}``
* ``GET /v1/samples/{name}/{file}`` -> a request photo or mask (by its file name),
  ``cameras.json``, ``orbit.json``, or ``expressions.json`` (``expressions.npy`` as
  ``{"frames": [[E floats], ...], "num_frames", "dim"}``).

Names are checked against a strict pattern and files against the folder's listing: nothing
a client sends is ever joined onto a path. Unknown names or files answer
``404 sample_not_found`` / ``404 sample_file_not_found``. The samples are public assets: no
authentication.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import numpy as np
from fastapi import APIRouter
from fastapi.responses import FileResponse, JSONResponse, Response

from .errors import ApiError

__all__ = ["make_samples_router", "DEFAULT_SAMPLES_DIR", "list_sample_entries"]

log = logging.getLogger(__name__)

DEFAULT_SAMPLES_DIR = Path(__file__).resolve().parent.parent / "fastgha_core" / "assets" / "samples"
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
_IMAGE_SUFFIXES = {".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".png": "image/png"}
MAX_EXPRESSION_FRAMES = 10_000  # a sample sequence longer than this is truncated in expressions.json


def _is_mask(p: Path) -> bool:
    return p.stem.endswith("_mask")


def _sample_dirs(root: Path) -> dict[str, Path]:
    if not root.is_dir():
        return {}
    return {
        p.name: p
        for p in sorted(root.iterdir())
        if p.is_dir() and _NAME_RE.match(p.name) and (p / "request" / "cameras.json").is_file()
    }


def _request_files(sample: Path) -> dict[str, Path]:
    """file name -> path of the request photos and masks (masks/ subfolder entries as ``masks/<name>``)."""
    req = sample / "request"
    out = {p.name: p for p in sorted(req.iterdir()) if p.is_file() and p.suffix.lower() in _IMAGE_SUFFIXES}
    if (req / "masks").is_dir():
        for p in sorted((req / "masks").iterdir()):
            if p.is_file() and p.suffix.lower() in _IMAGE_SUFFIXES:
                out[f"masks/{p.name}"] = p
    return out


def list_sample_entries(root: Path) -> list[dict]:
    """The ``GET /v1/samples`` entries of the samples under ``root``."""
    entries = []
    for name, d in _sample_dirs(root).items():
        files = _request_files(d)
        images = [f for f, p in files.items() if "/" not in f and not _is_mask(p)]
        masks = [f for f, p in files.items() if "/" in f or _is_mask(p)]
        n_expr = 0
        if (d / "expressions.npy").is_file():
            try:
                n_expr = int(np.load(d / "expressions.npy", mmap_mode="r").shape[0])
            except (ValueError, OSError):
                log.warning("sample %s: expressions.npy is unreadable", name)
        entries.append(
            {
                "name": name,
                "images": images,
                "masks": masks,
                "has_expressions": n_expr > 0,
                "num_expression_frames": n_expr,
                "has_orbit": (d / "orbit.json").is_file(),
            }
        )
    return entries


def make_samples_router(root: str | Path | None = None) -> APIRouter:
    """Routes ``/v1/samples`` over the sample folders in ``root`` (default: the shipped ones).

    Include it **before** the static mount at ``/`` (which would shadow it):
    ``app.include_router(make_samples_router())``.
    """
    base = Path(root) if root is not None else DEFAULT_SAMPLES_DIR
    router = APIRouter(prefix="/v1/samples", tags=["samples"])

    def _sample(name: str) -> Path:
        d = _sample_dirs(base).get(name) if _NAME_RE.match(name) else None
        if d is None:
            raise ApiError(404, "sample_not_found", f"no sample named {name[:64]!r}; GET /v1/samples lists them")
        return d

    @router.get("")
    def list_samples() -> dict:
        return {"samples": list_sample_entries(base)}

    @router.get("/{name}/{file:path}")
    def sample_file(name: str, file: str) -> Response:
        d = _sample(name)
        if file == "cameras.json":
            return FileResponse(d / "request" / "cameras.json", media_type="application/json")
        if file == "orbit.json" and (d / "orbit.json").is_file():
            return FileResponse(d / "orbit.json", media_type="application/json")
        if file == "expressions.json" and (d / "expressions.npy").is_file():
            arr = np.asarray(np.load(d / "expressions.npy"), dtype=np.float32)  # [T, E]
            if arr.ndim != 2:
                raise ApiError(404, "sample_file_not_found", f"sample {name}: expressions.npy is not [T, E]")
            arr = arr[:MAX_EXPRESSION_FRAMES]
            meta = {}
            if (d / "meta.json").is_file():
                try:
                    meta = json.loads((d / "meta.json").read_text())
                except ValueError:
                    meta = {}
            body = {"frames": np.round(arr.astype(np.float64), 5).tolist(), "num_frames": int(arr.shape[0]), "dim": int(arr.shape[1])}
            for k in ("expression_space", "fps"):
                if isinstance(meta, dict) and k in meta:
                    body[k] = meta[k]
            return JSONResponse(body)
        files = _request_files(d)
        if file in files:
            p = files[file]
            return FileResponse(p, media_type=_IMAGE_SUFFIXES[p.suffix.lower()])
        raise ApiError(404, "sample_file_not_found", f"sample {name} has no file {file[:64]!r}")

    return router
