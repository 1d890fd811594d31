"""Tracking on the real multi-view photo sets: estimated yaw against the annotated one.

``python -m fastgha_core.tracking.realsets [--root ../shared/realsets] [--json out.json]``

The sets (non-commercial evaluation material, never shipped) live outside the repository, in
``../shared/realsets`` relative to the repository root or where ``FASTGHA_REALSETS`` points; each
sub-folder holds the photos of one person, and each file name carries the annotated yaw as
``yaw<signed degrees>`` (``yaw0``, ``yaw+55``, ``yaw-70``): 0 = facing the camera, + = nose towards
the image's right edge (annotations are estimates, +-10-15 degrees).

Each set is tracked jointly (``track_photos``: one identity, one field of view); per photo the
report gives the annotated and estimated yaw, the estimated pitch (beside the annotated one where the
name carries ``pitch<signed degrees>``, as the synthetic photo sets' do) and roll, the landmark RMS,
the largest expression weight and the set's tracking time in seconds (``set_seconds``; the
detector is loaded before the first set). On the synthetic photo sets that ``python -m
fastgha_core.refine.realsets --synthetic N --root DIR`` writes (folders ``syn<seed>``, the default
views), where the true poses are known (``data.photosets.photoset_truth``), each row also carries
``rotation_error``: the geodesic angle in degrees between the tracked head rotation and the true one
(yaw, pitch and roll together), and the report prints their median and mean per annotated yaw.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
from pathlib import Path

import numpy as np

from .evaluate import rotation_error_deg
from .fit import head_angles_deg  # (yaw, pitch, roll) of a fitted head: the fitter's convention

__all__ = ["realsets_root", "annotated_yaw", "annotated_pitch", "head_angles_deg", "evaluate_realsets"]

_YAW = re.compile(r"yaw([+-]?\d+(?:\.\d+)?)")
_PITCH = re.compile(r"pitch([+-]?\d+(?:\.\d+)?)")


def realsets_root() -> Path:
    """``$FASTGHA_REALSETS`` or ``<repository root>/../shared/realsets`` (may not exist)."""
    env = os.environ.get("FASTGHA_REALSETS")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2].parent / "shared" / "realsets"


def annotated_yaw(name: str) -> float | None:
    """Degrees from a file name's ``yaw<deg>`` tag, or None."""
    m = _YAW.search(Path(name).stem)
    return float(m.group(1)) if m else None


def annotated_pitch(name: str) -> float | None:
    """Degrees from a file name's ``pitch<signed degrees>`` tag (+ = nose up; the synthetic photo sets'
    names, ``data/photosets.py``), or None (the real sets' ``pitch-down`` / ``pitch-up`` carry no number)."""
    m = _PITCH.search(Path(name).stem)
    return float(m.group(1)) if m else None


def _read(path: Path) -> np.ndarray:
    try:
        from ..images import read_image  # the project's one decoder (EXIF orientation applied)

        return read_image(path, max_pixels=64_000_000).rgb
    except ImportError:  # before fastgha_core.images exists: PIL with the EXIF orientation applied
        from PIL import Image, ImageOps

        with Image.open(path) as im:
            return np.asarray(ImageOps.exif_transpose(im).convert("RGB"))


