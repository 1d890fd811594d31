"""Leave-one-out evaluation on real photo sets (``../shared/realsets`` or ``$FASTGHA_REALSETS``).

For every set (a folder of photos of one person): track all photos together
(``fastgha_core.tracking.track_photos``: cameras, masks, expressions), then for every photo build
an avatar from the others (feed-forward, optionally refined with ``--refine-steps``), render it at the
left-out photo's tracked camera with its tracked expression, and compare with the left-out crop:

- masked PSNR and SSIM inside the left-out photo's mask (outside it both images are set to the
  background colour, so SSIM sees only the head);
- dlib identity distance: Euclidean distance between dlib's 128-d face descriptors of the render and
  of the photo (``face_recognition_models``; 0.6 is dlib's same-person threshold);
- the number of faces dlib's HOG detector finds in the render (1 is right; 2 means a doubled face),
  and in the left-out photo itself (``faces_in_photo``): the frontal HOG detector misses most
  profiles, so a render without a face of a photo without one says nothing about doubling;
- the same two counts by dlib's CNN detector (``mmod_human_face_detector.dat`` of
  ``face_recognition_models``, ``cnn_faces_in_render`` / ``cnn_faces_in_photo``), which also finds
  turned heads: a measurement beside HOG's, not the same detector;
- where the masked error comes from (``error_split``): the pixels inside the photo's mask that the
  render leaves uncovered (render alpha < 0.5: hair, neck, shoulders no other photo saw) and the
  covered ones, each given as the PSNR that term alone would allow, and the share of the error on
  the mask's outline (its pixels within 1.5 px of the outside);
- what the render draws beyond the photo's outline, which the masked scores never see
  (``beyond_mask``: render alpha >= 0.5 outside the mask dilated by 3 pixels, within the photo's
  frame, as a share of the mask's pixels).

With ``--align-left-out`` every row also carries the **test-view pose alignment** diagnostic
(``refine/testpose.py``; the protocol of pose-free novel-view-synthesis evaluations: the avatar
frozen, only the left-out camera optimised against the left-out photo, bounded to 25 degrees and
3 cm): the same scores at the aligned camera (``aligned_*`` columns), the correction (degrees,
millimetres) and the head's yaw / pitch / roll at the tracked and at the aligned camera beside the
file name's annotated yaw. The headline scores stay those at the tracked camera (the issue's
protocol); the aligned ones bound how much of the loss the left-out camera's own pose accounts for.

``python -m fastgha_core.refine.realsets --refine-steps 0,60 --grid OUT.png`` prints a markdown
table and writes a grid picture (one row per left-out photo: the photo, then one render per step count; with ``--mirror off,30``
one per mirrored-view variant and step count, ``model/mirror.py``; with ``--align-left-out`` each
render is followed by the render at the aligned camera; columns titled, each render labelled with
its masked PSNR and identity distance, each photo with its set and name; ``--own-cameras`` adds the
input-view check, the avatar of all of a set's photos at each photo's own camera). The sets are not
ours to publish: write the grid outside the repository. Sets that fail to track are reported and
skipped, and a photo the tracker cannot handle is dropped from its set (reported) while at least 3 remain;
without the folder the script says so and exits 0.

``--synthetic N [--first-seed S]`` runs the same protocol, tracking included, on ``N`` held-out
synthetic subjects photographed like the real sets (``data/photosets.py``: a frontal, -65, +40 and
+70 degrees of yaw, 25 degrees pitched up; written to ``--root`` when given, else to a temporary
folder): people no setting was chosen on, whose pictures may be looked at and published. With
``--truth cameras`` (or ``all``) the tracked poses and focal length (and identity and expressions)
are replaced by the ones the photos were drawn from: the same protocol without tracking's error,
which splits the leave-one-out's loss between tracking and reconstruction.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import logging
import os
import tempfile
import time
from contextlib import ExitStack, contextmanager
from pathlib import Path

import numpy as np
import torch

from ..constants import BACKGROUND_RGB

log = logging.getLogger(__name__)

__all__ = ["realsets_root", "list_sets", "evaluate_set", "error_split", "main"]

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")


def realsets_root() -> Path:
    """``$FASTGHA_REALSETS``, else ``../shared/realsets`` relative to the repository root."""
    env = os.environ.get("FASTGHA_REALSETS")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[3] / "shared" / "realsets"


def list_sets(root: Path) -> list[Path]:
    """Sub-folders of ``root`` holding at least 2 photos, sorted by name."""
    if not root.is_dir():
        return []
    return sorted(d for d in root.iterdir() if d.is_dir() and len([p for p in d.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES]) >= 2)


def _load_photos(folder: Path) -> tuple[list[np.ndarray], list[str]]:
    from ..images import read_image  # the project's one decoder (EXIF orientation applied)

    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES)
    return [read_image(p, max_pixels=64_000_000).rgb for p in paths], [p.name for p in paths]


OUTLINE_PX = 1.5  # error_split: the mask's pixels within this distance (pixels, centre to centre) of a pixel outside it form its outline
BOTTOM_ROWS = 0.3  # error_split: the bottom share of the image's rows whose error bottom_error_share gives (shoulders and torso)


def error_split(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, alpha: torch.Tensor, thresh: float = 0.5) -> dict:
    """Split the masked squared error of a render into its uncovered and covered pixels, and give
    the share of it on the mask's outline.

    Args:
        pred, target: ``[3, H, W]`` colours in [0, 1].
        mask: ``[1, H, W]`` or ``[H, W]``, > 0.5 inside the photo's matte.
        alpha: ``[1, H, W]`` or ``[H, W]`` the render's accumulated opacity.
        thresh: pixels with ``alpha < thresh`` count as uncovered.
    Returns:
        ``uncovered_frac``: share of the mask's pixels left uncovered; ``psnr_uncovered_only`` /
        ``psnr_covered_only``: the masked PSNR (dB, over the whole mask, like ``masked_psnr``) if only
        that term's error remained, i.e. ``-10 log10(SSE_term / (3 N_mask))``; the two terms' squared
        errors add up to the masked error (``None`` for a term without error or pixels);
        ``outline_error_share``: the share of the masked squared error on the mask's outline, its
        pixels within ``OUTLINE_PX`` of a pixel outside it (Euclidean, pixel centres; ``None`` for a
        render without error). On the real sets this ring of ~3 % of the pixels holds 19-44 % of the
        error per set, 9-57 % per photo (``docs/model-card-log.md``, "The outline's share of the error").
        ``psnr_gain_matched``: the masked PSNR with the covered pixels' colours multiplied by one gain
        per channel, fitted to the photo by least squares over those pixels (what exposure and white
        balance could explain); ``bottom_error_share``: the share of the masked squared error in the
        image's bottom ``BOTTOM_ROWS`` of rows (``None`` for a render without error).
    Raises:
        ValueError: when the shapes do not match or the mask is empty.
    """
    from scipy import ndimage

    m = (mask.reshape(pred.shape[-2:]) > 0.5)
    a = alpha.reshape(pred.shape[-2:])
    if pred.shape != target.shape or pred.ndim != 3 or pred.shape[0] != 3:
        raise ValueError(f"error_split: pred and target must both be [3, H, W], got {list(pred.shape)} and {list(target.shape)}")
    n = int(m.sum())
    if n == 0:
        raise ValueError("error_split: the mask is empty")
    se = ((pred - target) ** 2).sum(0)  # [H, W]
    unc = m & (a < thresh)
    out = {"uncovered_frac": float(unc.sum()) / n}
    for name, sel in (("uncovered", unc), ("covered", m & ~unc)):
        sse = float(se[sel].sum())
        out[f"psnr_{name}_only"] = float(-10 * np.log10(sse / (3 * n))) if sse > 0 else None
    ring = m & torch.from_numpy(ndimage.distance_transform_edt(m.cpu().numpy()) <= OUTLINE_PX).to(m.device)
    total = float(se[m].sum())
    out["outline_error_share"] = float(se[ring].sum()) / total if total > 0 else None
    cov = m & ~unc
    p, q = pred[:, cov], target[:, cov]  # [3, n_covered]
    gain = (p * q).sum(1) / (p * p).sum(1).clamp_min(1e-12)  # [3]
    matched = pred.clone()
    matched[:, cov] = p * gain[:, None]
    sse = float(((matched - target) ** 2).sum(0)[m].sum())
    out["psnr_gain_matched"] = float(-10 * np.log10(sse / (3 * n))) if sse > 0 else None
    y0 = int(round((1 - BOTTOM_ROWS) * se.shape[0]))
    out["bottom_error_share"] = float(se[y0:][m[y0:]].sum()) / total if total > 0 else None
    return out


BEYOND_MASK_DILATE_PX = 3  # beyond_mask: the photo's mask is dilated by this many pixels (its edge and a pixel of misregistration do not count)


def beyond_mask(alpha: torch.Tensor, mask: torch.Tensor, in_frame: torch.Tensor | None = None, thresh: float = 0.5,
                dilate_px: int = BEYOND_MASK_DILATE_PX) -> float:
    """Where the render draws the head and the photo shows none: the share (of the mask's pixel
    count) of pixels with ``alpha >= thresh`` outside the photo's mask dilated by ``dilate_px``
    pixels and inside the photo's frame.

    The masked scores never see these pixels (outside the mask both images are set to the
    background), yet a viewer does: a head drawn larger than the person's (a skull or hair layer
    the other photos do not bound) shows as a rim of hair in the air around the real outline.

    Args:
        alpha: ``[1, H, W]`` or ``[H, W]`` the render's accumulated opacity.
        mask: ``[1, H, W]`` or ``[H, W]``, > 0.5 inside the photo's matte.
        in_frame: ``bool [H, W]``: the crop's pixels that lie inside the original photo (the crop's
            padding beyond the photo's edge is unknown, not background: ``~HeadSurface.padding``);
            None: all.
    Returns:
        the share, >= 0 (it can exceed 1).
    Raises:
        ValueError: when the shapes differ or the mask is empty.
    """
    from ..model.surface import _mattes

    a = alpha.reshape(alpha.shape[-2:])
    m = mask.reshape(mask.shape[-2:]) > 0.5
    if a.shape != m.shape or (in_frame is not None and tuple(in_frame.shape) != tuple(a.shape)):
        raise ValueError(f"beyond_mask: alpha {list(a.shape)}, mask {list(m.shape)} and in_frame {None if in_frame is None else list(in_frame.shape)} must have one size")
    n = int(m.sum())
    if n == 0:
        raise ValueError("beyond_mask: the mask is empty")
    out = (a >= thresh) & ~_mattes(m[None].float(), dilate_px)[0].to(a.device)  # the mask grown as the carves grow mattes
    if in_frame is not None:
        out &= in_frame.to(out.device)
    return float(out.sum()) / n


def _count_cnn(faces, img: np.ndarray) -> int | None:
    """Faces found by dlib's CNN (MMOD) detector in ``img`` (upsampled once, as for HOG), or None
    when it is not loaded."""
    cnn = getattr(faces, "cnn_detector", None)
    if cnn is None:
        return None
    return len(cnn(img, 1))


def _load_cnn(faces):
    """Attach dlib's CNN face detector to ``faces`` (``cnn_detector``); leaves it None when absent."""
    faces.cnn_detector = None
    try:
        import face_recognition_models as frm  # type: ignore

        faces.cnn_detector = faces.dlib.cnn_face_detection_model_v1(frm.cnn_face_detector_model_location())
    except Exception as e:  # missing model file or a dlib without the CNN detector
        log.warning("dlib's CNN face detector unavailable: %s", e)
    return faces


