"""Synthetic photo sets laid out like the real ones: a held-out check for the real-photo evaluation.

``write_photosets(root, subjects, first_seed)`` writes one folder per held-out synthetic subject
(``synthetic.SyntheticSubject``: procedural skin, hair and lighting), each holding a few photos of
that person from around the head, named like the real sets' files (``NN_yaw+40_pitch+0.jpg``: the
true yaw and pitch in degrees) and nothing else: no cameras, no masks, no expressions. Finding them
is the tracker's job, as for a user's photos, so the leave-one-out of
``python -m fastgha_core.refine.realsets --synthetic N`` runs the real sets' protocol (tracking
included) on people whose every setting was never chosen on.

Conventions (the real sets' README and ``tracking/realsets.py``): yaw 0 = facing the camera, + =
nose towards the image's right edge; pitch + = nose up (the camera below the head). Each photo is
the subject rendered from ``CAMERA_DISTANCE`` metres at ``PHOTOSET_FOV_DEG`` (vertical field of view) over
``BACKGROUND_RGB`` with its own calm random expression (2-4 ``ict53`` shapes, weights U(0.1, 0.5)),
like people who hold still for a few photos. Everything is drawn from
``numpy.random.SeedSequence([seed, _S_PHOTOSET])``: a set is a pure function of its seed, views and size.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..cameras import Cameras
from .synthetic import CAMERA_DISTANCE, HELDOUT_SEEDS, SyntheticSubject

__all__ = ["PHOTOSET_VIEWS", "PHOTOSET_FIRST_SEED", "PHOTOSET_FOV_DEG", "write_photoset", "write_photosets", "photo_name", "PhotosetTruth", "photoset_truth"]

# (yaw, pitch) in degrees of each photo: a frontal, both sides at the real sets' turns short of a
# profile (MediaPipe finds no face in some 75-85-degree renders, as the tracking docs measure) and a
# pitched-up photo, as in phone-5 and studio-4.
PHOTOSET_VIEWS: tuple[tuple[float, float], ...] = ((0.0, 0.0), (-65.0, 0.0), (40.0, 0.0), (70.0, 0.0), (0.0, 25.0))
# First subject's seed: held out, and clear of the draws the docs' other evaluations use (1_000_000-1_000_003,
# 1_000_200-1_000_211, 1_000_400-1_000_419).
PHOTOSET_FIRST_SEED = 1_000_700
# Vertical field of view (degrees): wider than the training rig's FOV_DEG, so the photos show neck and
# shoulders around the head as photos of people do (the tracking evaluation's renders use the same).
PHOTOSET_FOV_DEG = 25.0
_S_PHOTOSET = 11  # SeedSequence stream id (synthetic.py's streams are 1-4, synth_writer.py's 5)


def photo_name(index: int, yaw: float, pitch: float) -> str:
    """``NN_yaw+Y_pitch+P.jpg`` (whole degrees, signed): the real sets' file names carry the yaw the same way."""
    return f"{index:02d}_yaw{round(yaw):+d}_pitch{round(pitch):+d}.jpg"


@dataclass
class PhotosetTruth:
    """What a photo set's ``V`` photos show, as drawn (``photoset_truth``): what tracking has to find."""

    identity: np.ndarray  # [100] the subject's ICT-FaceKit identity coefficients (SyntheticSubject.identity)
    expressions: np.ndarray  # [V, 53] float32 ict53 weights of each photo
    cameras: Cameras  # [V] of the photos (OpenCV, head at the world origin in the head model's axes)


def photoset_truth(seed: int, views: Sequence[tuple[float, float]] = PHOTOSET_VIEWS, size: int = 512,
                   subject: SyntheticSubject | None = None) -> PhotosetTruth:
    """The identity, per-photo expressions and cameras of ``write_photoset(folder, seed, views, size)``'s photos.

    Drawn from ``SeedSequence([seed, _S_PHOTOSET])`` in view order (the same draw the photos are
    rendered from). ``subject``: the seed's ``SyntheticSubject`` when already built. No checks:
    ``write_photoset`` validates its arguments before calling this."""
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), _S_PHOTOSET])))
    expressions = np.zeros((len(views), 53), dtype=np.float32)
    for e in expressions:
        k = int(rng.integers(2, 5))
        e[rng.choice(53, k, replace=False)] = rng.uniform(0.1, 0.5, k)
    cams = Cameras.stack([Cameras.facing_head(yaw, pitch, distance=CAMERA_DISTANCE, fov_deg=PHOTOSET_FOV_DEG, size=int(size)) for yaw, pitch in views])
    identity = (subject or SyntheticSubject(int(seed))).identity
    return PhotosetTruth(identity=np.asarray(identity, np.float32).copy(), expressions=expressions, cameras=cams)


