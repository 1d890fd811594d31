"""Helpers shared by the ``fastgha bench`` targets: timing, the benchmark avatar, the machine."""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import time
from dataclasses import dataclass
from typing import Any, Callable

import torch

__all__ = ["Timing", "time_fn", "bench_model", "input_views", "bench_avatar", "load_average", "positive_int", "non_negative_int"]

log = logging.getLogger(__name__)


def positive_int(text: str) -> int:
    """argparse ``type`` of the count options (repeats, frames, Gaussians): an integer >= 1; 0 or a
    negative count used to mean "the default" or crash deep in torch."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text}")
    return value


def non_negative_int(text: str) -> int:
    """argparse ``type`` of counts where 0 means "skip": an integer >= 0."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text}")
    return value


@dataclass
class Timing:
    """Median wall-clock and process-CPU milliseconds over ``repeats`` timed runs (after warm-up).

    ``cpu_ms`` sums all threads of this process, so on a shared machine ``cpu_ms / wall_ms``
    shows how much of the wall time was spent working rather than waiting for a core.
    """

    wall_ms: float
    cpu_ms: float
    repeats: int
    min_ms: float

    def to_dict(self) -> dict:
        return {"wall_ms": self.wall_ms, "cpu_ms": self.cpu_ms, "min_ms": self.min_ms, "repeats": self.repeats}


def time_fn(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> Timing:
    """Time ``fn()`` ``repeats`` times after ``warmup`` untimed calls."""
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    for _ in range(warmup):
        fn()
    wall, cpu = [], []
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        wall.append(1e3 * (time.perf_counter() - t0))
        cpu.append(1e3 * (time.process_time() - c0))
    return Timing(statistics.median(wall), statistics.median(cpu), repeats, min(wall))


def load_average() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def bench_model(name: str = "tiny"):
    """The model to benchmark (shipped weights when present, else random with a warning)."""
    from ..model.fastgha import load_model

    return load_model(name)


def input_views(model, views: int, seed: int = 0):
    """``views`` input images ``[V, 3, S, S]`` and cameras ``[V]`` at the model's input size.

    Uses the first shipped sample subject (``fastgha_core/assets/samples``) when it exists, so that
    a trained model reconstructs a real head (its foreground gate decides how many Gaussians
    survive); beyond the sample's views its photos repeat (the network's cost does not depend on
    the pixel values). Without samples: random images on orbit cameras.
    """
    from ..cameras import orbit_cameras
    from ..data.samples import list_samples, load_sample

    s = int(model.config.input_size)
    if list_samples():
        sample = load_sample(gt=False)
        images, cams = model.prepare(sample.request_images, sample.request_cameras, sample.request_masks)
        idx = [i % len(images) for i in range(views)]
        return images[idx], cams[idx]
    g = torch.Generator().manual_seed(seed)
    cams = orbit_cameras(views, radius=1.0, fov_deg=20.0, width=s, height=s)
    images = torch.rand(views, 3, s, s, generator=g)  # [V, 3, S, S]
    return images, cams


def bench_avatar(model, views: int = 4, seed: int = 0):
    """A reconstructed avatar of ``model`` from ``views`` input views (see ``input_views``)."""
    images, cams = input_views(model, views, seed)
    with torch.inference_mode():
        return model.reconstruct(images, cams)