def _identity(faces, img: np.ndarray, box=None):
    """(descriptor or None, number of faces found) for an ``[H, W, 3]`` uint8 image."""
    dets = faces.detector(img, 1)
    n = len(dets)
    if n:
        box = max(dets, key=lambda r: r.width() * r.height())
    if box is None:
        return None, n, None
    shape = faces.shape_predictor(img, box)
    return np.asarray(faces.face_rec.compute_face_descriptor(img, shape), dtype=np.float64), n, box


def _score(pred: torch.Tensor, alpha: torch.Tensor, target: torch.Tensor, m: torch.Tensor, faces, t_desc, t_box, in_frame: torch.Tensor | None = None) -> dict:
    """The scores of one render ``pred [1, 3, S, S]`` (alpha ``[1, 1, S, S]``) of the left-out photo
    ``target [1, 3, S, S]`` inside its mask ``m [1, 1, S, S]`` (0/1): masked PSNR / SSIM, the dlib
    identity distance to the photo's descriptor ``t_desc`` (face box ``t_box``), the face counts,
    ``error_split`` and ``beyond_mask_frac`` (``beyond_mask``, within ``in_frame``)."""
    from ..train.faces import to_uint8_hwc
    from ..train.metrics import ssim

    bg = torch.tensor(BACKGROUND_RGB).view(1, 3, 1, 1)
    pm, tm = pred * m + bg * (1 - m), target * m + bg * (1 - m)
    mse = ((pred - target) ** 2 * m).sum() / (3 * m.sum()).clamp_min(1)
    out = {
        "masked_psnr": float(-10 * torch.log10(mse.clamp_min(1e-10))),
        "masked_ssim": float(ssim(pm, tm)[0]),
        "identity_distance": None,
        "faces_in_render": None,
        "cnn_faces_in_render": None,
    }
    if faces is not None:
        p_img = to_uint8_hwc(pred[0])
        p_desc, n_faces, _ = _identity(faces, p_img, t_box)
        out["faces_in_render"] = n_faces
        out["cnn_faces_in_render"] = _count_cnn(faces, p_img)
        if p_desc is not None and t_desc is not None:
            out["identity_distance"] = float(np.linalg.norm(p_desc - t_desc))
    out.update(error_split(pred[0], target[0], m[0], alpha[0]))
    out["beyond_mask_frac"] = beyond_mask(alpha[0], m[0], in_frame)
    return out


