"""A toy-sized model config and a toy multi-view, multi-expression dataset, for tests and smoke runs
of the trainer (seconds on CPU, no assets needed).

The toy scene is a cluster of Gaussians whose upper half moves up with expression channel 0; it is
rendered by the project's rasterizer into ``num_cameras`` orbit cameras at ``num_timesteps``
expressions. Each sample follows the paper's recipe: ``num_inputs`` input views at different
timesteps, ``num_targets`` supervision views at one timestep (the input cameras + novel ones).
"""

from __future__ import annotations

import torch
from ..cameras import Cameras, farthest_viewpoint_sampling, orbit_cameras
from ..constants import BACKGROUND_RGB
from ..data.sample import TrainingSample
from ..gaussians import Gaussians

__all__ = ["toy_model_config", "ToyDataset", "ToySequence", "collate_toy"]


def toy_model_config(size: int = 32):
    """The ``tiny`` preset shrunk to ~90k parameters at ``size``² (``size`` divisible by 16)."""
    from ..config import DecoderConfig, DeformConfig, DinoConfig, GaussianHeadConfig, TransformerConfig, VAEConfig, get_preset

    return get_preset("tiny").copy(
        name="toy",
        input_size=size,
        render_size=size,
        dino=DinoConfig(hidden_size=32, num_layers=2, num_heads=2, intermediate_size=64, patch_size=16, num_register_tokens=0, feature_layers=(1, 2), out_channels=16, frozen=False),
        vae=VAEConfig(block_out_channels=(8, 8, 8, 8), layers_per_block=1, norm_num_groups=4, frozen=False),
        transformer=TransformerConfig(hidden_size=32, num_layers=1, num_heads=2),
        decoder=DecoderConfig(block_out_channels=(8, 8, 8, 8), layers_per_block=1, norm_num_groups=4, init_from_vae=False),
        gaussians=GaussianHeadConfig(feature_dim=8, prune_opacity=0.0),
        deform=DeformConfig(hidden_size=16, num_layers=2, pe_freqs=2),
    )


def _scene(n: int, gen: torch.Generator) -> Gaussians:
    d = torch.randn(n, 3, generator=gen)
    means = d / d.norm(dim=-1, keepdim=True) * 0.1 * torch.rand(n, 1, generator=gen) ** (1 / 3)
    q = torch.randn(n, 4, generator=gen)
    return Gaussians(
        means=means,
        quats=q / q.norm(dim=-1, keepdim=True),
        scales=torch.full((n, 3), 0.012) * (0.5 + torch.rand(n, 3, generator=gen)),
        opacities=0.6 + 0.35 * torch.rand(n, generator=gen),
        colors=0.15 + 0.7 * torch.rand(n, 3, generator=gen),
    )


class ToyDataset(torch.utils.data.Dataset):
    """Map-style dataset of ``TrainingSample``; item ``i`` is a pure function of ``(seed, i)``."""

    def __init__(self, length: int = 64, size: int = 32, num_inputs: int = 4, num_targets: int = 8, num_cameras: int = 8, num_timesteps: int = 4, expression_dim: int = 53, seed: int = 0):
        from ..render import render

        if num_targets > num_cameras or num_inputs > num_targets:
            raise ValueError(f"need num_inputs <= num_targets <= num_cameras, got {num_inputs}, {num_targets}, {num_cameras}")
        self.length, self.num_inputs, self.num_targets, self.seed = length, num_inputs, num_targets, seed
        gen = torch.Generator().manual_seed(seed)
        scene = _scene(300, gen)
        self.cams = orbit_cameras(num_cameras, radius=0.6, yaw_deg=50, pitch_deg=20, fov_deg=30, width=size, height=size)
        self.expressions = torch.zeros(num_timesteps, expression_dim)
        self.expressions[:, 0] = torch.linspace(0, 1, num_timesteps)
        imgs, masks, depths = [], [], []
        with torch.no_grad():
            for t in range(num_timesteps):
                up = (scene.means[:, 1:2] > 0).float()
                g = scene.replace(means=scene.means + up * torch.tensor([0.0, 0.03, 0.0]) * self.expressions[t, 0])
                out = render(g, self.cams, background=BACKGROUND_RGB, backend="cpu")
                imgs.append(out.rgb)
                masks.append(out.alpha)
                depths.append(out.depth)
        self.images = torch.stack(imgs)  # [T, C, 3, H, W]
        self.masks = torch.stack(masks)  # [T, C, 1, H, W]
        self.depths = torch.stack(depths)  # [T, C, 1, H, W]

    def __len__(self) -> int:
        return self.length

    def sequence(self) -> "ToySequence":
        """The rendered toy scene as a ``SequenceSource`` (for evaluation tests)."""
        return ToySequence(self)

    def __getitem__(self, i: int) -> TrainingSample:
        if not 0 <= i < self.length:
            raise IndexError(i)
        gen = torch.Generator().manual_seed(self.seed * 100_003 + i)
        T, C = self.images.shape[:2]
        cams = farthest_viewpoint_sampling(self.cams.centers, self.num_targets, generator=gen)
        in_cams = cams[: self.num_inputs]
        in_ts = torch.randint(T, (self.num_inputs,), generator=gen).tolist()
        t = int(torch.randint(T, (1,), generator=gen))
        return TrainingSample(
            input_images=torch.stack([self.images[s, c] for s, c in zip(in_ts, in_cams)]),
            input_K=self.cams.K[in_cams],
            input_w2c=self.cams.w2c[in_cams],
            input_expressions=self.expressions[in_ts],
            target_images=self.images[t, cams],
            target_masks=self.masks[t, cams],
            target_depths=self.depths[t, cams],
            target_K=self.cams.K[cams],
            target_w2c=self.cams.w2c[cams],
            expression=self.expressions[t],
            is_input_camera=torch.tensor([c in in_cams for c in cams]),
            input_depths=torch.stack([self.depths[s, c] for s, c in zip(in_ts, in_cams)]),
        )


def collate_toy(samples: list[TrainingSample]) -> TrainingSample:
    """Stack every field (adds the leading batch dim)."""
    from dataclasses import fields

    def stack(name: str):
        vals = [getattr(s, name) for s in samples]
        return None if any(v is None for v in vals) else torch.stack(vals)

    return TrainingSample(**{f.name: stack(f.name) for f in fields(TrainingSample)})


class ToySequence:
    """``SequenceSource`` view of a :class:`ToyDataset`'s renders."""

    def __init__(self, data: ToyDataset, subject: str = "toy") -> None:
        self.data, self.subject, self.sequence, self.expression_space = data, subject, "seq0", "ict53"

    @property
    def num_timesteps(self) -> int:
        return int(self.data.images.shape[0])

    @property
    def num_cameras(self) -> int:
        return int(self.data.images.shape[1])

    def cameras(self, t: int) -> Cameras:
        return self.data.cams

    def expression(self, t: int):
        return self.data.expressions[t]

    def view(self, t: int, c: int):
        from ..data.sample import View

        d = self.data
        return View(image=d.images[t, c], mask=d.masks[t, c], depth=d.depths[t, c])