def write_photoset(folder: str | Path, seed: int, views: Sequence[tuple[float, float]] = PHOTOSET_VIEWS, size: int = 512,
                   jpeg_quality: int = 95) -> list[Path]:
    """Render subject ``seed`` at every ``(yaw, pitch)`` of ``views`` into ``folder`` (created) as JPEGs.

    Args:
        folder: the set's folder; files already there with the same names are replaced.
        seed: a held-out seed (``synthetic.HELDOUT_SEEDS``).
        views: ``(yaw, pitch)`` pairs in degrees, |yaw| <= 90, |pitch| <= 45.
        size: the photos' side in pixels (square), >= 64.
        jpeg_quality: 1-100.
    Returns:
        The photos' paths, in ``views`` order (sorted names = that order).
    Raises:
        ValueError: a seed outside ``HELDOUT_SEEDS``, no views, a view out of range, a bad size or quality.
    """
    from PIL import Image

    if int(seed) not in HELDOUT_SEEDS:
        raise ValueError(f"photo sets use held-out seeds ({HELDOUT_SEEDS.start}-{HELDOUT_SEEDS.stop - 1}), got {seed}")
    if not views:
        raise ValueError("views must hold at least one (yaw, pitch) pair")
    for yaw, pitch in views:
        if not (abs(yaw) <= 90 and abs(pitch) <= 45):
            raise ValueError(f"each view needs |yaw| <= 90 and |pitch| <= 45 degrees, got ({yaw}, {pitch})")
    if int(size) < 64:
        raise ValueError(f"size must be >= 64 pixels, got {size}")
    if not 1 <= int(jpeg_quality) <= 100:
        raise ValueError(f"jpeg_quality must be in 1-100, got {jpeg_quality}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    subject = SyntheticSubject(int(seed))
    truth = photoset_truth(int(seed), views, int(size), subject)
    paths = []
    for i, (yaw, pitch) in enumerate(views):
        rgb = subject.render(subject.frame(truth.expressions[i]), truth.cameras[i : i + 1])[0].image  # [3, S, S] in [0, 1]
        img = (rgb.permute(1, 2, 0).numpy() * 255.0).round().astype(np.uint8)  # [S, S, 3]
        path = folder / photo_name(i, yaw, pitch)
        Image.fromarray(img).save(path, quality=int(jpeg_quality))
        paths.append(path)
    return paths


def write_photosets(root: str | Path, subjects: int = 4, first_seed: int = PHOTOSET_FIRST_SEED,
                    views: Sequence[tuple[float, float]] = PHOTOSET_VIEWS, size: int = 512) -> list[Path]:
    """``subjects`` sets, seeds ``first_seed ..``, each in ``root/syn<seed>/`` (``write_photoset``).

    Returns the sets' folders. Raises ValueError for ``subjects < 1``, seeds ``first_seed ..
    first_seed + subjects - 1`` not all held out (before anything is written), and as ``write_photoset``."""
    if int(subjects) < 1:
        raise ValueError(f"subjects must be >= 1, got {subjects}")
    last = int(first_seed) + int(subjects) - 1
    if int(first_seed) not in HELDOUT_SEEDS or last not in HELDOUT_SEEDS:
        raise ValueError(f"photo sets use held-out seeds ({HELDOUT_SEEDS.start}-{HELDOUT_SEEDS.stop - 1}); "
                         f"{subjects} set(s) from seed {first_seed} would use {first_seed}-{last}")
    root = Path(root)
    out = []
    for s in range(int(subjects)):
        d = root / f"syn{int(first_seed) + s}"
        write_photoset(d, int(first_seed) + s, views, size)
        out.append(d)
    return out
