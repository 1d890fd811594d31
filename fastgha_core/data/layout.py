"""Our one on-disk dataset layout (documented in ``docs/data-format.md``) and request folders.

::

    root/<subject>/<sequence>/
        meta.json          format, version, expression_space, T, C, image size, file formats, depth unit
        cameras.json       our camera schema: a JSON array of C cameras {"K", "w2c", "width", "height"}
        expressions.npy    [T, E] float32 expression codes (E from expression_space)
        timesteps/<t:05d>/
            <c:02d>.png|jpg        image, uint8 RGB, background already BACKGROUND_RGB
            <c:02d>_mask.png       uint8 alpha (0..255)
            <c:02d>_depth.png      uint16 camera z in units of meta["depth_unit_m"] (1e-4 m), 0 = none
            cameras.json           only when cameras change over time: the C cameras of this timestep

``write_sequence`` writes any ``SequenceSource``; ``open_dataset`` finds every sequence under a
root and returns lazy ``LayoutSequence`` readers (files are read on ``view``). Every reader of
another format (Ava-256, NeRSemble, VHAP) yields the same in-memory ``View``; converting one of them
to this layout is ``write_sequence(root, reader)``.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
from PIL import Image

from ..cameras import Cameras, cameras_from_json, cameras_to_json
from ..images import read_image, read_mask
from .sample import SequenceSource, View

__all__ = [
    "LAYOUT_FORMAT",
    "LAYOUT_VERSION",
    "DEPTH_UNIT_M",
    "LayoutSequence",
    "write_sequence",
    "open_dataset",
    "write_request_folder",
    "save_image",
    "load_image",
    "save_mask",
    "load_mask",
    "save_depth",
    "load_depth",
]

logger = logging.getLogger(__name__)

LAYOUT_FORMAT = "fastgha-sequence"
LAYOUT_VERSION = 1
DEPTH_UNIT_M = 1e-4  # 16-bit depth PNGs count tenths of a millimetre (max 6.55 m)
_IMAGE_FORMATS = ("png", "jpg")


# ---------------------------------------------------------------------------- file helpers
def _to_hwc_uint8(image: torch.Tensor | np.ndarray) -> np.ndarray:
    a = image.detach().cpu().numpy() if isinstance(image, torch.Tensor) else np.asarray(image)
    if a.ndim != 3 or a.shape[0] != 3:
        raise ValueError(f"image must be [3, H, W] float in [0, 1], got shape {a.shape}")
    return np.ascontiguousarray((np.clip(a, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8).transpose(1, 2, 0))


def save_image(path: str | Path, image, jpeg_quality: int = 95) -> None:
    """Write ``image [3, H, W]`` in [0, 1] as PNG or JPEG (by suffix)."""
    path = Path(path)
    im = Image.fromarray(_to_hwc_uint8(image), mode="RGB")
    if path.suffix.lower() in (".jpg", ".jpeg"):
        im.save(path, quality=int(jpeg_quality), subsampling=0 if jpeg_quality >= 95 else 2, optimize=False)
    else:
        im.save(path, compress_level=6)


def load_image(path: str | Path) -> torch.Tensor:
    """``[3, H, W]`` float32 in [0, 1] from an image file (upright and 8-bit: ``fastgha_core.images``)."""
    a = read_image(path).rgb
    return torch.from_numpy(a.astype(np.float32) / 255.0).permute(2, 0, 1).contiguous()


def save_mask(path: str | Path, mask) -> None:
    """Write ``mask [1, H, W]`` (or ``[H, W]``) in [0, 1] as an 8-bit PNG."""
    m = mask.detach().cpu().numpy() if isinstance(mask, torch.Tensor) else np.asarray(mask)
    m = m.reshape(m.shape[-2:])
    Image.fromarray((np.clip(m, 0, 1) * 255.0 + 0.5).astype(np.uint8), mode="L").save(path, compress_level=6)


def load_mask(path: str | Path) -> torch.Tensor:
    """``[1, H, W]`` float32 in [0, 1] (16-bit masks scaled, not clipped: ``fastgha_core.images``)."""
    a = read_mask(path)
    return torch.from_numpy(a.astype(np.float32) / 255.0)[None]


def save_depth(path: str | Path, depth, unit_m: float = DEPTH_UNIT_M) -> None:
    """Write ``depth [1, H, W]`` (metres, 0 = none) as a 16-bit PNG in units of ``unit_m``."""
    d = depth.detach().cpu().numpy() if isinstance(depth, torch.Tensor) else np.asarray(depth)
    d = d.reshape(d.shape[-2:]).astype(np.float64)
    q = np.clip(np.rint(d / unit_m), 0, 65535).astype(np.uint16)
    Image.fromarray(q).save(path, compress_level=6)


def load_depth(path: str | Path, unit_m: float = DEPTH_UNIT_M) -> torch.Tensor:
    """``[1, H, W]`` float32 metres (0 = no value) from a 16-bit PNG."""
    with Image.open(path) as im:
        a = np.asarray(im).astype(np.float32)
    return torch.from_numpy(a * np.float32(unit_m))[None]


def _write_json(path: Path, obj) -> None:
    path.write_text(json.dumps(obj, indent=1) + "\n")


# ---------------------------------------------------------------------------- writing
def _same_cameras(a: Cameras, b: Cameras) -> bool:
    return (a.width, a.height) == (b.width, b.height) and torch.equal(a.K, b.K) and torch.equal(a.w2c, b.w2c)


def write_sequence(
    root: str | Path,
    source: SequenceSource,
    image_format: str = "png",
    jpeg_quality: int = 95,
    depth: bool = True,
    progress: Callable[[int], None] | None = None,
    extra_meta: dict | None = None,
) -> Path:
    """Write ``source`` to ``root/<subject>/<sequence>/``; returns that folder.

    ``progress(n)`` is called after each written view (for a progress bar). Output bytes depend
    only on the source's views and the arguments.
    """
    if image_format not in _IMAGE_FORMATS:
        raise ValueError(f"image_format must be one of {_IMAGE_FORMATS}, got {image_format!r}")
    T, C = int(source.num_timesteps), int(source.num_cameras)
    if T < 1 or C < 1:
        raise ValueError(f"source must have at least one timestep and camera, got T={T}, C={C}")
    out = Path(root) / str(source.subject) / str(source.sequence)
    out.mkdir(parents=True, exist_ok=True)
    cams0 = source.cameras(0).flatten()
    if len(cams0) != C:
        raise ValueError(f"source.cameras(0) has {len(cams0)} cameras but num_cameras is {C}")
    varying = any(not _same_cameras(source.cameras(t).flatten(), cams0) for t in range(1, T))
    exprs = np.stack([np.asarray(source.expression(t), dtype=np.float32) for t in range(T)])  # [T, E]
    np.save(out / "expressions.npy", exprs)
    _write_json(out / "cameras.json", cameras_to_json(cams0))
    has_depth = depth
    views_at = getattr(source, "views", None)
    for t in range(T):
        tdir = out / "timesteps" / f"{t:05d}"
        tdir.mkdir(parents=True, exist_ok=True)
        if varying:
            _write_json(tdir / "cameras.json", cameras_to_json(source.cameras(t).flatten()))
        views = views_at(t) if callable(views_at) else [source.view(t, c) for c in range(C)]
        for c, v in enumerate(views):
            save_image(tdir / f"{c:02d}.{image_format}", v.image, jpeg_quality)
            save_mask(tdir / f"{c:02d}_mask.png", v.mask)
            if depth and v.depth is not None:
                save_depth(tdir / f"{c:02d}_depth.png", v.depth)
            elif depth:
                has_depth = False
            if progress is not None:
                progress(1)
    meta = {
        "format": LAYOUT_FORMAT,
        "version": LAYOUT_VERSION,
        "subject": str(source.subject),
        "sequence": str(source.sequence),
        "expression_space": str(source.expression_space),
        "num_timesteps": T,
        "num_cameras": C,
        "width": cams0.width,
        "height": cams0.height,
        "image_format": image_format,
        "has_mask": True,
        "has_depth": bool(has_depth),
        "depth_unit_m": DEPTH_UNIT_M,
        "cameras_per_timestep": bool(varying),
    }
    if extra_meta:
        meta["extra"] = extra_meta
    _write_json(out / "meta.json", meta)  # written last: a folder with meta.json is complete
    return out


def write_request_folder(
    folder: str | Path,
    views: Sequence[View],
    cameras: Cameras | Sequence[Cameras],
    image_format: str = "png",
    jpeg_quality: int = 95,
    masks: bool = True,
    info: dict | None = None,
) -> Path:
    """A request folder (``cameras.load_request_folder``): ``00.png, 01.png, ...`` sorted by name,
    ``cameras.json`` (array, same order), ``<name>_mask.png`` when ``masks``, optional ``info.json``."""
    if image_format not in _IMAGE_FORMATS:
        raise ValueError(f"image_format must be one of {_IMAGE_FORMATS}, got {image_format!r}")
    cams = Cameras.stack([c.flatten()[i] for c in ([cameras] if isinstance(cameras, Cameras) else cameras) for i in range(len(c.flatten()))])
    if len(cams) != len(views):
        raise ValueError(f"need one camera per view, got {len(views)} views and {len(cams)} cameras")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for i, v in enumerate(views):
        save_image(folder / f"{i:02d}.{image_format}", v.image, jpeg_quality)
        if masks:
            save_mask(folder / f"{i:02d}_mask.png", v.mask)
    _write_json(folder / "cameras.json", cameras_to_json(cams))
    if info is not None:
        _write_json(folder / "info.json", info)
    return folder


# ---------------------------------------------------------------------------- reading
class LayoutSequence:
    """A ``SequenceSource`` reading one ``root/<subject>/<sequence>/`` folder lazily."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        meta_file = self.folder / "meta.json"
        if not meta_file.exists():
            raise ValueError(f"{self.folder} is not a sequence folder of our layout (no meta.json)")
        try:
            meta = json.loads(meta_file.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"{meta_file} does not parse as JSON: {e}") from None
        if not isinstance(meta, dict) or meta.get("format") != LAYOUT_FORMAT:
            raise ValueError(f"{meta_file}: format is {meta.get('format') if isinstance(meta, dict) else meta!r}, expected {LAYOUT_FORMAT!r}")
        if int(meta.get("version", 0)) > LAYOUT_VERSION:
            raise ValueError(f"{meta_file}: layout version {meta.get('version')} is newer than supported {LAYOUT_VERSION}")
        self.meta = meta
        self.subject = str(meta["subject"])
        self.sequence = str(meta["sequence"])
        self.expression_space = str(meta["expression_space"])
        self._T, self._C = int(meta["num_timesteps"]), int(meta["num_cameras"])
        self._ext = meta["image_format"]
        cam_file = self.folder / "cameras.json"
        if not cam_file.is_file():
            raise ValueError(f"{self.folder} has meta.json but no cameras.json: the sequence is incomplete")
        self._cams = Cameras.stack(cameras_from_json(cam_file.read_text()))
        if len(self._cams) != self._C:
            raise ValueError(f"{self.folder}/cameras.json has {len(self._cams)} cameras, meta.json says {self._C}")
        self._expr = np.load(self.folder / "expressions.npy", mmap_mode="r")  # [T, E]
        if self._expr.shape[0] != self._T:
            raise ValueError(f"{self.folder}/expressions.npy has {self._expr.shape[0]} rows, meta.json says {self._T}")

    def __repr__(self) -> str:
        return f"LayoutSequence({self.folder})"

    @property
    def num_timesteps(self) -> int:
        return self._T

    @property
    def num_cameras(self) -> int:
        return self._C

    def _tdir(self, t: int) -> Path:
        if not 0 <= int(t) < self._T:
            raise IndexError(f"timestep {t} out of range [0, {self._T})")
        return self.folder / "timesteps" / f"{int(t):05d}"

    def cameras(self, t: int) -> Cameras:  # [C]
        tdir = self._tdir(t)
        if self.meta.get("cameras_per_timestep"):
            return Cameras.stack(cameras_from_json((tdir / "cameras.json").read_text()))
        return self._cams

    def expression(self, t: int) -> torch.Tensor:  # [E]
        self._tdir(t)
        return torch.from_numpy(np.array(self._expr[int(t)], dtype=np.float32))

    def view(self, t: int, c: int) -> View:
        tdir = self._tdir(t)
        if not 0 <= int(c) < self._C:
            raise IndexError(f"camera {c} out of range [0, {self._C})")
        stem = tdir / f"{int(c):02d}"
        image = load_image(stem.with_name(stem.name + f".{self._ext}"))
        mask_file = stem.with_name(stem.name + "_mask.png")
        mask = load_mask(mask_file) if mask_file.exists() else torch.ones(1, *image.shape[1:])
        depth_file = stem.with_name(stem.name + "_depth.png")
        unit = float(self.meta.get("depth_unit_m", DEPTH_UNIT_M))
        depth = load_depth(depth_file, unit) if depth_file.exists() else None
        return View(image=image, mask=mask, depth=depth)


def open_dataset(root: str | Path) -> list[LayoutSequence]:
    """Every sequence under ``root`` (a dataset root, a subject folder or a sequence folder),
    sorted by (subject, sequence). Folders without ``meta.json`` (e.g. ``request/``) are skipped."""
    root = Path(root)
    if not root.is_dir():
        raise ValueError(f"dataset root {root} does not exist or is not a folder")
    metas = sorted({*root.glob("meta.json"), *root.glob("*/meta.json"), *root.glob("*/*/meta.json")})
    seqs = [LayoutSequence(m.parent) for m in metas]
    if not seqs:
        raise ValueError(f"no sequences of our layout under {root} (expected <subject>/<sequence>/meta.json)")
    return sorted(seqs, key=lambda s: (s.subject, s.sequence))
