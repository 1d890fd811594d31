"""Training sampler: paper-appendix sampling, shapes, determinism, DataLoader workers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from fastgha_core.cameras import Cameras
from fastgha_core.data.sample import TrainingSample, View
from fastgha_core.data.sampling import (
    DepthDegrade,
    SyntheticTrainingDataset,
    TrainingDataset,
    collate_samples,
)

E = 5


class FakeSource:
    """T timesteps x C cameras on a ring; pixel values encode (t, c); the head turns with t."""

    def __init__(self, T=6, C=12, w=20, h=16, space="flame120", name="s", depth_cams=(0, 1, 2, 3)):
        self.subject, self.sequence, self.expression_space = name, "seq", space
        self.T, self.C, self.w, self.h = T, C, w, h
        self.depth_cams = set(depth_cams)
        ang = torch.linspace(-math.pi / 2, math.pi / 2, C, dtype=torch.float64)
        eyes = torch.stack([torch.sin(ang), 0.3 * torch.cos(3 * ang), torch.cos(ang)], -1)  # [C, 3]
        self._base = Cameras.look_at(eyes.float(), fov_deg=30.0, width=w, height=h)

    @property
    def num_timesteps(self):
        return self.T

    @property
    def num_cameras(self):
        return self.C

    def cameras(self, t):
        # head yaw of 5 deg per timestep folded into w2c (head-centric cameras vary with t)
        a = math.radians(5 * t)
        H = torch.eye(4)
        H[:3, :3] = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        return Cameras(self._base.K, self._base.w2c @ H, self.w, self.h)

    def expression(self, t):
        return torch.arange(E, dtype=torch.float32) + 10 * t

    def view(self, t, c):
        img = torch.empty(3, self.h, self.w)
        img[0], img[1], img[2] = t / 10, c / 20, 0.5
        depth = torch.full((1, self.h, self.w), 1.0 + c / 100) if c in self.depth_cams else None
        return View(img, torch.ones(1, self.h, self.w), depth)


def _decode(img: torch.Tensor) -> tuple[int, int]:  # [3, H, W] -> (t, c)
    return round(float(img[0, 0, 0]) * 10), round(float(img[1, 0, 0]) * 20)


def test_sample_shapes_and_paper_structure():
    src = FakeSource()
    ds = TrainingDataset([src], num_inputs=4, num_targets=8, seed=1, length=20)
    assert len(ds) == 20
    for i in range(6):
        s, plan = ds[i], ds.plan(i)
        assert isinstance(s, TrainingSample)
        assert s.input_images.shape == (4, 3, 16, 20) and s.input_K.shape == (4, 3, 3) and s.input_w2c.shape == (4, 4, 4)
        assert s.input_expressions.shape == (4, E) and s.expression.shape == (E,)
        assert s.target_images.shape == (8, 3, 16, 20) and s.target_masks.shape == (8, 1, 16, 20)
        assert s.target_depths.shape == (8, 1, 16, 20) and s.target_K.shape == (8, 3, 3) and s.target_w2c.shape == (8, 4, 4)
        assert s.is_input_camera.dtype == torch.bool and s.is_input_camera.tolist() == [True] * 4 + [False] * 4
        # 8 distinct cameras; the novel ones are not among the inputs
        assert len(set(plan.target_cameras)) == 8
        assert not set(plan.novel_cameras) & set(plan.input_cameras)
        # supervision: all 8 images at one timestep, cameras in plan order
        assert [_decode(x) for x in s.target_images] == [(plan.timestep, c) for c in plan.target_cameras]
        # inputs: the input cameras at 4 distinct timesteps (T = 6 >= 4)
        assert [_decode(x) for x in s.input_images] == list(zip(plan.input_timesteps, plan.input_cameras))
        assert len(set(plan.input_timesteps)) == 4
        # expression of the supervision timestep, and of each input timestep
        torch.testing.assert_close(s.expression, src.expression(plan.timestep))
        torch.testing.assert_close(s.input_expressions, torch.stack([src.expression(t) for t in plan.input_timesteps]))
        # head-centric cameras of the right timestep
        torch.testing.assert_close(s.target_w2c, src.cameras(plan.timestep).w2c[list(plan.target_cameras)])
        torch.testing.assert_close(s.input_w2c[1], src.cameras(plan.input_timesteps[1]).w2c[plan.input_cameras[1]])
        # depth priors where the source has them, zeros elsewhere
        for k, c in enumerate(plan.target_cameras):
            expect = 1.0 + c / 100 if c in src.depth_cams else 0.0
            assert float(s.target_depths[k].min()) == pytest.approx(expect) == pytest.approx(float(s.target_depths[k].max()))


def test_cameras_are_farthest_viewpoint_spread():
    """The 8 chosen viewpoints are better spread than random subsets of 8 (greedy FPS on a ring)."""
    src = FakeSource(C=16)
    ds = TrainingDataset([src], seed=0, length=8)
    dirs = src.cameras(0).centers / src.cameras(0).centers.norm(dim=-1, keepdim=True)

    def min_gap(idx):
        d = torch.cdist(dirs[list(idx)], dirs[list(idx)]) + 10 * torch.eye(len(idx))
        return float(d.min())

    rng = np.random.default_rng(0)
    random_gaps = [min_gap(rng.choice(16, 8, replace=False)) for _ in range(200)]
    for i in range(4):
        assert min_gap(ds.plan(i).target_cameras) >= np.median(random_gaps)
    starts = {ds.plan(i).target_cameras[0] for i in range(8)}
    assert len(starts) > 1  # random start camera


def test_determinism_and_seed():
    src = FakeSource()
    a = TrainingDataset([src], seed=5, length=10)
    b = TrainingDataset([FakeSource()], seed=5, length=10)
    c = TrainingDataset([src], seed=6, length=10)
    for i in range(4):
        torch.testing.assert_close(a[i].target_images, b[i].target_images)
        torch.testing.assert_close(a[i].input_images, b[i].input_images)
    assert any(a.plan(i) != c.plan(i) for i in range(4))
    assert len({a.plan(i) for i in range(10)}) > 5


def test_short_sequences_repeat_timesteps_and_multiple_sources():
    short = FakeSource(T=2, name="short")
    long = FakeSource(T=40, name="long")
    ds = TrainingDataset([short, long], seed=0, length=60)
    picks = [ds.plan(i).source for i in range(60)]
    assert picks.count(1) > picks.count(0)  # drawn by number of timesteps
    i = picks.index(0)
    assert set(ds.plan(i).input_timesteps) <= {0, 1}
    assert ds[i].input_images.shape[0] == 4


def test_dataloader_with_two_workers_matches_direct_access():
    ds = TrainingDataset([FakeSource()], seed=2, length=6)
    dl = DataLoader(ds, batch_size=3, num_workers=2, collate_fn=collate_samples)
    batches = list(dl)
    assert len(batches) == 2
    b = batches[1]
    assert b.target_images.shape == (3, 8, 3, 16, 20) and b.expression.shape == (3, E) and b.is_input_camera.shape == (3, 8)
    direct = collate_samples([ds[3], ds[4], ds[5]])
    torch.testing.assert_close(b.target_images, direct.target_images)
    torch.testing.assert_close(b.input_w2c, direct.input_w2c)


def test_refusals_and_errors():
    with pytest.raises(ValueError, match="no expression codes"):
        TrainingDataset([FakeSource(space="none")])
    with pytest.raises(ValueError, match="one expression space"):
        TrainingDataset([FakeSource(), FakeSource(space="ict53")])
    with pytest.raises(ValueError, match="cameras"):
        TrainingDataset([FakeSource(C=6)], num_targets=8)
    with pytest.raises(ValueError, match="num_inputs"):
        TrainingDataset([FakeSource()], num_inputs=5, num_targets=4)
    with pytest.raises(IndexError):
        TrainingDataset([FakeSource()], length=3)[3]
    a, b = TrainingDataset([FakeSource(w=20)])[0], TrainingDataset([FakeSource(w=24)])[0]
    with pytest.raises(ValueError, match="resolution"):
        collate_samples([a, b])


def test_resolution_crops_square_and_keeps_projection():
    src = FakeSource(w=40, h=30)
    ds = TrainingDataset([src], seed=0, length=2, resolution=12)
    s, plan = ds[0], ds.plan(0)
    assert s.target_images.shape == (8, 3, 12, 12)
    # a world point projects to the same place relative to the crop: crop 30x30 at left = 5, scale 12/30
    cam_full = src.cameras(plan.timestep)[plan.target_cameras[0] : plan.target_cameras[0] + 1]
    p = torch.tensor([[0.02, -0.03, 0.05]])
    uv_full, _ = cam_full.project(p)
    uv_small, _ = Cameras(s.target_K[:1], s.target_w2c[:1], 12, 12).project(p)
    torch.testing.assert_close(uv_small[0, 0], (uv_full[0, 0] - torch.tensor([5.0, 0.0])) * 12 / 30)


def test_depth_degrade():
    gen = torch.Generator().manual_seed(0)
    d = torch.zeros(1, 64, 64)
    d[:, 16:48, 16:48] = 1.0
    assert torch.equal(DepthDegrade(0, 0, 0, 0)(d, gen), d)
    out = DepthDegrade()(d, torch.Generator().manual_seed(0))
    assert torch.equal(out[d == 0], torch.zeros_like(out[d == 0]))  # no depth invented off the surface
    inside = out[d > 0]
    holes = float((inside == 0).float().mean())
    assert 0.0 <= holes < 0.3
    assert float((inside[inside > 0] - 1).abs().mean()) < 0.05
    torch.testing.assert_close(DepthDegrade()(d, torch.Generator().manual_seed(0)), out)


def test_synthetic_dataset_with_injected_generator_reuses_subjects():
    built = []

    def make(seed, timesteps, num_cameras, resolution, sequence):
        built.append((seed, sequence))
        return FakeSource(T=timesteps, C=num_cameras, w=resolution, h=resolution, name=str(seed))

    ds = SyntheticTrainingDataset(range(100, 110), resolution=16, timesteps=5, num_cameras=10, make_sequence=make,
                                  length=32, samples_per_subject=8, cache_size=2, seed=4)
    samples = [ds[i] for i in range(16)]
    assert len(built) == 2  # two blocks of 8 samples, one subject build each
    assert samples[0].target_images.shape == (8, 3, 16, 16)
    assert ds.subject_of(0) == ds.subject_of(7)
    # depth priors are degraded (holes/noise) but deterministic per index
    ds2 = SyntheticTrainingDataset(range(100, 110), resolution=16, timesteps=5, num_cameras=10, make_sequence=make,
                                   length=32, samples_per_subject=8, cache_size=2, seed=4)
    torch.testing.assert_close(ds2[3].target_depths, samples[3].target_depths)
    torch.testing.assert_close(ds2[3].target_images, samples[3].target_images)
    dl = DataLoader(ds, batch_size=4, num_workers=2, collate_fn=collate_samples)
    b = next(iter(dl))
    torch.testing.assert_close(b.target_images[3], samples[3].target_images)


def test_synthetic_dataset_with_the_real_generator():
    synthetic = pytest.importorskip("fastgha_core.data.synthetic", reason="synthetic generator not in this tree yet")
    ds = SyntheticTrainingDataset(list(synthetic.TRAIN_SEEDS)[:2], resolution=32, timesteps=4, num_cameras=8, length=2)
    s = ds[0]
    src, plan = ds.plan(0)
    assert s.target_images.shape == (8, 3, 32, 32) and s.input_images.shape == (4, 3, 32, 32)
    assert src.expression_space == "ict53" and s.expression.shape == (53,)
    torch.testing.assert_close(s.expression, src.expression(plan.timestep))
    assert not set(plan.novel_cameras) & set(plan.input_cameras)