def evaluate_realsets(root: Path | None = None, detector=None, config=None) -> list[dict]:
    """One dict per photo of every set under ``root`` (module doc). Raises like ``track_photos``."""
    from .pipeline import TrackConfig, track_photos

    root = Path(root) if root is not None else realsets_root()
    sets = sorted(p for p in root.iterdir() if p.is_dir())
    if not sets:
        raise ValueError(f"no photo sets (sub-folders) in {root}")
    if detector is None:
        from .faces import load_face_detector

        detector = load_face_detector()
    rows = []
    for d in sets:
        paths = sorted(p for p in d.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
        imgs = [_read(p) for p in paths]
        t0 = time.perf_counter()
        res = track_photos(imgs, config or TrackConfig(), names=[f"{d.name}/{p.name}" for p in paths], detector=detector)
        seconds = time.perf_counter() - t0
        true_R = _true_rotations(d, paths)
        for v, p in enumerate(paths):
            yaw, pitch, roll = head_angles_deg(res.fit.rotations[v])
            ann = annotated_yaw(p.name)
            ann_pitch = annotated_pitch(p.name)
            top = int(np.argmax(res.expressions[v]))
            from ..expressions import ICT53_NAMES

            rows.append({
                "set": d.name, "photo": p.name, "yaw_annotated": ann, "yaw": round(yaw, 1), "pitch": round(pitch, 1),
                "roll": round(roll, 1), "yaw_error": None if ann is None else round(abs(yaw - ann), 1),
                "pitch_annotated": ann_pitch, "pitch_error": None if ann_pitch is None else round(abs(pitch - ann_pitch), 1),
                "rms_px": round(float(res.fit.rms_px[v]), 2), "max_expression": round(float(res.expressions[v, top]), 2),
                "max_expression_name": ICT53_NAMES[top], "set_seconds": round(seconds, 2),
                "align_deg": None if res.alignment is None else round(float(res.alignment.rotation_deg[v]), 2),
                "align_mm": None if res.alignment is None else [round(float(x), 1) for x in res.alignment.shift_mm[v]],
                "rms_px_before_align": None if res.alignment is None else round(float(res.alignment.rms_before[v]), 2),
                "rotation_error": None if true_R is None else round(rotation_error_deg(res.fit.rotations[v], true_R[v]), 2),
            })  # fmt: skip
    return rows


def _true_rotations(folder: Path, paths: list[Path]) -> np.ndarray | None:
    """``[V, 3, 3]`` true head -> camera rotations of a synthetic photo set (``syn<seed>`` holding
    exactly ``write_photoset``'s default photos), else None."""
    from ..data.photosets import PHOTOSET_VIEWS, photo_name, photoset_truth

    m = re.fullmatch(r"syn(\d+)", folder.name)
    if m is None or [p.name for p in paths] != [photo_name(i, y, q) for i, (y, q) in enumerate(PHOTOSET_VIEWS)]:
        return None
    return photoset_truth(int(m.group(1))).cameras.w2c[:, :3, :3].double().numpy()


def rotation_summary(rows: list[dict]) -> str | None:
    """The ``rotation_error`` of the rows that carry one: median and mean overall and per annotated
    yaw, one line each (None when no row does)."""
    known = [r for r in rows if r.get("rotation_error") is not None]
    if not known:
        return None
    errs = np.array([r["rotation_error"] for r in known])
    lines = [f"{len(known)} photos with a known pose: rotation error median {np.median(errs):.2f} deg, mean {errs.mean():.2f} deg"]
    for yaw in sorted({r["yaw_annotated"] for r in known}, key=lambda y: (y is None, y)):
        e = np.array([r["rotation_error"] for r in known if r["yaw_annotated"] == yaw])
        lines.append(f"  annotated yaw {yaw:g}: {len(e)} photos, median {np.median(e):.2f}, mean {e.mean():.2f} deg")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m fastgha_core.tracking.realsets", description=__doc__.split("\n")[0])
    p.add_argument("--root", default=None, help="folder of photo sets (default: ../shared/realsets or $FASTGHA_REALSETS)")
    p.add_argument("--json", default=None, help="also write the rows here")
    from .pipeline import PHOTO_ALIGN_MODES, TURNED_MIN_YAW_DEG, TrackConfig

    p.add_argument("--photo-align", default="turned", choices=PHOTO_ALIGN_MODES,
                   help=f"the photometric registration of the photos' poses: off, the photos turned >= {TURNED_MIN_YAW_DEG:g} degrees (the default) "
                   "or all (TrackConfig.with_photo_align)")
    a = p.parse_args(argv)

    rows = evaluate_realsets(Path(a.root) if a.root else None, config=TrackConfig.with_photo_align(a.photo_align))
    print("| set | photo | yaw annotated | yaw | error | pitch (annotated) | roll | RMS px | largest expression | registration (deg; mm) | RMS px before it |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        pitch = str(r["pitch"]) if r["pitch_annotated"] is None else f"{r['pitch']} ({r['pitch_annotated']:g})"
        reg = "-" if r["align_deg"] is None else f"{r['align_deg']}; {', '.join(f'{x:+.1f}' for x in r['align_mm'])}"
        print(f"| {r['set']} | {r['photo']} | {r['yaw_annotated']} | {r['yaw']} | {r['yaw_error']} | {pitch} | {r['roll']} | "
              f"{r['rms_px']} | {r['max_expression_name']} {r['max_expression']} | {reg} | {r['rms_px_before_align'] or '-'} |")  # fmt: skip
    secs = {r["set"]: r["set_seconds"] for r in rows}
    print("tracking time per set (s, detection + fit + crops + masks): " + ", ".join(f"{k} {v:.1f}" for k, v in secs.items()))
    errs = [r["yaw_error"] for r in rows if r["yaw_error"] is not None]
    print(f"{len(rows)} photos, yaw error median {np.median(errs):.1f} deg, max {max(errs):.1f} deg")
    perrs = [r["pitch_error"] for r in rows if r["pitch_error"] is not None]
    if perrs:  # names with a pitch<degrees> tag (the synthetic photo sets)
        print(f"{len(perrs)} photos with an annotated pitch, pitch error median {np.median(perrs):.1f} deg, max {max(perrs):.1f} deg")
    rot = rotation_summary(rows)
    if rot:  # the synthetic photo sets: the truth is known
        print(rot)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
