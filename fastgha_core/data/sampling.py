"""Training samples (paper, appendix "Input settings").

One sample, drawn from one sequence:

1. a random supervision timestep ``t`` and a random start camera; farthest-viewpoint sampling on
   the camera centres at ``t`` collects ``S = num_targets`` (8) cameras;
2. the first ``V = num_inputs`` (4) of them — the best spread — are the input cameras; each
   input image comes from its own random timestep (distinct when the sequence is long enough);
3. supervision = the ``S`` images at timestep ``t``: the ``V`` input cameras plus ``S - V``
   novel ones, with masks, depth priors (zeros where none) and the expression code of ``t``.

Shapes of a :class:`~fastgha_core.data.sample.TrainingSample` (no batch dim; ``collate_samples``
adds a leading ``B``)::

    input_images      [V, 3, H, W]   float32 in [0, 1] over BACKGROUND_RGB
    input_K           [V, 3, 3]      input_w2c [V, 4, 4]   (head-centric, per input timestep)
    input_expressions [V, E]
    target_images     [S, 3, H, W]   target_masks [S, 1, H, W]   target_depths [S, 1, H, W] (0 = none)
    target_K          [S, 3, 3]      target_w2c [S, 4, 4]
    expression        [E]            code of the supervision timestep
    is_input_camera   [S] bool       True for the first V targets (same cameras as the inputs)
    input_depths      [V, 1, H, W]   true camera z of each input view at its own timestep (0 = none)

Both datasets are map-style and deterministic per ``(seed, index)``, whatever the number of
DataLoader workers; use ``collate_fn=collate_samples``.
"""

from __future__ import annotations

import logging
import math
from collections import OrderedDict
from dataclasses import dataclass, fields
from typing import Any, Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.data import Dataset

from ..cameras import Cameras, farthest_viewpoint_sampling
from .sample import SequenceSource, TrainingSample, View