ALIGNED_KEYS = ("masked_psnr", "masked_ssim", "identity_distance", "faces_in_render", "cnn_faces_in_render", "uncovered_frac")


def aligned_columns(model, avatar, expression: torch.Tensor, camera, target: torch.Tensor, m: torch.Tensor, faces, t_desc, t_box, name: str,
                    config=None, from_annotation: float = 5.0) -> tuple[dict, torch.Tensor]:
    """The test-view pose alignment diagnostic of one left-out photo (``refine/testpose.py``).

    The frozen ``avatar`` (drawn as ``model.animate`` draws it at ``expression [E]``, the tracked one)
    is aligned to ``target [1, 3, S, S]`` (matted, mask ``m [1, 1, S, S]``) from the tracked
    ``camera`` (batch ``[1]``, ``S x S``, world = the head frame); returns the row's extra columns
    (``aligned_<score>`` for the scores of ``_score``; the correction ``align_rotation_deg`` /
    ``align_translation_mm`` (and its camera-frame components ``align_translation_xyz_mm``: right,
    down, away from the camera) and its ``align_d{yaw,pitch,roll}_deg``; the head's ``yaw_tracked`` /
    ``yaw_aligned`` (and pitch, roll) in ``tracking.fit.head_angles_deg``'s convention;
    ``yaw_annotated`` from the file name ``name`` or None; ``align_s``) and the aligned render
    ``[3, S, S]``.

    ``from_annotation`` > 0: where the annotated yaw differs from the tracked one by more than that
    many degrees, a second alignment starts from the tracked camera turned about the head's up axis
    to the annotated yaw (no yaw sweep), and ``annot_start_*`` give where it ends (``yaw``,
    ``masked_psnr``, ``loss_end``) and its masked PSNR before aligning (``masked_psnr_start``): which
    of the two ends the frozen avatar prefers (the lower ``loss_end``)."""
    from ..render import render
    from ..tracking.realsets import annotated_yaw
    from .testpose import AlignConfig, align_camera, apply_correction, head_angles, pivot_of

    res = align_camera(lambda c: model.animate(avatar, expression, camera=c), camera, target[0], m[0], config)
    ro = render(model.animate(avatar, expression, camera=res.camera), res.camera, background=BACKGROUND_RGB)
    pred = ro.rgb.clamp(0, 1)
    sc = _score(pred, ro.alpha, target, m, faces, t_desc, t_box)
    a0, a1 = head_angles(camera), head_angles(res.camera)
    cols = {f"aligned_{k}": sc[k] for k in ALIGNED_KEYS}
    cols.update({
        "align_rotation_deg": round(res.rotation_deg, 2),
        "align_translation_mm": round(res.translation_mm, 1),
        "align_translation_xyz_mm": [round(1000 * float(x), 1) for x in res.translation],  # camera frame: right, down, away
        **{f"align_d{a}_deg": round(y - x, 2) for a, x, y in zip(("yaw", "pitch", "roll"), a0, a1)},
        **{f"{a}_tracked": round(x, 2) for a, x in zip(("yaw", "pitch", "roll"), a0)},
        **{f"{a}_aligned": round(y, 2) for a, y in zip(("yaw", "pitch", "roll"), a1)},
        "yaw_annotated": annotated_yaw(name),
        "align_start_yaw_deg": res.start_yaw_deg,
        "align_loss_start": round(res.loss_start, 5),
        "align_loss_end": round(res.loss_end, 5),
        "align_s": round(res.seconds, 1),
    })
    ann = cols["yaw_annotated"]
    if from_annotation > 0 and ann is not None and abs(ann - a0[0]) > from_annotation:
        up = camera.flatten().w2c[0, :3, 1].float()
        pivot = pivot_of(model.animate(avatar, expression, camera=camera))
        d = math.radians(ann - a0[0])
        start = apply_correction(camera, d * up, torch.zeros(3), pivot)
        if (head_angles(start)[0] - a0[0]) * (ann - a0[0]) < 0:  # the up axis turns the other way
            start = apply_correction(camera, -d * up, torch.zeros(3), pivot)
        cfg = dataclasses.replace(config or AlignConfig(), yaw_sweep_deg=())
        r2 = align_camera(lambda c: model.animate(avatar, expression, camera=c), start, target[0], m[0], cfg, pivot=pivot)
        ro0 = render(model.animate(avatar, expression, camera=start), start, background=BACKGROUND_RGB)
        sc0 = _score(ro0.rgb.clamp(0, 1), ro0.alpha, target, m, None, None, None)
        ro2 = render(model.animate(avatar, expression, camera=r2.camera), r2.camera, background=BACKGROUND_RGB)
        sc2 = _score(ro2.rgb.clamp(0, 1), ro2.alpha, target, m, None, None, None)
        cols.update({
            "annot_start_yaw": round(head_angles(start)[0], 2),
            "annot_start_masked_psnr_start": sc0["masked_psnr"],
            "annot_start_yaw_aligned": round(head_angles(r2.camera)[0], 2),
            "annot_start_masked_psnr": sc2["masked_psnr"],
            "annot_start_loss_end": round(r2.loss_end, 5),
        })
    return cols, pred[0]


