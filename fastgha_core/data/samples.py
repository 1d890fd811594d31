"""The shipped sample subjects (``fastgha_core/assets/samples/<name>/``).

Three held-out synthetic subjects at 256², made by ``python -m fastgha_core.data.make_samples``.
Each folder holds::

    request/       00.jpg .. 03.jpg, 00_mask.png .., cameras.json, info.json   (a request folder)
    expressions.npy  [T, 53] float32 ict53 codes of a sequence with strong expressions
    orbit.json     T cameras in our schema (``cameras.orbit_cameras``), one per frame
    gt/            0000.jpg .. ground truth: frame t = expression t seen from orbit camera t
    meta.json      seed, subject, expression_space, frame count, resolution

The demo, the server tests and the browser demo use them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..cameras import Cameras, cameras_from_json, load_request_folder
from .layout import load_image, load_mask

__all__ = ["SAMPLES_DIR", "Sample", "info_expressions", "list_samples", "load_sample"]

SAMPLES_DIR = Path(__file__).resolve().parent.parent / "assets" / "samples"


@dataclass
class Sample:
    """One shipped sample subject, loaded."""

    name: str
    folder: Path
    request_dir: Path  # pass to ``cameras.load_request_folder`` or the server
    request_images: Tensor  # [V, 3, H, W] float32 in [0, 1], white background
    request_masks: Tensor  # [V, 1, H, W] float32
    request_cameras: Cameras  # [V]
    expression_space: str  # "ict53"
    expressions: Tensor  # [T, E] float32
    orbit_cameras: Cameras  # [T]
    gt_frames: Tensor | None  # [T, 3, H, W] float32 (None when loaded with gt=False)
    meta: dict
    request_expressions: Tensor | None = None  # [V, E] float32 the input photos' codes (request/info.json), or None


def info_expressions(folder: str | Path, views: int, dim: int) -> Tensor | None:
    """``[views, dim]`` float32 expression codes of a request folder's photos from its ``info.json``
    (``"expressions"``, written by ``make_samples`` for the synthetic samples: each input photo's
    code, in the photos' sorted order), or None when the file or the key is absent.
    Raises ``ValueError`` when they do not have that shape."""
    info = Path(folder) / "info.json"
    if not info.exists():
        return None
    data = json.loads(info.read_text())
    if "expressions" not in data:
        return None
    codes = torch.tensor(data["expressions"], dtype=torch.float32)
    if tuple(codes.shape) != (views, dim):
        raise ValueError(f"{info}: expressions must be {views} x {dim}, got {list(codes.shape)}")
    return codes


def list_samples(root: str | Path | None = None) -> list[str]:
    """Names of the sample subjects (sorted)."""
    root = SAMPLES_DIR if root is None else Path(root)
    if not root.is_dir():
        return []
    return sorted(p.name for p in root.iterdir() if (p / "meta.json").exists())


def load_sample(name: str | None = None, gt: bool = True, root: str | Path | None = None) -> Sample:
    """Load sample ``name`` (default: the first one). ``gt=False`` skips the ground-truth frames."""
    root = SAMPLES_DIR if root is None else Path(root)
    names = list_samples(root)
    if not names:
        raise FileNotFoundError(f"no sample subjects under {root}; run `python -m fastgha_core.data.make_samples`")
    name = names[0] if name is None else name
    if name not in names:
        raise ValueError(f"unknown sample {name!r}; expected one of {names}")
    folder = root / name
    meta = json.loads((folder / "meta.json").read_text())
    paths, cams = load_request_folder(folder / "request")
    images = torch.stack([load_image(p) for p in paths])  # [V, 3, H, W]
    masks = []
    for p in paths:
        m = p.with_name(p.stem + "_mask.png")
        masks.append(load_mask(m) if m.exists() else torch.ones(1, *images.shape[-2:]))
    expressions = torch.from_numpy(np.load(folder / "expressions.npy").astype(np.float32))  # [T, E]
    orbit = Cameras.stack(cameras_from_json((folder / "orbit.json").read_text()))
    if len(orbit) != expressions.shape[0]:
        raise ValueError(f"sample {name}: {len(orbit)} orbit cameras but {expressions.shape[0]} expression frames")
    frames = None
    if gt:
        files = sorted((folder / "gt").glob("*.jpg"))
        if len(files) != expressions.shape[0]:
            raise ValueError(f"sample {name}: {len(files)} ground-truth frames but {expressions.shape[0]} expression frames")
        frames = torch.stack([load_image(f) for f in files])
    return Sample(
        name=name,
        folder=folder,
        request_dir=folder / "request",
        request_images=images,
        request_masks=torch.stack(masks),
        request_cameras=Cameras.stack(cams),
        expression_space=str(meta.get("expression_space", "ict53")),
        expressions=expressions,
        orbit_cameras=orbit,
        gt_frames=frames,
        meta=meta,
        request_expressions=info_expressions(folder / "request", len(paths), expressions.shape[1]),
    )