__all__ = [
    "SamplePlan",
    "DepthDegrade",
    "TrainingDataset",
    "SyntheticTrainingDataset",
    "collate_samples",
    "plan_sample",
    "build_sample",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SamplePlan:
    """Which images make up one sample."""

    source: int  # index into the dataset's sources
    timestep: int  # supervision timestep
    target_cameras: tuple[int, ...]  # [S] farthest-viewpoint order; the first V are the inputs
    input_timesteps: tuple[int, ...]  # [V]
    num_inputs: int

    @property
    def input_cameras(self) -> tuple[int, ...]:
        return self.target_cameras[: self.num_inputs]

    @property
    def novel_cameras(self) -> tuple[int, ...]:
        return self.target_cameras[self.num_inputs :]


def plan_sample(source: SequenceSource, source_index: int, rng: np.random.Generator, num_inputs: int, num_targets: int) -> SamplePlan:
    """Draw one :class:`SamplePlan` from ``source`` with ``rng`` (paper appendix)."""
    T, C = source.num_timesteps, source.num_cameras
    if C < num_targets:
        raise ValueError(
            f"{source.subject}/{source.sequence} has {C} cameras, fewer than num_targets={num_targets}"
        )
    t = int(rng.integers(T))
    start = int(rng.integers(C))
    centers = source.cameras(t).centers.double()  # [C, 3]
    order = farthest_viewpoint_sampling(centers, num_targets, start=start)
    input_ts = rng.choice(T, size=num_inputs, replace=T < num_inputs)
    return SamplePlan(source_index, t, tuple(int(c) for c in order), tuple(int(x) for x in input_ts), num_inputs)


# ---------------------------------------------------------------- resizing
def _fit_square(view: View, cam: Cameras, size: int) -> tuple[View, Cameras]:
    """Centre-crop ``view`` to a square and resize it to ``size`` (K follows)."""
    h, w = view.image.shape[-2:]
    side = min(h, w)
    left, top = (w - side) // 2, (h - side) // 2

    def crop(x: Tensor) -> Tensor:
        return x[..., top : top + side, left : left + side]

    img, mask = crop(view.image), crop(view.mask)
    if side != size:
        img = F.interpolate(img[None], size=(size, size), mode="bilinear", align_corners=False, antialias=side > size)[0]
        mask = F.interpolate(mask[None], size=(size, size), mode="bilinear", align_corners=False, antialias=side > size)[0]
    depth = view.depth
    if depth is not None:
        depth = crop(depth)
        if side != size:
            depth = F.interpolate(depth[None], size=(size, size), mode="nearest")[0]
    cam = cam.crop(left, top, side, side).resize(size, size)
    return View(img.clamp(0, 1), mask.clamp(0, 1), depth), cam


def build_sample(
    source: SequenceSource,
    plan: SamplePlan,
    resolution: int | None = None,
    depth_fn: Callable[[Tensor, int], Tensor] | None = None,
) -> TrainingSample:
    """Read the images of ``plan`` from ``source`` into a :class:`TrainingSample`.

    ``resolution``: centre-crop to a square and resize to ``resolution``² (None keeps the source's
    size). ``depth_fn(depth [1,H,W], k) -> depth`` post-processes the k-th target depth prior.
    """

    def get(t: int, c: int) -> tuple[View, Cameras]:
        view, cam = source.view(t, c), source.cameras(t)[c : c + 1]
        if resolution is not None:
            view, cam = _fit_square(view, cam, resolution)
        return view, cam

    in_views, in_cams, in_expr, in_depth = [], [], [], []
    for t, c in zip(plan.input_timesteps, plan.input_cameras):
        v, cam = get(t, c)
        in_views.append(v.image)
        in_depth.append(v.depth if v.depth is not None else torch.zeros_like(v.mask))
        in_cams.append(cam)
        in_expr.append(source.expression(t))
    tg_img, tg_mask, tg_depth, tg_cams = [], [], [], []
    for k, c in enumerate(plan.target_cameras):
        v, cam = get(plan.timestep, c)
        tg_img.append(v.image)
        tg_mask.append(v.mask)
        d = v.depth if v.depth is not None else torch.zeros_like(v.mask)
        if depth_fn is not None and v.depth is not None:
            d = depth_fn(d, k)
        tg_depth.append(d)
        tg_cams.append(cam)
    S = len(plan.target_cameras)
    return TrainingSample(
        input_images=torch.stack(in_views),  # [V, 3, H, W]
        input_K=torch.cat([c.K for c in in_cams]).float(),  # [V, 3, 3]
        input_w2c=torch.cat([c.w2c for c in in_cams]).float(),  # [V, 4, 4]
        input_expressions=torch.stack(in_expr).float(),  # [V, E]
        target_images=torch.stack(tg_img),  # [S, 3, H, W]
        target_masks=torch.stack(tg_mask),  # [S, 1, H, W]
        target_depths=torch.stack(tg_depth),  # [S, 1, H, W]
        target_K=torch.cat([c.K for c in tg_cams]).float(),  # [S, 3, 3]
        target_w2c=torch.cat([c.w2c for c in tg_cams]).float(),  # [S, 4, 4]
        expression=source.expression(plan.timestep).float(),  # [E]
        is_input_camera=torch.arange(S) < plan.num_inputs,  # [S]
        input_depths=torch.stack(in_depth).float(),  # [V, 1, H, W] true camera z, never degraded
    )


def collate_samples(samples: Sequence[TrainingSample]) -> TrainingSample:
    """Stack samples into one :class:`TrainingSample` with a leading batch dim ``B``."""
    if not samples:
        raise ValueError("collate_samples needs at least one sample, got none")
    out = {}
    for f in fields(TrainingSample):
        vals = [getattr(s, f.name) for s in samples]
        if any(v is None for v in vals):  # optional fields (input_depths): batched only when every sample has them
            out[f.name] = None
            continue
        shapes = {tuple(v.shape) for v in vals}
        if len(shapes) > 1:
            raise ValueError(
                f"cannot batch samples: field {f.name} has shapes {sorted(shapes)}; "
                "give the dataset a common `resolution` (and one expression space)"
            )
        out[f.name] = torch.stack(vals)
    return TrainingSample(**out)


def _check_common(sources: Sequence[SequenceSource], num_inputs: int, num_targets: int) -> None:
    if not 1 <= num_inputs <= num_targets:
        raise ValueError(f"need 1 <= num_inputs <= num_targets, got num_inputs={num_inputs}, num_targets={num_targets}")
    if not sources:
        raise ValueError("TrainingDataset needs at least one sequence source, got none")
    spaces = set()
    for s in sources:
        if s.expression_space == "none":
            raise ValueError(
                f"{s.subject}/{s.sequence} has no expression codes (expression_space 'none'; e.g. Ava-256 "
                "without a FLAME fit). Give the reader expression codes (open_ava256(..., flame_fit=...)) "
                "or leave the sequence out of training"
            )
        if s.num_cameras < num_targets:
            raise ValueError(f"{s.subject}/{s.sequence} has {s.num_cameras} cameras; num_targets={num_targets} needs as many")
        if s.num_timesteps < 1:
            raise ValueError(f"{s.subject}/{s.sequence} has no timesteps")
        spaces.add(s.expression_space)
    if len(spaces) > 1:
        raise ValueError(f"all sources must share one expression space, got {sorted(spaces)}")


# ---------------------------------------------------------------- datasets
class TrainingDataset(Dataset):
    """Map-style training samples over a list of :class:`SequenceSource`.

    Args:
        sources: sequences (any reader); all must share one expression space.
        num_inputs: V, input views per sample.
        num_targets: S, supervision views (the V input cameras + S - V novel ones).
        seed: sample ``i`` depends only on ``(seed, i)``.
        length: number of samples (default: total timesteps of all sources). A sequence is
            drawn with probability proportional to its number of timesteps.
        resolution: centre-crop and resize every view to this square size (None: keep; then
            all sources must have one image size to be batched).
        max_retries: missing images (dropped frames) make the sample redraw up to this often.
    """

    def __init__(
        self,
        sources: Sequence[SequenceSource],
        num_inputs: int = 4,
        num_targets: int = 8,
        seed: int = 0,
        length: int | None = None,
        resolution: int | None = None,
        max_retries: int = 8,
    ):
        sources = list(sources)
        _check_common(sources, num_inputs, num_targets)
        self.sources = sources
        self.num_inputs, self.num_targets = int(num_inputs), int(num_targets)
        self.seed = int(seed)
        weights = np.array([s.num_timesteps for s in sources], dtype=np.float64)
        self._p = weights / weights.sum()
        self.length = int(weights.sum()) if length is None else int(length)
        self.resolution = resolution
        self.max_retries = int(max_retries)

    def __len__(self) -> int:
        return self.length

    def plan(self, index: int, attempt: int = 0) -> SamplePlan:
        rng = np.random.default_rng([self.seed, int(index), int(attempt)])
        k = int(rng.choice(len(self.sources), p=self._p))
        return plan_sample(self.sources[k], k, rng, self.num_inputs, self.num_targets)

    def __getitem__(self, index: int) -> TrainingSample:
        if not 0 <= index < self.length:
            raise IndexError(f"sample index {index} out of range [0, {self.length})")
        for attempt in range(self.max_retries + 1):
            plan = self.plan(index, attempt)
            try:
                return build_sample(self.sources[plan.source], plan, self.resolution)
            except FileNotFoundError as e:  # MissingViewError: a dropped frame
                logger.debug("sample %d attempt %d: %s", index, attempt, e)
                last = e
        raise FileNotFoundError(f"sample {index}: images missing in {self.max_retries + 1} draws; last: {last}")


@dataclass(frozen=True)
class DepthDegrade:
    """Turns true depth into a VGGT-like prior: low-pass, relative noise, holes, scale error.

    All values are per sample and deterministic given the generator; ``DepthDegrade(0, 0, 0, 0)``
    is the identity.
    """

    blur_sigma_px: float = 1.5  # Gaussian low-pass in pixels (masked, so silhouettes stay put)
    noise_rel: float = 0.003  # per-pixel noise, fraction of depth
    hole_fraction: float = 0.03  # fraction of the surface dropped in blobs
    scale_error: float = 0.01  # std of one global multiplicative error per view

    def __call__(self, depth: Tensor, gen: torch.Generator) -> Tensor:  # [1, H, W] -> [1, H, W]
        valid = (depth > 0).float()
        d = depth
        if self.blur_sigma_px > 0:
            r = max(1, int(math.ceil(3 * self.blur_sigma_px)))
            x = torch.arange(-r, r + 1, dtype=torch.float32)
            k = torch.exp(-0.5 * (x / self.blur_sigma_px) ** 2)
            k = k / k.sum()

            def blur(t: Tensor) -> Tensor:
                t = F.conv2d(t[None], k.view(1, 1, 1, -1), padding=(0, r))
                return F.conv2d(t, k.view(1, 1, -1, 1), padding=(r, 0))[0]

            num, den = blur(d * valid), blur(valid)
            d = torch.where(valid > 0, num / den.clamp_min(1e-6), torch.zeros_like(d))
        if self.noise_rel > 0:
            d = d * (1 + self.noise_rel * torch.randn(d.shape, generator=gen))
        if self.scale_error > 0:
            d = d * (1 + self.scale_error * float(torch.randn((), generator=gen)))
        if self.hole_fraction > 0:
            h, w = d.shape[-2:]
            low = torch.rand((1, 1, max(2, h // 16), max(2, w // 16)), generator=gen)
            field = F.interpolate(low, size=(h, w), mode="bilinear", align_corners=False)[0]
            d = torch.where(field < self.hole_fraction, torch.zeros_like(d), d)
        return d * valid


class SyntheticTrainingDataset(Dataset):
    """Samples drawn on the fly from the synthetic generator, with no disk involved.

    Index ``i`` belongs to block ``i // samples_per_subject``; each block picks one subject seed
    from ``seeds`` and one of its ``sequences_per_subject`` sequences, so consecutive indices
    reuse one built subject (kept in a per-worker LRU of ``cache_size`` sequences). Iterate in
    order (``shuffle=False``; blocks are already in random subject order). Sample ``i`` depends
    only on ``(seed, i)``, so each DataLoader worker gets its own indices and streams are distinct
    and deterministic.

    Args:
        seeds: subject seeds (e.g. ``synthetic.TRAIN_SEEDS``).
        resolution, timesteps, num_cameras: passed to ``synthetic.make_sequence``.
        depth_degrade: applied to the true depth of every target (None: true depth).
        length: number of samples in one epoch.
    """

    def __init__(
        self,
        seeds: Sequence[int],
        resolution: int = 128,
        timesteps: int = 32,
        num_cameras: int = 16,
        depth_degrade: DepthDegrade | None = DepthDegrade(),
        num_inputs: int = 4,
        num_targets: int = 8,
        seed: int = 0,
        length: int = 100_000,
        samples_per_subject: int = 16,
        sequences_per_subject: int = 4,
        cache_size: int = 8,
        make_sequence: Callable[..., SequenceSource] | None = None,
    ):
        self.seeds = [int(s) for s in seeds]
        if not self.seeds:
            raise ValueError("SyntheticTrainingDataset needs at least one subject seed, got none")
        if not 1 <= num_inputs <= num_targets <= num_cameras:
            raise ValueError(
                f"need 1 <= num_inputs <= num_targets <= num_cameras, got {num_inputs}, {num_targets}, {num_cameras}"
            )
        for name, v in (("samples_per_subject", samples_per_subject), ("sequences_per_subject", sequences_per_subject), ("cache_size", cache_size), ("length", length)):
            if int(v) < 1:
                raise ValueError(f"{name} must be >= 1, got {v}")
        self.resolution, self.timesteps, self.num_cameras = int(resolution), int(timesteps), int(num_cameras)
        self.depth_degrade = depth_degrade
        self.num_inputs, self.num_targets = int(num_inputs), int(num_targets)
        self.seed, self.length = int(seed), int(length)
        self.samples_per_subject = int(samples_per_subject)
        self.sequences_per_subject = int(sequences_per_subject)
        self.cache_size = int(cache_size)
        self._make = make_sequence
        self._cache: OrderedDict[tuple[int, int], SequenceSource] = OrderedDict()

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_cache"] = OrderedDict()  # each worker builds its own subjects
        return state

    def __len__(self) -> int:
        return self.length

    def subject_of(self, index: int) -> tuple[int, int]:
        """(subject seed, sequence) that sample ``index`` is drawn from."""
        rng = np.random.default_rng([self.seed, 1, int(index) // self.samples_per_subject])
        return self.seeds[int(rng.integers(len(self.seeds)))], int(rng.integers(self.sequences_per_subject))

    def source(self, subject_seed: int, sequence: int) -> SequenceSource:
        key = (int(subject_seed), int(sequence))
        src = self._cache.get(key)
        if src is not None:
            self._cache.move_to_end(key)
            return src
        make = self._make
        if make is None:
            from .synthetic import make_sequence as make
        src = make(key[0], timesteps=self.timesteps, num_cameras=self.num_cameras, resolution=self.resolution, sequence=key[1])
        self._cache[key] = src
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        return src

    def plan(self, index: int) -> tuple[SequenceSource, SamplePlan]:
        src = self.source(*self.subject_of(index))
        rng = np.random.default_rng([self.seed, 2, int(index)])
        return src, plan_sample(src, 0, rng, self.num_inputs, self.num_targets)

    def __getitem__(self, index: int) -> TrainingSample:
        if not 0 <= index < self.length:
            raise IndexError(f"sample index {index} out of range [0, {self.length})")
        src, plan = self.plan(index)
        depth_fn = None
        if self.depth_degrade is not None:
            gen = torch.Generator().manual_seed(int(np.random.default_rng([self.seed, 3, int(index)]).integers(2**62)))
            depth_fn = lambda d, k: self.depth_degrade(d, gen)  # noqa: E731  one stream per sample
        return build_sample(src, plan, None, depth_fn)
