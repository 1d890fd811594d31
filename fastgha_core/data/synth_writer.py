"""Writing synthetic subjects to disk (used by ``fastgha synth`` and the sample generator)."""

from __future__ import annotations

import json
import logging
import re
import shutil
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from ..cameras import farthest_viewpoint_sampling
from .layout import write_request_folder, write_sequence
from .synthetic import SyntheticSequence, make_sequence, subject_name

__all__ = ["request_selection", "write_subject_request", "synth_dataset"]

logger = logging.getLogger(__name__)

_S_REQUEST = 5  # SeedSequence stream id for the request-folder choice


def request_selection(seq: SyntheticSequence, k: int = 4) -> list[tuple[int, int]]:
    """``k`` (timestep, camera) pairs: well-spread cameras (farthest-viewpoint sampling from a
    seeded random start) at ``k`` different random timesteps. Deterministic per sequence."""
    T, C = seq.num_timesteps, seq.num_cameras
    if not 1 <= k <= min(T, C):
        raise ValueError(f"k must be in [1, min(T={T}, C={C})], got {k}")
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([seq.seed, _S_REQUEST, seq.sequence_index])))
    start = int(rng.integers(C))
    cams = farthest_viewpoint_sampling(seq.cameras(0).centers, k, start=start)
    times = sorted(int(t) for t in rng.choice(T, size=k, replace=False))
    return list(zip(times, cams))


def write_subject_request(seq: SyntheticSequence, folder: str | Path, k: int = 4, image_format: str = "png", jpeg_quality: int = 95) -> Path:
    """A request folder of ``k`` photos of ``seq`` (see ``request_selection``) with masks."""
    pairs = request_selection(seq, k)
    views = [seq.view(t, c) for t, c in pairs]
    cams = [seq.cameras(t)[c : c + 1] for t, c in pairs]
    info = {
        "subject": seq.subject,
        "sequence": seq.sequence,
        "timesteps": [t for t, _ in pairs],
        "cameras": [c for _, c in pairs],
        "expressions": [seq.expression(t).tolist() for t, _ in pairs],
        "expression_space": seq.expression_space,
    }
    return write_request_folder(folder, views, cams, image_format=image_format, jpeg_quality=jpeg_quality, info=info)


def synth_dataset(
    out: str | Path,
    seeds: Iterable[int],
    timesteps: int = 32,
    num_cameras: int = 16,
    resolution: int = 256,
    image_format: str = "png",
    jpeg_quality: int = 95,
    depth: bool = True,
    request_views: int = 4,
    progress: Callable[[int], None] | None = None,
) -> list[Path]:
    """Write one sequence per seed to ``out/<subject>/seq000/`` and a request folder to
    ``out/<subject>/request/``. Returns the sequence folders.

    A subject folder that an earlier run wrote (every ``meta.json`` in it names this generator) is
    replaced as a whole, so no timestep, camera or request photo of the earlier run is left beside
    the new ones (they used to be, and the request folder then held more photos than cameras).

    Raises:
        ValueError: a subject folder exists and holds anything else (checked for every seed before
            anything is written or removed).
    """
    out = Path(out)
    seeds = [int(s) for s in seeds]
    earlier = [out / subject_name(seed) for seed in seeds if (out / subject_name(seed)).exists()]
    for folder in earlier:
        if not _written_by_us(folder):
            raise ValueError(f"{folder} exists and was not written by fastgha synth; choose another output folder")
    for folder in earlier:
        shutil.rmtree(folder)
    folders = []
    for seed in seeds:
        seq = make_sequence(int(seed), timesteps=timesteps, num_cameras=num_cameras, resolution=resolution)
        folder = write_sequence(out, seq, image_format=image_format, jpeg_quality=jpeg_quality, depth=depth, progress=progress,
                                extra_meta={"generator": "fastgha_core.data.synthetic", "seed": int(seed)})
        if request_views > 0:
            write_subject_request(seq, out / seq.subject / "request", request_views, image_format, jpeg_quality)
        folders.append(folder)
        logger.debug("wrote %s", folder)
    return folders


def _written_by_us(folder: Path) -> bool:
    """Whether ``folder`` is a subject folder of ``synth_dataset``: it holds only ``request/`` and
    sequence folders ``seqNNN/`` whose ``meta.json`` names ``fastgha_core.data.synthetic`` as their
    generator, or which have none yet (a run stopped before writing it: ``meta.json`` comes last)."""
    if not folder.is_dir():
        return False
    for child in folder.iterdir():
        if child.name == "request" and child.is_dir():
            continue
        if not (child.is_dir() and re.fullmatch(r"seq\d{3}", child.name)):
            return False
        meta = child / "meta.json"
        if meta.exists():
            try:
                generator = json.loads(meta.read_text()).get("extra", {}).get("generator")
            except (OSError, ValueError, AttributeError):
                return False
            if generator != "fastgha_core.data.synthetic":
                return False
    return True