def evaluate_set(model, folder: Path, steps_list: list[int], size: int = 256, faces=None, refine_cameras: bool = True, surface: bool = True,
                 photo_align: str = "turned", mirror: list[str] | None = None, own_cameras: bool = False, align_left_out: bool = False,
                 refine_preset: str | None = None, truth=None, truth_parts: str = "cameras") -> dict:
    """Leave-one-out over the photos of ``folder`` (see the module docstring); one row per (photo, steps)
    and mirror variant.

    ``surface``: reconstruct on the tracked head surface (``model/surface.py``), as the server does.
    ``refine_preset``: refine with ``REFINE_PRESETS[refine_preset]`` (``"auto"``: the one
    ``refine_preset_for`` picks, as the server does; its own camera setting; ``steps`` from
    ``steps_list``) instead of the default settings with ``refine_cameras``.
    ``photo_align``: the photometric registration of the photos' poses in tracking, ``"off"``, ``"turned"``
    (the default) or ``"all"`` (``TrackConfig.with_photo_align``).
    ``mirror``: variants of the mirrored virtual views (``model/mirror.py``) to compare on the same
    tracking, each ``"off"``, ``"on"`` (the config's thresholds), a yaw threshold in degrees
    (``mirror_min_yaw_deg``), ``"YAW/DROP"`` (and ``mirror_drop_seen_deg``), ``"YAW/DROP/MM"`` (and
    ``mirror_midline_m`` in millimetres) or ``"YAW/DROP/MM/OFFSET"`` (and ``mirror_blend_offset_deg``;
    an empty field keeps the config's value); rows
    then carry a ``"mirror"`` key and ``renders`` is keyed by ``(variant, steps)``. None: the
    model's config as it is, rows without that key, ``renders`` keyed by steps.
    ``own_cameras``: also the input-view check (``own_camera_rows``), returned as ``own_camera_rows``.
    ``align_left_out``: also the test-view pose alignment diagnostic (``aligned_columns``) in every
    row, and its render in ``renders`` under ``(key, "aligned")``.
    ``truth``: a synthetic set's ``data.photosets.PhotosetTruth`` (its photos in sorted-name order):
    after tracking, the tracked poses and intrinsics (``truth_parts="cameras"``), or those and the
    identity and expressions (``"all"``), are replaced by the true ones and the crops, masks and head
    surface are made from them (``tracking.pipeline.tracked_photos_from_fit``); rows carry ``"truth"``.
    Raises ValueError for another ``truth_parts`` or a ``truth`` of another photo count."""
    from ..model.surface import HeadSurface
    from ..refine import RefineConfig, refine_avatar, refine_config_for
    from ..render import render
    from ..train.faces import to_uint8_hwc
    from ..tracking import track_photos
    from ..tracking.pipeline import TrackConfig

    photos, names = _load_photos(folder)
    if truth is not None:
        if truth_parts not in TRUTH_PARTS:
            raise ValueError(f"truth_parts must be one of {', '.join(TRUTH_PARTS)}, got {truth_parts!r}")
        if len(truth.expressions) != len(names):
            raise ValueError(f"{folder.name}: the truth describes {len(truth.expressions)} photos, the folder holds {len(names)}")
        truth_of = dict(zip(names, range(len(names))))  # photo name -> its index in truth (before any photo is dropped)
    t0 = time.perf_counter()
    dropped = []
    while True:  # a photo the tracker cannot handle (e.g. no face found) is dropped and reported
        try:
            tr = track_photos(photos, TrackConfig.with_photo_align(photo_align, size=size), names=names)
            break
        except ValueError as e:
            bad = [i for i, n in enumerate(names) if n in str(e)]
            if not bad or len(names) <= 3:
                raise
            dropped.append(f"{names[bad[0]]}: {e}")
            log.warning("%s: dropping %s (%s)", folder.name, names[bad[0]], e)
            del photos[bad[0]], names[bad[0]]
    if truth is not None:
        tr = _with_truth(tr, photos, names, truth, [truth_of[n] for n in names], truth_parts, size)
    t_track = time.perf_counter() - t0
    crops = torch.from_numpy(tr.crops).permute(0, 3, 1, 2).float() / 255.0  # [V, 3, S, S]
    masks = torch.from_numpy(tr.masks)[:, None].float()  # [V, 1, S, S]
    bg = torch.tensor(BACKGROUND_RGB).view(1, 3, 1, 1)
    matted = crops * masks + bg * (1 - masks)
    cams = tr.cameras
    expr = torch.from_numpy(tr.expressions).float()
    v = len(names)
    padding = HeadSurface.from_tracking(tr).padding(size, size)  # [V, S, S] the crops beyond their photos (not the photos' background)
    variants = [None] if mirror is None else list(mirror)
    rows, renders = [], {(s if mv is None else (mv, s)): [] for mv in variants for s in steps_list}
    if align_left_out:
        renders.update({(key, "aligned"): [] for key in list(renders)})
    if own_cameras:
        own_rows = own_camera_rows(model, folder.name, tr, matted, masks, names, faces, variants, surface)
    for k, mv in ((k, mv) for k in range(v) for mv in variants):
        keep = [i for i in range(v) if i != k][: model.config.max_views]
        imgs, in_cams = model.prepare(matted[keep], cams[keep])
        head = HeadSurface.from_tracking(tr).subset(keep) if surface else None
        t1 = time.perf_counter()
        with mirror_variant(model.config.gaussians, mv):
            avatar0 = model.reconstruct(imgs, in_cams, expressions=expr[keep], surface=head)
        t_rec = time.perf_counter() - t1
        target = matted[k : k + 1]
        m = (masks[k : k + 1] > 0.5).float()
        t_img = to_uint8_hwc(target[0])
        t_desc, n_photo, t_box = _identity(faces, t_img) if faces is not None else (None, None, None)
        n_photo_cnn = _count_cnn(faces, t_img) if faces is not None else None
        in_frame = ~padding[k]
        for steps in steps_list:
            t1 = time.perf_counter()
            res = refine_avatar(
                model, avatar0, matted[keep], cams[keep], masks[keep], expressions=expr[keep],
                config=RefineConfig(steps=steps, optimize_cameras=refine_cameras) if refine_preset is None else refine_config_for(avatar0, steps, refine_preset),
            )
            dt = time.perf_counter() - t1
            g = model.animate(res.avatar, expr[k], camera=cams[k : k + 1])  # as the server draws it (view blending, model/viewblend.py)
            ro = render(g, cams[k : k + 1], background=BACKGROUND_RGB)
            pred = ro.rgb.clamp(0, 1)  # [1, 3, S, S]
            row = {
                "set": folder.name,
                "left_out": names[k],
                "steps": steps,
                **_score(pred, ro.alpha, target, m, faces, t_desc, t_box, in_frame),
                "faces_in_photo": n_photo,
                "cnn_faces_in_photo": n_photo_cnn,
                "refine_s": round(dt, 2),
                "reconstruct_s": round(t_rec, 2),
                "gaussians": len(res.avatar.gaussians),
            }
            if mv is not None:
                row["mirror"] = mv
            if truth is not None:
                row["truth"] = truth_parts
            key = steps if mv is None else (mv, steps)
            if align_left_out:
                with mirror_variant(model.config.gaussians, mv):
                    cols, pred_al = aligned_columns(model, res.avatar, expr[k], cams[k : k + 1], target, m, faces, t_desc, t_box, names[k])
                row.update(cols)
                renders[(key, "aligned")].append(pred_al)
            rows.append(row)
            renders[key].append(pred[0])
    out = {"set": folder.name, "track_s": round(t_track, 1), "dropped": dropped, "rows": rows, "targets": list(matted.unbind(0)), "renders": renders}
    if own_cameras:
        out["own_camera_rows"] = own_rows
    return out


