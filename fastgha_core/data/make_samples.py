"""Regenerate the shipped sample subjects: ``python -m fastgha_core.data.make_samples [--out DIR]``.

Deterministic: the same code writes the same bytes. See ``samples.py`` for the folder contents.
Seeds are held-out (``synthetic.HELDOUT_SEEDS``), picked once for a spread of skin tones and hair.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
from pathlib import Path

import numpy as np

from ..cameras import cameras_to_json, orbit_cameras
from .layout import save_image
from .samples import SAMPLES_DIR
from .synth_writer import write_subject_request
from .synthetic import FOV_DEG, HELDOUT_SEEDS, make_sequence, render_views, subject_name

__all__ = ["SAMPLE_SEEDS", "make_sample", "main"]

logger = logging.getLogger(__name__)

SAMPLE_SEEDS = (1_000_000, 1_000_001, 1_000_003)
RESOLUTION = 256
FRAMES = 48
JPEG_QUALITY = 90


def make_sample(seed: int, out: Path, frames: int = FRAMES, resolution: int = RESOLUTION, jpeg_quality: int = JPEG_QUALITY) -> Path:
    """Write one sample subject to ``out/<subject>/``."""
    if seed not in HELDOUT_SEEDS:
        raise ValueError(f"sample subjects must use held-out seeds {HELDOUT_SEEDS}, got {seed}")
    name = subject_name(seed)
    folder = Path(out) / name
    if folder.exists():
        shutil.rmtree(folder)
    (folder / "gt").mkdir(parents=True)
    capture = make_sequence(seed, timesteps=32, num_cameras=16, resolution=resolution, sequence=0)
    write_subject_request(capture, folder / "request", k=4, image_format="jpg", jpeg_quality=jpeg_quality)
    anim = make_sequence(seed, timesteps=frames, num_cameras=1, resolution=resolution, sequence=1, activity=0.9, strength=(0.6, 1.0))
    np.save(folder / "expressions.npy", anim.expressions)
    orbit = orbit_cameras(frames, radius=1.0, fov_deg=FOV_DEG, width=resolution, height=resolution)
    (folder / "orbit.json").write_text(json.dumps(cameras_to_json(orbit), indent=1) + "\n")
    for t in range(frames):
        view = render_views(anim, t, orbit[t : t + 1])[0]
        save_image(folder / "gt" / f"{t:04d}.jpg", view.image, jpeg_quality)
    meta = {
        "name": name,
        "subject": name,
        "seed": int(seed),
        "expression_space": "ict53",
        "num_frames": frames,
        "resolution": resolution,
        "fov_deg": FOV_DEG,
        "generator": "python -m fastgha_core.data.make_samples",
    }
    (folder / "meta.json").write_text(json.dumps(meta, indent=1) + "\n")
    return folder


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=str(SAMPLES_DIR), help=f"output folder (default {SAMPLES_DIR})")
    p.add_argument("--frames", type=int, default=FRAMES)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    for seed in SAMPLE_SEEDS:
        folder = make_sample(seed, Path(args.out), frames=args.frames)
        size = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
        logger.info("wrote %s (%.0f KB)", folder, size / 1024)
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
