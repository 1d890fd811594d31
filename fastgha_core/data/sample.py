"""In-memory data types shared by every data source (synthetic generator, our on-disk layout,
Ava-256, NeRSemble, VHAP readers) and consumed by the training sampler and the trainer."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from torch import Tensor

from ..cameras import Cameras

__all__ = ["View", "SequenceSource", "TrainingSample"]


@dataclass
class View:
    """One camera at one timestep."""

    image: Tensor  # [3, H, W] float32 in [0, 1], background already BACKGROUND_RGB
    mask: Tensor  # [1, H, W] float32 in [0, 1] (foreground alpha)
    depth: Tensor | None  # [1, H, W] float32 camera z in metres (0 where no surface), or None


class SequenceSource(Protocol):
    """One captured sequence of one subject: T timesteps seen by C fixed cameras.

    Every reader (synthetic, on-disk layout, Ava-256, NeRSemble, VHAP) returns objects with
    this interface; cameras are head-centric (head pose folded into the cameras) so that
    ``cameras(t)`` may change with t.
    """

    subject: str
    sequence: str
    expression_space: str  # "ict53" | "flame120" | "none" (no codes: readers without tracking)

    @property
    def num_timesteps(self) -> int: ...

    @property
    def num_cameras(self) -> int: ...

    def cameras(self, t: int) -> Cameras:  # batch [C]
        ...

    def expression(self, t: int) -> Tensor:  # [E]
        ...

    def view(self, t: int, c: int) -> View: ...


@dataclass
class TrainingSample:
    """One training example (paper appendix): 4 inputs at 4 timesteps, 8 supervision views at one
    timestep (the 4 input cameras + 4 novel ones). Shapes without a batch dim; batch them with
    ``sampling.collate_samples`` (a DataLoader ``collate_fn``), which adds a leading ``B``.
    """

    input_images: Tensor  # [V, 3, H, W]       V = 4 by default
    input_K: Tensor  # [V, 3, 3]
    input_w2c: Tensor  # [V, 4, 4]
    input_expressions: Tensor  # [V, E]   (not given to the model; for analysis)
    target_images: Tensor  # [S, 3, H, W]      S = 8 by default
    target_masks: Tensor  # [S, 1, H, W]
    target_depths: Tensor  # [S, 1, H, W] depth prior (0 = no value)
    target_K: Tensor  # [S, 3, 3]
    target_w2c: Tensor  # [S, 4, 4]
    expression: Tensor  # [E] expression code of the supervision timestep
    is_input_camera: Tensor  # [S] bool, True for the views whose camera is an input camera
    # [V, 1, H, W] true camera z (metres) of each *input* view at its own timestep, 0 = no value
    # (readers without depth); None when the source of the sample does not provide the field.
    # Supervises the input views' own depth maps (``LossConfig.w_input_depth``); never degraded.
    input_depths: Tensor | None = None

    def input_cameras(self) -> Cameras:
        return Cameras(self.input_K, self.input_w2c, self.input_images.shape[-1], self.input_images.shape[-2])

    def target_cameras(self) -> Cameras:
        return Cameras(self.target_K, self.target_w2c, self.target_images.shape[-1], self.target_images.shape[-2])