TRUTH_PARTS = ("cameras", "all")  # evaluate_set's truth_parts / the CLI's --truth


def _with_truth(tr, photos: list[np.ndarray], names: list[str], truth, idx: list[int], parts: str, size: int):
    """``tr`` (a ``TrackedPhotos``) remade with the true cameras (``parts="cameras"``), or cameras,
    identity and expressions (``"all"``) of ``truth`` rows ``idx`` (one per photo)."""
    from ..tracking.camera import cameras_to_pose
    from ..tracking.fit import LandmarkModel
    from ..tracking.pipeline import TrackConfig, tracked_photos_from_fit

    cams = truth.cameras.flatten()
    R, t = cameras_to_pose(cams)
    fit = dataclasses.replace(tr.fit, rotations=R[idx].astype(np.float64), translations=t[idx].astype(np.float64),
                              K=cams.K[idx].double().numpy())
    if parts == "all":
        fit.identity = np.asarray(truth.identity, np.float64).copy()
        fit.expressions = np.asarray(truth.expressions[idx], np.float64).copy()
    cfg = TrackConfig(size=size)
    model = LandmarkModel.from_head_model(num_identity=cfg.fit.num_identity, layout=tr.layout)
    return tracked_photos_from_fit(photos, fit, tr.landmarks, model, cfg, names=names)


MIRROR_FIELDS = ("mirror_views", "mirror_min_yaw_deg", "mirror_drop_seen_deg", "mirror_midline_m", "mirror_blend_offset_deg")


@contextmanager
def mirror_variant(gcfg, mv: str | None):
    """Set a ``GaussianHeadConfig``'s mirrored-view fields to the variant ``mv`` (``evaluate_set``'s
    ``mirror``; None: as they are) for the ``with`` block, then restore them."""
    saved = {f: getattr(gcfg, f) for f in MIRROR_FIELDS}
    try:
        if mv is not None:
            gcfg.mirror_views = mv != "off"
            if mv not in ("on", "off"):
                parts = mv.split("/")
                gcfg.mirror_min_yaw_deg = float(parts[0])
                if len(parts) > 1 and parts[1]:
                    gcfg.mirror_drop_seen_deg = float(parts[1])
                if len(parts) > 2 and parts[2]:
                    gcfg.mirror_midline_m = float(parts[2]) / 1000
                if len(parts) > 3 and parts[3]:
                    gcfg.mirror_blend_offset_deg = float(parts[3])
        yield gcfg
    finally:
        for f, x in saved.items():
            setattr(gcfg, f, x)


def own_camera_rows(model, set_name: str, tr, matted, masks, names, faces, variants, surface: bool = True) -> list[dict]:
    """The input-view check: the avatar of all of a set's photos (at most ``max_views``), rendered
    at each of those photos' own tracked camera with its tracked expression, per mirror variant;
    one row per (variant, photo) with the leave-one-out rows' scores (``_score``: ``masked_psnr``,
    ``identity_distance``, ``error_split``'s terms, ``beyond_mask_frac``, ...)."""
    from ..model.surface import HeadSurface
    from ..render import render
    from ..train.faces import to_uint8_hwc

    cams, expr = tr.cameras, torch.from_numpy(tr.expressions).float()
    keep = list(range(len(names)))[: model.config.max_views]
    imgs, in_cams = model.prepare(matted[keep], cams[keep])
    tracked = HeadSurface.from_tracking(tr)
    head = tracked.subset(keep) if surface else None
    padding = tracked.padding(matted.shape[-1], matted.shape[-2])
    photo_faces = {k: _identity(faces, to_uint8_hwc(matted[k])) if faces is not None else (None, None, None) for k in keep}  # each photo's descriptor, once for all variants
    rows = []
    for mv in variants:
        with mirror_variant(model.config.gaussians, mv):
            av = model.reconstruct(imgs, in_cams, expressions=expr[keep], surface=head)
        for k in keep:
            ro = render(model.animate(av, expr[k], camera=cams[k : k + 1]), cams[k : k + 1], background=BACKGROUND_RGB)
            m, target = (masks[k : k + 1] > 0.5).float(), matted[k : k + 1]
            t_desc, _, t_box = photo_faces[k]
            rows.append({"set": set_name, "photo": names[k], "mirror": mv, **_score(ro.rgb.clamp(0, 1), ro.alpha, target, m, faces, t_desc, t_box, ~padding[k])})
    return rows


