"""Readers for real multi-view head datasets: Ava-256, NeRSemble and VHAP exports.

Every reader returns ``list[SequenceSource]`` (see ``data/sample.py``) with the same in-memory
types as the synthetic generator and our on-disk layout:

- cameras are *head-centric*: the per-frame head pose (dataset world <- head) is folded into
  ``w2c``, so ``cameras(t)`` changes with ``t`` and the avatar never moves;
- ``view(t, c).image [3, H, W]`` float32 in [0, 1], composited over ``BACKGROUND_RGB`` with the
  mask; ``mask [1, H, W]``; ``depth [1, H, W]`` only when a precomputed depth prior exists;
- ``K`` in pixels of the image as read, corner pixel convention: calibrations are parsed by the
  converters of ``cameras.py`` (OpenCV calibrations of Ava-256 / NeRSemble get +0.5 on the
  principal point; VHAP ``transforms.json`` stores ``cy`` from the bottom row and is read as
  ``h - cy``) and scaled from the calibration size
  to the image size.

Precomputed depth priors (VGGT, offline) are read when present: float32 ``.npy`` in metres or
16-bit ``.png`` in millimetres (0 = no value), holding camera ``z`` of the *head-centric*
camera in metres (= the dataset camera's z converted to metres). Where each reader looks is
written in its docstring and in ``docs/datasets.md``.

Formats were checked against the datasets' public loaders: facebookresearch/ava-256 and
goliath (``camera_calibration.json`` "KRT" list, ``image/cam<ID>.zip`` with
``cam<ID>/<frame:06d>.avif``, ``head_pose/head_pose.zip`` with ``<frame:06d>.txt`` 3x4),
tobias-kirschstein/nersemble(-data, -benchmark) (``camera_params.json`` with ``world_2_cam`` and
``intrinsics``, mp4 or extracted frames, ``flame2023_tracking.npz``) and ShenhanQian/VHAP
(``export_as_nerf_dataset.py``: ``transforms*.json`` + ``flame_param/<t:05d>.npz``).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from ..cameras import (
    Cameras,
    fold_head_pose,
    head_pose_matrix,
    read_ava256_calibration_json,
    read_nersemble_camera_params,
    read_transforms_json,
)
from ..constants import BACKGROUND_RGB
from ..expressions import flame120_from_axis_angle
from ..images import decode_pixels_bytes
from .sample import View

__all__ = [
    "MissingViewError",
    "RealSequence",
    "open_ava256",
    "open_nersemble",
    "open_vhap",
    "AVA256_CALIBRATION_SIZE",
    "NERSEMBLE_CALIBRATION_SIZE",
]

logger = logging.getLogger(__name__)

# Full-resolution sensor sizes (width, height) the calibrations refer to.
AVA256_CALIBRATION_SIZE = (2668, 4096)  # Ava-256 dome cameras, portrait
NERSEMBLE_CALIBRATION_SIZE = (2200, 3208)  # NeRSemble v2 (README: intrinsics for 3208x2200 images)
# Ava-256 ``segmentation_parts`` classes kept as foreground (datasheet: 1 hair, 2 body, 3 chair,
# 4 apparel, 5 lenses, 6-10 lips/teeth/tongue). The chair (3) and 0 are background.
AVA256_FOREGROUND_CLASSES = (1, 2, 4, 5, 6, 7, 8, 9, 10)

_IMAGE_EXTS = (".avif", ".png", ".jpg", ".jpeg", ".webp")
_DEPTH_EXTS = (".npy", ".png")


class MissingViewError(FileNotFoundError):
    """A (timestep, camera) image listed by the dataset is absent (e.g. a dropped frame)."""


# ---------------------------------------------------------------- file containers
class _Container:
    """A zip archive or an extracted folder whose files are found by base name.

    Real archives nest files differently (``cam400943/000123.avif`` or ``000123.avif``), so an
    index ``base name -> member`` is built once on first use. Zip handles are reopened after a
    fork (DataLoader workers) and are not pickled.
    """

    def __init__(self, path: Path):
        self.path = Path(path)
        self._index: dict[str, str] | None = None
        self._zip: zipfile.ZipFile | None = None
        self._pid = -1

    @staticmethod
    def find(base: Path, name: str) -> "_Container | None":
        """``base/name.zip`` or the folder ``base/name``, whichever exists."""
        z = base / f"{name}.zip"
        if z.is_file():
            return _Container(z)
        d = base / name
        return _Container(d) if d.is_dir() else None

    def __getstate__(self) -> dict:
        return {"path": self.path, "_index": self._index, "_zip": None, "_pid": -1}

    @property
    def is_zip(self) -> bool:
        return self.path.suffix.lower() == ".zip"

    def _zipfile(self) -> zipfile.ZipFile:
        if self._zip is None or self._pid != os.getpid():
            self._zip = zipfile.ZipFile(self.path, "r")
            self._pid = os.getpid()
        return self._zip

    def _build_index(self) -> dict[str, str]:
        if self._index is None:
            index: dict[str, str] = {}
            if self.is_zip:
                names = [n for n in self._zipfile().namelist() if not n.endswith("/")]
            else:
                names = [str(p.relative_to(self.path)) for p in self.path.rglob("*") if p.is_file()]
            for n in sorted(names):
                index.setdefault(Path(n).name, n)
            self._index = index
        return self._index

    def names(self) -> list[str]:
        return list(self._build_index())

    def read(self, stem: str, exts: Sequence[str]) -> tuple[bytes, str] | None:
        """Bytes and suffix of the first file named ``stem + ext``, or None."""
        index = self._build_index()
        for ext in exts:
            member = index.get(stem + ext)
            if member is not None:
                if self.is_zip:
                    return self._zipfile().read(member), ext
                return (self.path / member).read_bytes(), ext
        return None


# ---------------------------------------------------------------- decoding helpers
def _decode_image(data: bytes, name: str = "dataset image") -> np.ndarray:
    """Encoded image -> uint8 ``[H, W, C]`` (C = 1, 3 or 4), upright, 8-bit (``fastgha_core.images``:
    EXIF orientation applied, 16-bit grey scaled by 255/65535). AVIF needs Pillow >= 11.2 with libavif."""
    return decode_pixels_bytes(data, name)


def _decode_depth(data: bytes, ext: str) -> np.ndarray:
    """Depth file -> float32 ``[H, W]`` metres (0 = no value)."""
    if ext == ".npy":
        d = np.load(io.BytesIO(data), allow_pickle=False).astype(np.float32)
    else:
        with Image.open(io.BytesIO(data)) as im:
            d = np.asarray(im).astype(np.float32) / 1000.0  # 16-bit millimetres
    d = np.squeeze(d)
    if d.ndim != 2:
        raise ValueError(f"depth prior must be a 2-D map, got shape {d.shape}")
    return np.nan_to_num(d, nan=0.0, posinf=0.0, neginf=0.0)


def _resize_u8(arr: np.ndarray, width: int, height: int, nearest: bool = False) -> np.ndarray:
    if arr.shape[1] == width and arr.shape[0] == height:
        return arr
    squeeze = arr.ndim == 3 and arr.shape[2] == 1
    im = Image.fromarray(arr[..., 0] if squeeze else arr)
    im = im.resize((width, height), Image.NEAREST if nearest else Image.BILINEAR)
    out = np.asarray(im)
    return out[..., None] if squeeze or out.ndim == 2 else out


def _resize_depth(d: np.ndarray, width: int, height: int) -> np.ndarray:
    if d.shape == (height, width):
        return d
    # nearest: averaging depth across silhouettes would invent surfaces
    return np.asarray(Image.fromarray(d, mode="F").resize((width, height), Image.NEAREST), dtype=np.float32)


def compose_view(rgb: np.ndarray, alpha: np.ndarray | None, depth: np.ndarray | None) -> View:
    """uint8 ``rgb [H, W, 3|4]``, float ``alpha [H, W]`` in [0, 1] (None: the image's alpha
    channel, else all ones), ``depth [H, W]`` metres or None -> :class:`View` over BACKGROUND_RGB."""
    h, w = rgb.shape[:2]
    if alpha is None:
        alpha = rgb[..., 3].astype(np.float32) / 255.0 if rgb.shape[2] == 4 else np.ones((h, w), np.float32)
    if rgb.shape[2] == 1:
        rgb = np.repeat(rgb, 3, axis=2)
    img = torch.from_numpy(np.array(rgb[..., :3], dtype=np.uint8)).permute(2, 0, 1).float() / 255.0  # [3, H, W]
    a = torch.from_numpy(np.ascontiguousarray(alpha, dtype=np.float32)).clamp(0, 1)[None]  # [1, H, W]
    bg = torch.tensor(BACKGROUND_RGB, dtype=torch.float32).view(3, 1, 1)
    img = img * a + bg * (1.0 - a)
    dep = None if depth is None else torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32))[None]
    return View(image=img.contiguous(), mask=a.contiguous(), depth=dep)


# ---------------------------------------------------------------- camera helpers
# Dataset calibrations are parsed by the converters of ``cameras.py`` (which also move OpenCV
# principal points to our pixel-corner convention); this module scales them to the image size
# and folds the per-timestep head poses in.
def _rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    M = np.eye(4, dtype=np.float64)
    M[:3, :3] = R
    M[:3, 3] = t
    return M


def _orthonormalize(R: np.ndarray) -> np.ndarray:
    """Nearest rotation (SVD), removing the float noise of files written with few digits."""
    U, _, Vt = np.linalg.svd(R)
    Rn = U @ Vt
    if np.linalg.det(Rn) < 0:
        U[:, -1] *= -1
        Rn = U @ Vt
    return Rn


def _stack_resized(cams: Sequence[Cameras], image_size: tuple[int, int]) -> Cameras:
    """Single cameras calibrated at their own size -> one batch ``[C]`` for ``image_size`` (w, h)."""
    out = []
    for c in cams:
        sx, sy = image_size[0] / c.width, image_size[1] / c.height
        if abs(sx - sy) > 0.01 * max(sx, sy):
            raise ValueError(
                f"image size {image_size[0]}x{image_size[1]} does not have the aspect ratio of the calibration "
                f"size {c.width}x{c.height}; pass calibration_size=(width, height) of the calibrated images"
            )
        out.append(c.resize(*image_size))
    return Cameras.stack(out)


class _StaticCameras:
    """A fixed rig ``Cameras [C]`` plus per-timestep head poses ``head_to_world [T, 4, 4]``
    (rigid, metres) folded in as ``w2c_head = w2c @ head_to_world`` (``cameras.fold_head_pose``)."""

    def __init__(self, rig: Cameras, head_to_world: np.ndarray | Tensor | None):
        self.rig = rig
        self.head = None if head_to_world is None else torch.as_tensor(head_to_world, dtype=torch.float64)
        self.K = rig.K
        self.width, self.height = rig.width, rig.height

    def at(self, t: int) -> Cameras:
        if self.head is None:
            return self.rig
        return fold_head_pose(Cameras(self.rig.K, self.rig.w2c.double(), self.width, self.height), self.head[t]).to(dtype=torch.float32)


# ---------------------------------------------------------------- the common source type
@dataclass
class RealSequence:
    """One sequence of a real dataset, implementing ``SequenceSource``.

    Built by the ``open_*`` functions; ``loader(t, c) -> View`` reads one image lazily.
    ``expression_space`` is ``"flame120"``, or ``"none"`` when the dataset ships no expression
    tracking (then ``expression(t)`` is an empty ``[0]`` tensor and the training sampler refuses
    the source).
    """

    subject: str
    sequence: str
    expression_space: str
    _cameras: _StaticCameras
    _expressions: Tensor | None  # [T, E] or None
    _loader: Any  # callable (t, c) -> View
    _num_timesteps: int
    camera_names: list[str] = field(default_factory=list)
    frame_ids: list[int] = field(default_factory=list)

    @property
    def num_timesteps(self) -> int:
        return self._num_timesteps

    @property
    def num_cameras(self) -> int:
        return int(self._cameras.K.shape[0])

    def _check(self, t: int, c: int | None = None) -> None:
        if not 0 <= int(t) < self._num_timesteps:
            raise IndexError(f"{self.subject}/{self.sequence}: timestep {t} out of range [0, {self._num_timesteps})")
        if c is not None and not 0 <= int(c) < self.num_cameras:
            raise IndexError(f"{self.subject}/{self.sequence}: camera {c} out of range [0, {self.num_cameras})")

    def cameras(self, t: int) -> Cameras:  # batch [C]
        self._check(t)
        return self._cameras.at(int(t))

    def expression(self, t: int) -> Tensor:  # [E]
        self._check(t)
        if self._expressions is None:
            return torch.zeros(0)
        return self._expressions[int(t)].clone()

    def view(self, t: int, c: int) -> View:
        self._check(t, c)
        v = self._loader(int(t), int(c))
        h, w = v.image.shape[-2:]
        if (w, h) != (self._cameras.width, self._cameras.height):
            raise ValueError(
                f"{self.subject}/{self.sequence}: image (t={t}, camera {self.camera_names[c] if self.camera_names else c}) "
                f"is {w}x{h}, but the sequence's cameras describe {self._cameras.width}x{self._cameras.height}"
            )
        return v


def _read_image_size(data: bytes) -> tuple[int, int]:
    """(w, h) of the upright image (EXIF orientations 5-8 swap the stored sides), as _decode_image returns it."""
    with Image.open(io.BytesIO(data)) as im:
        w, h = im.size
        try:
            o = int(im.getexif().get(0x0112, 1))
        except Exception:
            o = 1
        return (h, w) if o in (5, 6, 7, 8) else (w, h)


# ================================================================ Ava-256
def _ava_head_pose(data: bytes) -> np.ndarray:
    """``head_pose/<frame>.txt`` (3x4 head -> world, mm) -> 4x4 in metres."""
    M = np.loadtxt(io.BytesIO(data), dtype=np.float64).reshape(-1, 4)[:3]
    return _rigid(_orthonormalize(M[:, :3]), M[:, 3] / 1000.0)


def _load_flame_fit(path: Path) -> tuple[np.ndarray, Tensor]:
    """An Ava-256 FLAME fit npz -> (frame ids [N], flame120 [N, 120])."""
    with np.load(path) as z:
        keys = set(z.files)
        if "frame_id" not in keys:
            raise ValueError(f"FLAME fit {path}: needs 'frame_id' (N,) plus 'flame120' (N,120) or expr/jaw_pose/eyes_pose; has {sorted(keys)}")
        ids = np.asarray(z["frame_id"]).astype(np.int64).reshape(-1)
        if "flame120" in keys:
            codes = torch.as_tensor(np.asarray(z["flame120"], dtype=np.float32))
            if codes.shape != (len(ids), 120):
                raise ValueError(f"FLAME fit {path}: flame120 must be ({len(ids)}, 120), got {tuple(codes.shape)}")
        elif {"expr", "jaw_pose", "eyes_pose"} <= keys:
            codes = flame120_from_axis_angle(z["expr"], z["jaw_pose"], z["eyes_pose"], z["eyelids"] if "eyelids" in keys else None)
        else:
            raise ValueError(f"FLAME fit {path}: needs 'flame120' or expr/jaw_pose/eyes_pose, has {sorted(keys)}")
    return ids, codes.float()


@dataclass
class _AvaLoader:
    """Reads one Ava-256 view (picklable, for DataLoader workers)."""

    name: str
    frames: list[int]
    cam_ids: list[str]
    images: dict
    segs: dict
    parts: dict
    depths: dict
    fg: np.ndarray  # [256] class id -> foreground

    def __call__(self, t: int, c: int) -> View:
        cam, name = self.cam_ids[c], f"{self.frames[t]:06d}"
        got = self.images[cam].read(name, _IMAGE_EXTS)
        if got is None:
            raise MissingViewError(f"Ava-256 {self.name}: no image for frame {name}, camera {cam}")
        rgb = _decode_image(got[0])
        h, w = rgb.shape[:2]
        alpha = None
        seg, part, dep = self.segs[cam], self.parts[cam], self.depths[cam]
        if seg is not None and (s := seg.read(name, (".png",))) is not None:
            alpha = (_resize_u8(_decode_image(s[0]), w, h, nearest=True)[..., 0] > 0).astype(np.float32)
        elif part is not None and (s := part.read(name, (".png",))) is not None:
            alpha = self.fg[_resize_u8(_decode_image(s[0]), w, h, nearest=True)[..., 0]]
        depth = None
        if dep is not None and (d := dep.read(name, _DEPTH_EXTS)) is not None:
            depth = _resize_depth(_decode_depth(*d), w, h)
        return compose_view(rgb[..., :3] if rgb.shape[2] == 4 else rgb, alpha, depth)


def open_ava256(
    root: str | Path,
    *,
    segments: Sequence[str] | None = None,
    cameras: Sequence[str] | None = None,
    flame_fit: str | Path | None = None,
    calibration_size: tuple[int, int] = AVA256_CALIBRATION_SIZE,
    head_axes: Sequence[Sequence[float]] | None = None,
    foreground_classes: Sequence[int] = AVA256_FOREGROUND_CLASSES,
) -> list[RealSequence]:
    """Open one Ava-256 capture; one :class:`RealSequence` per segment (``seg_id``).

    Args:
        root: the capture folder ``m--<date>--<time>--<ID>--GHS`` or its ``decoder`` folder:
            ``camera_calibration.json`` (``{"KRT": [{"cameraId", "K" (3x3, transposed), "T" (4x4
            w2c, transposed, mm)}]}``), ``frame_list.csv`` (``seg_id,frame_id``),
            ``image/cam<ID>.zip`` (``<frame:06d>.avif``), ``head_pose/head_pose.zip``
            (``<frame:06d>.txt``, 3x4 head -> world, mm), ``segmentation_parts/cam<ID>.zip``
            (``<frame:06d>.png`` class ids) or ``segmentation_fgbg/cam<ID>.zip``. Every zip may
            instead be an extracted folder of the same name (png/jpg images are accepted too).
        segments: keep only these ``seg_id`` values (default: all).
        cameras: keep only these camera ids (default: every calibrated camera with images).
        flame_fit: npz with ``frame_id [N]`` and ``flame120 [N, 120]`` (or FLAME ``expr``,
            ``jaw_pose``, ``eyes_pose``): Ava-256 ships no FLAME tracking, so without it the
            sequences have ``expression_space == "none"``. Frames absent from the fit are dropped.
        calibration_size: (width, height) of the images the calibration describes.
        head_axes: 3x3 rotation taking our canonical axes (+x subject's left, +y up, +z out of
            the face) to Ava-256's head frame; identity by default (not verified on real data:
            if renders come out rotated, pass the fix here).
        foreground_classes: ``segmentation_parts`` ids that count as the head.

    Depth priors are read from ``depth/cam<ID>.zip`` or ``depth/cam<ID>/`` (``<frame:06d>.npy|png``).
    """
    root = Path(root)
    if (root / "decoder" / "camera_calibration.json").exists():
        root = root / "decoder"
    calib_path = root / "camera_calibration.json"
    if not calib_path.exists():
        raise ValueError(f"{root} is not an Ava-256 capture: no camera_calibration.json (or decoder/camera_calibration.json)")
    calib = read_ava256_calibration_json(calib_path, width=calibration_size[0], height=calibration_size[1])
    fl_path = root / "frame_list.csv"
    if not fl_path.exists():
        raise ValueError(f"Ava-256 capture {root} has no frame_list.csv")
    with fl_path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or not {"seg_id", "frame_id"} <= set(rows[0]):
        raise ValueError(f"{fl_path}: expected columns seg_id,frame_id")

    cam_ids = sorted(c for c in calib if _Container.find(root / "image", f"cam{c}") is not None)
    if cameras is not None:
        wanted = [str(c) for c in cameras]
        missing = [c for c in wanted if c not in cam_ids]
        if missing:
            raise ValueError(f"Ava-256 capture {root}: cameras {missing} have no calibration or no images")
        cam_ids = wanted
    if len(cam_ids) == 0:
        raise ValueError(f"Ava-256 capture {root}: no camera has both a calibration entry and image/cam<ID>.zip")

    images = {c: _Container.find(root / "image", f"cam{c}") for c in cam_ids}
    segs = {c: _Container.find(root / "segmentation_fgbg", f"cam{c}") for c in cam_ids}
    parts = {c: _Container.find(root / "segmentation_parts", f"cam{c}") for c in cam_ids}
    depths = {c: _Container.find(root / "depth", f"cam{c}") for c in cam_ids}
    head_c = _Container.find(root / "head_pose", "head_pose") or (
        _Container(root / "head_pose") if (root / "head_pose").is_dir() else None
    )
    if head_c is None:
        raise ValueError(f"Ava-256 capture {root}: no head_pose/head_pose.zip (per-frame head poses are required)")
    if all(segs[c] is None and parts[c] is None for c in cam_ids):
        logger.warning("Ava-256 capture %s has no segmentation: masks are all ones", root)

    fit_ids, fit_codes = (None, None) if flame_fit is None else _load_flame_fit(Path(flame_fit))
    fit_row = {} if fit_ids is None else {int(i): k for k, i in enumerate(fit_ids)}

    by_seg: dict[str, list[int]] = {}
    for r in rows:
        by_seg.setdefault(r["seg_id"], []).append(int(r["frame_id"]))
    if segments is not None:
        unknown = [s for s in segments if s not in by_seg]
        if unknown:
            raise ValueError(f"Ava-256 capture {root}: unknown segments {unknown}; have {sorted(by_seg)[:8]}...")
        by_seg = {s: by_seg[s] for s in segments}

    # image size from the first readable image of the first camera
    first = None
    for frames in by_seg.values():
        for fr in frames[:8]:
            first = images[cam_ids[0]].read(f"{fr:06d}", _IMAGE_EXTS)
            if first is not None:
                break
        if first is not None:
            break
    if first is None:
        raise ValueError(f"Ava-256 capture {root}: no image found for camera {cam_ids[0]}")
    width, height = _read_image_size(first[0])
    rig = _stack_resized([calib[c] for c in cam_ids], (width, height))
    axes = np.eye(3) if head_axes is None else _orthonormalize(np.asarray(head_axes, dtype=np.float64))
    canon_to_head = _rigid(axes, np.zeros(3))
    fg = np.zeros(256, dtype=np.float32)
    fg[[int(k) for k in foreground_classes]] = 1.0

    subject = root.parent.name if root.name == "decoder" else root.name
    out = []
    for seg, frames in by_seg.items():
        if fit_ids is not None:
            kept = [f for f in frames if f in fit_row]
            if len(kept) < len(frames):
                logger.warning("Ava-256 %s/%s: %d of %d frames have no FLAME fit and are dropped", subject, seg, len(frames) - len(kept), len(frames))
            frames = kept
        if not frames:
            continue
        poses = []
        for fr in frames:
            got = head_c.read(f"{fr:06d}", (".txt",))
            if got is None:
                raise ValueError(f"Ava-256 capture {root}: no head pose for frame {fr:06d}")
            poses.append(_ava_head_pose(got[0]) @ canon_to_head)
        exprs = None if fit_codes is None else fit_codes[[fit_row[f] for f in frames]]

        out.append(
            RealSequence(
                subject=subject,
                sequence=seg,
                expression_space="none" if exprs is None else "flame120",
                _cameras=_StaticCameras(rig, np.stack(poses)),
                _expressions=exprs,
                _loader=_AvaLoader(f"{subject}/{seg}", list(frames), cam_ids, images, segs, parts, depths, fg),
                _num_timesteps=len(frames),
                camera_names=list(cam_ids),
                frame_ids=list(frames),
            )
        )
    return out


# ================================================================ NeRSemble
def _nersemble_tracking(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as z:
        d = {k: np.asarray(z[k]) for k in z.files}
    need = {"expression", "jaw", "eyes", "translation"}
    if not need <= set(d) or not ({"rotation_matrices", "rotation"} & set(d)):
        raise ValueError(
            f"NeRSemble FLAME tracking {path}: needs expression (T,100), jaw (T,3), eyes (T,6), translation (T,3) "
            f"and rotation_matrices (T,3,3) or rotation (T,3); has {sorted(d)}"
        )
    return d


def _nersemble_head_to_world(trk: dict[str, np.ndarray]) -> np.ndarray:
    """FLAME model -> world ``x_w = s R x + t`` (nersemble-benchmark ``FlameProvider``) as rigid
    transforms ``[T, 4, 4]`` of a world scaled by ``1/s`` (projections are unchanged, depth is z/s)."""
    if "rotation_matrices" in trk:
        R = trk["rotation_matrices"].astype(np.float64).reshape(-1, 3, 3)
    else:
        from scipy.spatial.transform import Rotation  # Euler 'XYZ' as dreifus Pose.from_euler

        R = Rotation.from_euler("XYZ", trk["rotation"].astype(np.float64).reshape(-1, 3)).as_matrix()
    t = trk["translation"].astype(np.float64).reshape(-1, 3)
    s = float(np.asarray(trk.get("scale", 1.0)).reshape(-1)[0])
    if not s > 0:
        raise ValueError(f"NeRSemble FLAME tracking scale must be positive, got {s}")
    return np.stack([_rigid(_orthonormalize(Ri), ti) for Ri, ti in zip(R, t)]), s


class _VideoFrames:
    """Random access into an mp4 through imageio-ffmpeg (reopened after fork, not pickled)."""

    def __init__(self, path: Path):
        self.path = path
        self._reader = None
        self._pid = -1

    def __getstate__(self) -> dict:
        return {"path": self.path, "_reader": None, "_pid": -1}

    def frame(self, index: int) -> np.ndarray:  # uint8 [H, W, 3]
        import imageio.v2 as iio

        if self._reader is None or self._pid != os.getpid():
            self._reader = iio.get_reader(str(self.path), format="FFMPEG")
            self._pid = os.getpid()
        try:
            return np.asarray(self._reader.get_data(int(index)))
        except IndexError:
            raise MissingViewError(f"{self.path}: no frame {index}") from None


def _find_first(base: Path, names: Sequence[str]) -> Path | None:
    for n in names:
        if (base / n).exists():
            return base / n
    return None


_NERSEMBLE_IMAGE_DIRS = ("images-2x", "images-4x", "images", "images-2x-73fps")
_NERSEMBLE_ALPHA_DIRS = ("alpha_map", "alpha_maps", "alpha_map-73fps")


@dataclass
class _NerLoader:
    """Reads one NeRSemble view from videos or extracted frames (picklable)."""

    name: str
    seq_dir: Path
    frames: list[int]  # timestep -> video frame / frame folder number
    serials: list[str]
    use_video: bool
    image_dir: str | None
    frame_dirs: dict  # frame number -> folder (extracted layout)
    videos: dict  # serial -> _VideoFrames
    alphas: dict  # serial -> _VideoFrames

    def read(self, fr: int, s: str) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        if self.use_video:
            rgb = self.videos[s].frame(fr)
            alpha = self.alphas[s].frame(fr)[..., 0].astype(np.float32) / 255.0 if s in self.alphas else None
            dep = _Container.find(self.seq_dir / "depth", f"cam_{s}")
            dep_name = f"{fr:05d}"
        else:
            fd = self.frame_dirs.get(fr)
            if fd is None:
                raise MissingViewError(f"NeRSemble {self.name}: no folder frame_{fr:05d}")
            p = _find_first(fd / self.image_dir, (f"cam_{s}.png", f"cam_{s}.jpg", f"cam_{s}.jpeg"))
            if p is None:
                raise MissingViewError(f"NeRSemble {self.name}: no image {fd / self.image_dir}/cam_{s}.png|jpg")
            rgb = _decode_image(p.read_bytes())
            a = _find_first(fd, [f"{d}/cam_{s}.png" for d in _NERSEMBLE_ALPHA_DIRS])
            alpha = None
            if a is not None:
                alpha = _resize_u8(_decode_image(a.read_bytes()), rgb.shape[1], rgb.shape[0])[..., 0].astype(np.float32) / 255.0
            dep = _Container(fd / "depth") if (fd / "depth").is_dir() else None
            dep_name = f"cam_{s}"
        depth = None
        if dep is not None and (d := dep.read(dep_name, _DEPTH_EXTS)) is not None:
            depth = _resize_depth(_decode_depth(*d), rgb.shape[1], rgb.shape[0])
        if rgb.shape[2] == 4 and alpha is not None:
            rgb = rgb[..., :3]
        return rgb, alpha, depth

    def __call__(self, t: int, c: int) -> View:
        return compose_view(*self.read(self.frames[t], self.serials[c]))


def open_nersemble(
    root: str | Path,
    *,
    participant: int | str | None = None,
    sequences: Sequence[str] | None = None,
    cameras: Sequence[str] | None = None,
    tracking: str = "tracking/flame2023_tracking.npz",
    image_dir: str | None = None,
    calibration_size: tuple[int, int] | None = None,
) -> list[RealSequence]:
    """Open the sequences of one NeRSemble participant.

    Layout (``root`` = the NeRSemble folder plus ``participant``, or the participant folder):
    ``calibration/camera_params.json`` (or ``camera_params.json``) with ``world_2_cam``
    ``{serial: 4x4 OpenCV w2c}`` and ``intrinsics`` (one shared 3x3, or ``{serial: 3x3}`` in the
    benchmark release), optionally ``width``/``height``. Per sequence ``sequences/<SEQ>/``:

    - videos: ``images/cam_<serial>.mp4`` and ``alpha_maps/cam_<serial>.mp4`` (v2, benchmark),
      decoded with imageio-ffmpeg (slow random access: extract frames for training);
    - or extracted frames: ``[timesteps/]frame_<t:05d>/images-2x/cam_<serial>.png|jpg`` and
      ``.../alpha_map/cam_<serial>.png`` (v1 layout; ``image_dir`` picks another image folder);
    - FLAME tracking ``tracking/flame2023_tracking.npz`` (``expression (T,100)``, ``jaw (T,3)``,
      ``eyes (T,6)``, ``rotation (T,3)``/``rotation_matrices (T,3,3)``, ``translation (T,3)``,
      ``scale (1,1)``, ``frames (T,)``): timesteps are its rows (video frames ``frames[t]``),
      expressions become ``flame120`` and the head pose ``x_w = s R x + t`` is folded into the
      cameras (in FLAME model units, metres: depth of the head-centric camera is z_world / s).
      Without it every frame is a timestep, cameras stay in NeRSemble's world and
      ``expression_space`` is ``"none"``.

    Depth priors: ``sequences/<SEQ>/depth/cam_<serial>/<frame:05d>.npy|png`` (videos) or
    ``frame_<t:05d>/depth/cam_<serial>.npy|png`` (extracted frames).

    ``calibration_size`` (w, h) defaults to the file's ``width``/``height``, else to the image
    size for per-camera intrinsics (benchmark) and to 2200x3208 for shared intrinsics (v2).
    """
    root = Path(root)
    if participant is not None:
        root = root / (f"{int(participant):03d}" if str(participant).isdigit() else str(participant))
    calib_path = _find_first(root, ("calibration/camera_params.json", "camera_params.json"))
    if calib_path is None:
        raise ValueError(f"{root} is not a NeRSemble participant folder: no calibration/camera_params.json")
    params = json.loads(calib_path.read_text())
    if "world_2_cam" not in params or "intrinsics" not in params:
        raise ValueError(f"{calib_path}: expected keys world_2_cam and intrinsics, got {sorted(params)}")
    serials = sorted(str(s) for s in params["world_2_cam"])
    if cameras is not None:
        missing = [str(c) for c in cameras if str(c) not in serials]
        if missing:
            raise ValueError(f"{calib_path}: cameras {missing} not calibrated; have {serials}")
        serials = [str(c) for c in cameras]
    per_cam_K = isinstance(params["intrinsics"], dict)
    seq_root = root / "sequences"
    if not seq_root.is_dir():
        raise ValueError(f"NeRSemble participant {root} has no sequences/ folder")
    names = sorted(p.name for p in seq_root.iterdir() if p.is_dir()) if sequences is None else list(sequences)

    out = []
    for seq in names:
        sdir = seq_root / seq
        if not sdir.is_dir():
            raise ValueError(f"NeRSemble participant {root}: no sequence {seq}")
        videos = {s: sdir / "images" / f"cam_{s}.mp4" for s in serials}
        use_video = all(v.exists() for v in videos.values())
        frame_base = sdir / "timesteps" if (sdir / "timesteps").is_dir() else sdir
        frame_dirs = {int(p.name.split("_")[-1]): p for p in sorted(frame_base.glob("frame_*")) if p.is_dir()}
        if not use_video and not frame_dirs:
            raise ValueError(f"NeRSemble {root.name}/{seq}: neither images/cam_<serial>.mp4 for every camera nor frame_<5 digits> folders")
        trk_path = sdir / tracking
        if trk_path.exists():
            trk = _nersemble_tracking(trk_path)
            T = int(trk["expression"].shape[0])
            frames = [int(f) for f in np.asarray(trk.get("frames", np.arange(T))).reshape(-1)]
            if len(frames) != T:
                raise ValueError(f"{trk_path}: 'frames' has {len(frames)} entries for {T} tracked timesteps")
            exprs = flame120_from_axis_angle(trk["expression"], trk["jaw"], trk["eyes"])
            head, scale = _nersemble_head_to_world(trk)
        else:
            logger.warning("NeRSemble %s/%s: no FLAME tracking at %s: no expressions, head pose not removed", root.name, seq, trk_path)
            if use_video:
                import imageio.v2 as iio

                with iio.get_reader(str(videos[serials[0]]), format="FFMPEG") as r:
                    frames = list(range(r.count_frames()))
            else:
                frames = sorted(frame_dirs)
            exprs, head, scale = None, None, 1.0

        img_dir = image_dir
        if not use_video and img_dir is None:
            found = _find_first(next(iter(frame_dirs.values())), _NERSEMBLE_IMAGE_DIRS)
            if found is None:
                raise ValueError(f"NeRSemble {root.name}/{seq}: frame folders have none of {_NERSEMBLE_IMAGE_DIRS}")
            img_dir = found.name
        alpha_paths = {s: sdir / "alpha_maps" / f"cam_{s}.mp4" for s in serials}
        loader = _NerLoader(
            name=f"{root.name}/{seq}",
            seq_dir=sdir,
            frames=frames,
            serials=serials,
            use_video=use_video,
            image_dir=img_dir,
            frame_dirs=frame_dirs if not use_video else {},
            videos={s: _VideoFrames(videos[s]) for s in serials} if use_video else {},
            alphas={s: _VideoFrames(p) for s, p in alpha_paths.items() if use_video and p.exists()},
        )
        rgb0 = loader.read(frames[0], serials[0])[0]
        height, width = rgb0.shape[:2]
        if calibration_size is not None:
            calib = (int(calibration_size[0]), int(calibration_size[1]))
        elif "width" in params and "height" in params:
            calib = (int(params["width"]), int(params["height"]))
        else:
            calib = (width, height) if per_cam_K else NERSEMBLE_CALIBRATION_SIZE
        calib_cams = read_nersemble_camera_params(params, width=calib[0], height=calib[1])
        rig = _stack_resized([calib_cams[s] for s in serials], (width, height))
        if head is not None and scale != 1.0:
            # x_cam = Rc (s R x + t) + tc  ==  s [Rc R x + (Rc t + tc) / s]: rigid in model units
            w2c = rig.w2c.double().clone()
            w2c[:, :3, 3] /= scale
            rig = Cameras(rig.K, w2c.float(), rig.width, rig.height)
            head = head.copy()
            head[:, :3, 3] /= scale
        out.append(
            RealSequence(
                subject=root.name,
                sequence=seq,
                expression_space="none" if exprs is None else "flame120",
                _cameras=_StaticCameras(rig, head),
                _expressions=exprs,
                _loader=loader,
                _num_timesteps=len(frames),
                camera_names=list(serials),
                frame_ids=list(frames),
            )
        )
    return out


# ================================================================ VHAP exports
@dataclass
class _VhapLoader:
    """Reads one view of a VHAP export (picklable)."""

    root: Path
    frames: list  # [T][C] frame dicts of transforms.json

    def __call__(self, t: int, c: int) -> View:
        f, root = self.frames[t][c], self.root
        p = root / f["file_path"]
        if not p.exists():
            raise MissingViewError(f"VHAP export {root}: missing image {p}")
        rgb = _decode_image(p.read_bytes())
        alpha = None
        if "fg_mask_path" in f and (root / f["fg_mask_path"]).exists():
            m = _resize_u8(_decode_image((root / f["fg_mask_path"]).read_bytes()), rgb.shape[1], rgb.shape[0])
            alpha = m[..., 0].astype(np.float32) / 255.0
            rgb = rgb[..., :3] if rgb.shape[2] == 4 else rgb
        depth = None
        if (root / "depth").is_dir() and (d := _Container(root / "depth").read(Path(f["file_path"]).stem, _DEPTH_EXTS)) is not None:
            depth = _resize_depth(_decode_depth(*d), rgb.shape[1], rgb.shape[0])
        return compose_view(rgb, alpha, depth)


def open_vhap(
    root: str | Path,
    *,
    division: str | None = None,
    root_joint: Sequence[float] = (0.0, 0.0, 0.0),
    subject: str | None = None,
) -> list[RealSequence]:
    """Open a VHAP ``export_as_nerf_dataset.py`` folder as one sequence.

    ``transforms.json`` (or ``transforms_<division>.json``): ``frames`` with ``timestep_index``,
    ``camera_index``, ``fl_x fl_y cx cy w h`` (``cy`` measured from the *bottom* row: VHAP's
    opencv->opengl conversion sets ``K[1, 2] = H - K[1, 2]``; read back as ``h - cy``),
    ``transform_matrix`` (c2w, OpenGL axes),
    ``file_path``, optional ``fg_mask_path`` and ``flame_param_path``
    (``flame_param/<t:05d>.npz``: ``expr (1,N)``, ``jaw_pose (1,3)``, ``eyes_pose (1,6)``,
    ``rotation (1,3)`` axis-angle, ``translation (1,3)``, ``neck_pose``, ``shape``).

    FLAME applies ``rotation`` about its root joint ``J0`` (which depends on the shape and needs
    the licensed FLAME model): ``x_w = R (x - J0) + J0 + t``. Pass ``root_joint=J0`` (metres) for
    an exact head pose; the default (origin) is off by ``(I - R) J0``, a few millimetres for
    moderate rotations. ``neck_pose`` is not removed. Depth priors: ``depth/<image stem>.npy|png``.
    """
    root = Path(root)
    name = "transforms.json" if division is None else f"transforms_{division}.json"
    tpath = root / name
    if not tpath.exists():
        raise ValueError(f"{root} is not a VHAP export: no {name}")
    db = json.loads(tpath.read_text())
    frames = db.get("frames")
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{tpath}: expected a non-empty 'frames' list")
    need = {"timestep_index", "camera_index", "transform_matrix", "file_path"}
    for i, fr in enumerate(frames):
        if not need <= set(fr):
            raise ValueError(f"{tpath}: frame {i} lacks {sorted(need - set(fr))}")
    ts = sorted({int(f["timestep_index"]) for f in frames})
    cs = sorted({int(f["camera_index"]) for f in frames})
    entry = {(int(f["timestep_index"]), int(f["camera_index"])): f for f in frames}
    missing = [(t, c) for t in ts for c in cs if (t, c) not in entry]
    if missing:
        raise ValueError(f"{tpath}: every timestep needs every camera; missing (timestep, camera) {missing[:4]}")

    # cameras in frame order (cameras.read_transforms_json: OpenGL c2w -> OpenCV w2c; VHAP's cy is
    # measured from the bottom row: its opencv->opengl conversion wrote K[1, 2] = H - K[1, 2])
    per_frame = read_transforms_json(db, principal_point_origin="bottom")
    cam_of = {(int(f["timestep_index"]), int(f["camera_index"])): per_frame[i] for i, f in enumerate(frames)}
    rig = Cameras.stack([cam_of[(ts[0], c)] for c in cs])
    # VHAP writes the same rig for every timestep; moving cameras are not supported
    for t in ts[1:]:
        other = Cameras.stack([cam_of[(t, c)] for c in cs])
        if (other.w2c - rig.w2c).abs().max() > 1e-5 or (other.K - rig.K).abs().max() > 1e-4:
            raise ValueError(f"{tpath}: cameras change between timesteps {ts[0]} and {t}; only fixed rigs are supported")

    J0 = torch.as_tensor(root_joint, dtype=torch.float64).reshape(3)
    heads, exprs = [], []
    has_flame = all("flame_param_path" in entry[(t, cs[0])] for t in ts)
    if has_flame:
        for t in ts:
            p = root / entry[(t, cs[0])]["flame_param_path"]
            if not p.exists():
                raise ValueError(f"VHAP export {root}: missing {p}")
            with np.load(p) as z:
                keys = set(z.files)
                if not {"expr", "jaw_pose", "eyes_pose", "rotation", "translation"} <= keys:
                    raise ValueError(f"{p}: needs expr, jaw_pose, eyes_pose, rotation, translation; has {sorted(keys)}")
                exprs.append(flame120_from_axis_angle(z["expr"].reshape(-1), z["jaw_pose"].reshape(3), z["eyes_pose"].reshape(6)))
                rot, tr = z["rotation"].reshape(3), z["translation"].reshape(3)
            # FLAME rotates about its root joint: x_w = R (x - J0) + J0 + t
            heads.append(head_pose_matrix(torch.as_tensor(rot), torch.as_tensor(tr), J0))
    else:
        logger.warning("VHAP export %s has no flame_param_path: no expressions, head pose not removed", root)

    return [
        RealSequence(
            subject=subject or root.name,
            sequence=division or "all",
            expression_space="flame120" if has_flame else "none",
            _cameras=_StaticCameras(rig, torch.stack(heads) if has_flame else None),
            _expressions=torch.stack(exprs) if has_flame else None,
            _loader=_VhapLoader(root, [[entry[(t, c)] for c in cs] for t in ts]),
            _num_timesteps=len(ts),
            camera_names=[str(entry[(ts[0], c)].get("camera_id", c)) for c in cs],
            frame_ids=list(ts),
        )
    ]