def _mean(vals):
    vals = [x for x in vals if x is not None]
    return float(np.mean(vals)) if vals else None


def _count_one(rs, key):
    if all(r.get(key) is None for r in rs):
        return "n/a"
    return f"{sum(1 for r in rs if r.get(key) == 1)}/{len(rs)}"


def _fmt(x, spec):
    return "n/a" if x is None else format(x, spec)


def summary_table(rows: list[dict]) -> str:
    """Markdown table: one line per (set, steps) with the means over left-out photos.

    Columns after identity: photos with exactly one face by HOG (renders, left-out photos) and by
    dlib's CNN detector (renders, photos); the mean share of the mask left uncovered by the render,
    the mean PSNR each error term alone would allow and the mean share of the error on the mask's
    outline (``error_split``), and the mean share the render draws beyond the mask (``beyond_mask``)."""
    mir = any("mirror" in r for r in rows)
    head = (
        "| set | refine steps | photos | masked PSNR ↑ | masked SSIM ↑ | identity distance ↓ | renders with exactly 1 face | left-out photos with exactly 1 face "
        "| CNN: renders with 1 face | CNN: photos with 1 face | mask uncovered | PSNR, uncovered error only | PSNR, covered error only "
        "| error on the mask's outline | render beyond the mask |\n"
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    )
    if mir:  # the mirrored-view variant (model/mirror.py) after the set
        head = head.replace("| set |", "| set | mirror |", 1).replace("|---|", "|---|---|", 1)
    body = ""
    keys = sorted({(r["set"], r.get("mirror", ""), r["steps"]) for r in rows}, key=lambda k: (k[0], [r.get("mirror", "") for r in rows].index(k[1]), k[2]))
    for s, mv, st in keys:
        rs = [r for r in rows if r["set"] == s and r["steps"] == st and r.get("mirror", "") == mv]
        idd = _mean([r["identity_distance"] for r in rs])
        unc = _mean([r.get("uncovered_frac") for r in rs])
        body += (
            f"| {s} |{f' {mv} |' if mir else ''} {st} | {len(rs)} | {_mean([r['masked_psnr'] for r in rs]):.2f} | {_mean([r['masked_ssim'] for r in rs]):.3f} | "
            f"{_fmt(idd, '.3f')} | {_count_one(rs, 'faces_in_render')} | {_count_one(rs, 'faces_in_photo')} | "
            f"{_count_one(rs, 'cnn_faces_in_render')} | {_count_one(rs, 'cnn_faces_in_photo')} | "
            f"{'n/a' if unc is None else f'{100 * unc:.1f}%'} | {_fmt(_mean([r.get('psnr_uncovered_only') for r in rs]), '.2f')} | "
            f"{_fmt(_mean([r.get('psnr_covered_only') for r in rs]), '.2f')} | {_pct(_mean([r.get('outline_error_share') for r in rs]))} | "
            f"{_pct(_mean([r.get('beyond_mask_frac') for r in rs]))} |\n"
        )
    return head + body


def _pct(x) -> str:
    return "n/a" if x is None else f"{100 * x:.1f}%"


def _median(vals):
    vals = [x for x in vals if x is not None]
    return float(np.median(vals)) if vals else None


def align_summary_table(rows: list[dict]) -> str:
    """Markdown table of the test-view pose alignment diagnostic (rows with ``aligned_masked_psnr``):
    one line per (set, mirror variant, steps), the means at the tracked camera and at the aligned one,
    and the median correction. A diagnostic beside the leave-one-out protocol, not the protocol."""
    rows = [r for r in rows if "aligned_masked_psnr" in r]
    if not rows:
        return ""
    head = (
        "| set | refine steps | photos | masked PSNR, tracked -> aligned camera | masked SSIM | identity distance | renders with 1 face (HOG) "
        "| CNN: renders with 1 face | median correction (deg; mm) |\n|---|---:|---:|---|---|---|---|---|---|\n"
    )
    body = ""
    keys = sorted({(r["set"], r.get("mirror", ""), r["steps"]) for r in rows}, key=lambda k: (k[0], [r.get("mirror", "") for r in rows].index(k[1]), k[2]))
    for s, mv, st in keys:
        rs = [r for r in rows if r["set"] == s and r["steps"] == st and r.get("mirror", "") == mv]
        pair = lambda key, spec: f"{_fmt(_mean([r[key] for r in rs]), spec)} -> {_fmt(_mean([r['aligned_' + key] for r in rs]), spec)}"  # noqa: E731
        one = lambda key: f"{_count_one(rs, key)} -> {_count_one(rs, 'aligned_' + key)}"  # noqa: E731
        body += (
            f"| {s}{f' ({mv})' if mv else ''} | {st} | {len(rs)} | {pair('masked_psnr', '.2f')} | {pair('masked_ssim', '.3f')} | {pair('identity_distance', '.3f')} | "
            f"{one('faces_in_render')} | {one('cnn_faces_in_render')} | "
            f"{_fmt(_median([r['align_rotation_deg'] for r in rs]), '.1f')}; {_fmt(_median([r['align_translation_mm'] for r in rs]), '.1f')} |\n"
        )
    return head + body


def align_photo_table(rows: list[dict]) -> str:
    """Markdown table, one line per row with the alignment diagnostic: the head's yaw annotated (file
    name), at the tracked and at the aligned camera, the pitch and roll change, the correction, and
    masked PSNR / identity at both cameras."""
    rows = [r for r in rows if "aligned_masked_psnr" in r]
    if not rows:
        return ""
    out = (
        "| set | photo | steps | yaw annotated | yaw tracked | yaw aligned | pitch tracked -> aligned | roll change | correction (deg; mm) "
        "| masked PSNR tracked -> aligned | identity tracked -> aligned | from the annotated yaw: yaw aligned (PSNR start -> aligned; lower loss than from the tracked yaw?) |"
        "\n|---|---|---:|---:|---:|---:|---|---:|---|---|---|---|\n"
    )
    for r in rows:
        mv = f" ({r['mirror']})" if r.get("mirror") else ""
        out += (
            f"| {r['set']}{mv} | {r['left_out']} | {r['steps']} | {_fmt(r['yaw_annotated'], '+.0f')} | "
            f"{r['yaw_tracked']:.1f} | {r['yaw_aligned']:.1f} | {r['pitch_tracked']:.1f} -> {r['pitch_aligned']:.1f} | {r['align_droll_deg']:+.1f} | "
            f"{r['align_rotation_deg']:.1f}; {r['align_translation_mm']:.1f} | {r['masked_psnr']:.2f} -> {r['aligned_masked_psnr']:.2f} | "
            f"{_fmt(r['identity_distance'], '.3f')} -> {_fmt(r['aligned_identity_distance'], '.3f')} | {_from_annotation(r)} |\n"
        )
    return out


def _from_annotation(r: dict) -> str:
    if "annot_start_yaw_aligned" not in r:
        return "-"
    better = "yes" if r["annot_start_loss_end"] < r["align_loss_end"] else "no"
    return f"{r['annot_start_yaw_aligned']:.1f} ({r['annot_start_masked_psnr_start']:.2f} -> {r['annot_start_masked_psnr']:.2f}; {better})"


def _column_name(c) -> str:
    """A grid column's title from its key in ``evaluate_set``'s renders: steps, ``(mirror, steps)``, or
    either followed by ``"aligned"`` (``--align-left-out``)."""
    if isinstance(c, tuple) and c[-1] == "aligned":
        return f"{_column_name(c[0])}, aligned"
    if isinstance(c, tuple):
        return f"mirror {c[0]}, {c[1]} steps"
    return f"{c} refine steps"


def grid_titles(cols) -> list[str]:
    """The ``--grid`` picture's column titles: the matted left-out photo, then one per render column."""
    return ["left-out photo"] + [_column_name(c) for c in cols]


def _score_label(psnr, identity) -> str:
    return f"{psnr:.1f} dB, id " + ("-" if identity is None else f"{identity:.2f}")


def grid_labels(rows: list[dict], cols) -> list[list[str]]:
    """One set's ``--grid`` cell labels, one list per left-out photo (its set and name over the photo;
    masked PSNR and dlib identity distance over each render, "-" where dlib found no face), matched to
    ``rows`` by the column keys ``evaluate_set`` files its renders under."""
    out = {}
    for r in rows:
        key = r["steps"] if "mirror" not in r else (r["mirror"], r["steps"])
        cells = out.setdefault(r["left_out"], {"photo": f"{r['set']} {Path(r['left_out']).stem}"})
        cells[key] = _score_label(r["masked_psnr"], r["identity_distance"])
        if "aligned_masked_psnr" in r:
            cells[(key, "aligned")] = _score_label(r["aligned_masked_psnr"], r["aligned_identity_distance"])
    return [[cells["photo"]] + [cells.get(c) for c in cols] for cells in out.values()]


def main(argv=None) -> int:
    from ..tracking.pipeline import PHOTO_ALIGN_MODES, TURNED_MIN_YAW_DEG

    ap = argparse.ArgumentParser(prog="python -m fastgha_core.refine.realsets",
                                 description="leave-one-out evaluation on photo sets: the real ones, or held-out synthetic ones with --synthetic")
    ap.add_argument("--root", default=None, help="folder of sets (default $FASTGHA_REALSETS or ../shared/realsets)")
    ap.add_argument("--sets", default=None, help="comma-separated set names (default: all)")
    ap.add_argument("--model", default="tiny")
    ap.add_argument("--refine-steps", default="0,60", help="comma-separated refinement step counts to compare (default 0,60)")
    ap.add_argument("--no-refine-cameras", action="store_true", help="refine without per-view camera corrections")
    ap.add_argument("--refine-preset", default=None, help="refine with this REFINE_PRESETS entry (e.g. photos: colours only; auto: as the server picks it) "
                    "and its own camera setting, instead of the default settings with camera corrections")
    ap.add_argument("--no-surface", action="store_true", help="use the network's depth instead of the tracked head surface")
    ap.add_argument("--photo-align", default="turned", choices=PHOTO_ALIGN_MODES,
                    help=f"the photometric registration of the photos' poses in tracking: off, the photos turned >= {TURNED_MIN_YAW_DEG:g} degrees "
                    "(the default) or all (TrackConfig.with_photo_align)")
    ap.add_argument("--no-cnn-faces", action="store_true", help="skip dlib's CNN face detector column (slower than HOG)")
    ap.add_argument("--size", type=int, default=256, help="crop side of the tracked photos and of the renders")
    ap.add_argument("--mirror", default=None,
                    help="comma-separated mirrored-view variants to compare on the same tracking (model/mirror.py): off, on (the config's thresholds), "
                    "a yaw threshold in degrees or YAW/DROP/MM/OFFSET, trailing fields optional (mirror_min_yaw_deg / mirror_drop_seen_deg / mirror_midline_m in mm / mirror_blend_offset_deg), e.g. off,30,30/60,30/0/20,30///20 (default: the model's config)")
    ap.add_argument("--own-cameras", action="store_true",
                    help="also render the avatar of all of a set's photos at each photo's own camera (the input-view check; per --mirror variant)")
    ap.add_argument("--align-left-out", action="store_true",
                    help="also the test-view pose alignment diagnostic: the avatar frozen, the left-out camera optimised against the left-out photo "
                    "(refine/testpose.py), scored beside the tracked camera; not the leave-one-out protocol")
    ap.add_argument("--synthetic", type=int, default=0, metavar="N",
                    help="instead of the real sets: N held-out synthetic photo sets laid out like them (fastgha_core/data/photosets.py), "
                    "written to --root when given (else a temporary folder) and evaluated the same way, tracking included")
    ap.add_argument("--first-seed", type=int, default=None,
                    help="with --synthetic: the first subject's seed; the sets use seeds S..S+N-1, each held out (1000000-1009999), in folders syn<seed> (default 1000700)")
    ap.add_argument("--truth", default=None, choices=TRUTH_PARTS,
                    help="with --synthetic: replace what tracking found by the truth the photos were drawn from, to split the error between "
                    "tracking and reconstruction: cameras (poses and focal length) or all (also identity and expressions)")
    ap.add_argument("--json", default=None, help="write all rows here")
    ap.add_argument("--grid", default=None, help="write a grid picture here (NOT inside the repository)")
    args = ap.parse_args(argv)
    if args.synthetic < 0:
        ap.error(f"--synthetic must be >= 0, got {args.synthetic}")
    if args.first_seed is not None and not args.synthetic:
        ap.error("--first-seed needs --synthetic N with N >= 1")
    if args.truth is not None and not args.synthetic:
        ap.error("--truth needs --synthetic N with N >= 1: only the synthetic sets' truth is known")
    if args.synthetic:
        from ..data.photosets import PHOTOSET_FIRST_SEED, write_photosets

        if args.sets:
            ap.error("--sets picks among the real sets; with --synthetic the sets are chosen by N and --first-seed")
        if args.root and Path(args.root).exists() and not Path(args.root).is_dir():
            ap.error(f"--root {args.root} is a file: --synthetic writes its sets into a folder there")
        if args.root:  # never mixed into a folder of real sets: every set under --root would be evaluated with them
            others = [d.name for d in list_sets(Path(args.root)) if not d.name.startswith("syn")]
            if others:
                ap.error(f"--synthetic writes its sets to --root, which holds other photo sets ({', '.join(others[:3])}): give an empty or new folder")
        with ExitStack() as stack:
            root = Path(args.root) if args.root else Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="fastgha-photosets-")))
            try:
                folders = write_photosets(root, args.synthetic, PHOTOSET_FIRST_SEED if args.first_seed is None else args.first_seed)
            except ValueError as e:
                ap.error(str(e))
            print(f"{args.synthetic} synthetic photo set(s) written to {root}", flush=True)
            return _run(ap, args, root, only=[d.name for d in folders])
    return _run(ap, args, Path(args.root) if args.root else realsets_root())


def _truth_of(folder: Path, args: argparse.Namespace):
    """With ``--truth``: the ``PhotosetTruth`` of the synthetic set ``folder`` (``syn<seed>``, the default views); else None."""
    if args.truth is None:
        return None
    from ..data.photosets import photoset_truth

    return photoset_truth(int(folder.name[3:]))


def _run(ap: argparse.ArgumentParser, args: argparse.Namespace, root: Path, only: list[str] | None = None) -> int:
    """``main`` after its arguments: evaluate the sets under ``root`` (``only`` those names when given)."""
    logging.basicConfig(level=logging.WARNING)
    from ..model.fastgha import load_model
    from ..train.faces import load_face_metrics

    sets = list_sets(root)
    if only is not None:
        sets = [s for s in sets if s.name in set(only)]
    if args.sets:
        want = set(args.sets.split(","))
        sets = [s for s in sets if s.name in want]
    if not sets:
        print(f"no photo sets under {root}: nothing to evaluate")
        return 0
    model = load_model(args.model)
    faces = load_face_metrics()
    if faces is not None and not args.no_cnn_faces:
        faces = _load_cnn(faces)
    steps_list = [int(s) for s in args.refine_steps.split(",")]
    from . import REFINE_PRESETS

    if args.refine_preset is not None and args.refine_preset != "auto" and args.refine_preset not in REFINE_PRESETS:
        ap.error(f"--refine-preset must be auto or one of {', '.join(REFINE_PRESETS)}, got {args.refine_preset!r}")
    mirror = None
    if args.mirror:
        mirror = [x.strip() for x in args.mirror.split(",") if x.strip()]
        for x in mirror:
            if x not in ("on", "off"):
                try:
                    if len(x.split("/")) > 4:
                        raise ValueError(x)
                    [float(p) for p in x.split("/") if p]
                except ValueError:
                    ap.error(f"--mirror: each variant must be off, on or YAW[/DROP[/MM[/OFFSET]]] (numbers), got {x!r}")
    cols = steps_list if mirror is None else [(mv, s) for mv in mirror for s in steps_list]
    if args.align_left_out:  # each render followed by the render at the aligned camera
        cols = [x for c in cols for x in (c, (c, "aligned"))]
    all_rows, own_rows, grid, labels = [], [], [], []
    for folder in sets:
        try:
            out = evaluate_set(model, folder, steps_list, args.size, faces, refine_cameras=not args.no_refine_cameras, surface=not args.no_surface,
                               photo_align=args.photo_align, mirror=mirror, own_cameras=args.own_cameras, align_left_out=args.align_left_out,
                               refine_preset=args.refine_preset, truth=_truth_of(folder, args), truth_parts=args.truth or "cameras")
        except (ValueError, ImportError) as e:
            print(f"{folder.name}: skipped ({e})")
            continue
        all_rows += out["rows"]
        for k, t in enumerate(out["targets"]):
            grid.append([t] + [out["renders"][c][k] for c in cols])
        labels += grid_labels(out["rows"], cols)
        print(f"{folder.name}: tracked in {out['track_s']} s; photos dropped (tracking failed): {out['dropped'] or 'none'}", flush=True)
        for r in out["rows"]:
            print(json.dumps(r), flush=True)
        for mv in dict.fromkeys(r["mirror"] for r in out.get("own_camera_rows", [])):
            rs = [r for r in out["own_camera_rows"] if r["mirror"] == mv]
            idd = _mean([r["identity_distance"] for r in rs])
            print(f"{folder.name}: avatar of all photos at their own cameras, mirror {mv or 'as configured'}: masked PSNR {_mean([r['masked_psnr'] for r in rs]):.2f} dB "
                  f"({' / '.join(format(r['masked_psnr'], '.2f') for r in rs)}), identity {_fmt(idd, '.3f')}, "
                  f"error on the mask's outline {' / '.join(_pct(r['outline_error_share']) for r in rs)}, "
                  f"beyond the mask {' / '.join(_pct(r['beyond_mask_frac']) for r in rs)}", flush=True)
        own_rows += out.get("own_camera_rows", [])
    print(summary_table(all_rows))
    if args.align_left_out:
        print("Test-view pose alignment (a diagnostic: the left-out camera optimised against the left-out photo, the avatar frozen; "
              "the leave-one-out protocol is the table above, at the tracked camera):\n")
        print(align_summary_table(all_rows))
        print(align_photo_table(all_rows))
    if args.json:
        Path(args.json).write_text(json.dumps(all_rows + [dict(r, check="own_camera") for r in own_rows], indent=1))
    if args.grid and grid:
        from ..train.visualize import save_grid

        save_grid(Path(args.grid), grid, titles=grid_titles(cols), labels=labels)
        print(f"grid written to {args.grid} (rows: left-out photos; columns: {', '.join(grid_titles(cols))})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
