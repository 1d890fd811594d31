"""Training-side robustness: tracking-shaped pose noise on the input cameras (data/augment.py).

The noise has the configured statistics, moves only the cameras given to the encoder, is off by
default (and in the presets), and is a pure function of (seed, sample index)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from fastgha_core.cameras import look_at_w2c
from fastgha_core.data.augment import InputCameraNoise, InputCameraNoiseDataset, perturb_w2c, rotation_vector, view_yaw_deg
from fastgha_core.data.sampling import SyntheticTrainingDataset, collate_samples
from fastgha_core.train.trainer import TRAIN_PRESETS, TrainConfig, load_train_config

from test_sampling import FakeSource


def _ring(yaw_deg: float, n: int, dist: float = 1.0) -> torch.Tensor:  # [n, 4, 4] cameras at one yaw, looking at the head centre
    a = math.radians(yaw_deg)
    w = look_at_w2c([dist * math.sin(a), 0.0, dist * math.cos(a)]).to(torch.float64)
    return w.expand(n, 4, 4).clone()


def _head_rotvec_deg(w0: torch.Tensor, w1: torch.Tensor) -> torch.Tensor:  # the head-frame rotation R0^T R1 as (pitch, yaw, roll) degrees
    return torch.rad2deg(rotation_vector(w0[:, :3, :3].transpose(-1, -2) @ w1[:, :3, :3]))


def test_view_yaw_and_rotation_vector_round_trip():
    assert view_yaw_deg(_ring(0, 1)).abs().item() < 1e-6
    assert view_yaw_deg(_ring(60, 1)).item() == pytest.approx(60.0, abs=1e-4)
    assert view_yaw_deg(_ring(-35, 1)).item() == pytest.approx(-35.0, abs=1e-4)
    from fastgha_core.data.augment import _so3_exp

    v = torch.tensor([[0.1, -0.2, 0.05], [0.0, 0.0, 0.0], [1.0, 0.5, -0.3]], dtype=torch.float64)
    R = _so3_exp(v)
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(3, 3, 3), atol=1e-12, rtol=0)
    torch.testing.assert_close(rotation_vector(R), v, atol=1e-9, rtol=0)


def test_noise_has_the_configured_statistics_at_a_frontal_view():
    noise = InputCameraNoise(enabled=True, yaw_std_deg=3.0, pitch_std_deg=2.0, roll_std_deg=1.0, yaw_gain=2.0, lateral_std_mm=4.0, depth_std=0.05)
    n = 20000
    w0 = _ring(0, n)
    w1 = perturb_w2c(w0, noise, torch.Generator().manual_seed(0))
    R1 = w1[:, :3, :3]
    torch.testing.assert_close(R1 @ R1.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(n, 3, 3), atol=1e-10, rtol=0)
    rv = _head_rotvec_deg(w0, w1)  # [n, 3] = head x (pitch), y (yaw), z (roll)
    np.testing.assert_allclose(rv.std(0).numpy(), [2.0, 3.0, 1.0], rtol=0.03)
    np.testing.assert_allclose(rv.mean(0).numpy(), [0, 0, 0], atol=0.05)
    t0, t1 = w0[:, :3, 3], w1[:, :3, 3]  # the frontal camera has t = (0, 0, 1): depth and lateral parts are separable
    eps = t1[:, 2] / t0[:, 2] - 1
    assert float(eps.std()) == pytest.approx(0.05, rel=0.03)
    lat_mm = (t1[:, :2] - t0[:, :2]) * 1e3
    np.testing.assert_allclose(lat_mm.std(0).numpy(), [4.0, 4.0], rtol=0.03)
    # the components are drawn independently
    c = np.corrcoef(torch.cat([rv, eps[:, None], lat_mm], 1).numpy().T)
    assert np.abs(c - np.eye(6)).max() < 0.05


def test_rotation_noise_grows_with_the_view_yaw_and_keeps_the_head_centre_in_place():
    noise = InputCameraNoise(enabled=True, yaw_std_deg=2.5, pitch_std_deg=2.0, roll_std_deg=1.0, yaw_gain=2.0, lateral_std_mm=0.0, depth_std=0.03)
    n = 20000
    for yaw, gain in ((30, 2.0), (-60, 3.0), (90, 4.0)):
        w0 = _ring(yaw, n)
        w1 = perturb_w2c(w0, noise, torch.Generator().manual_seed(1))
        np.testing.assert_allclose(_head_rotvec_deg(w0, w1).std(0).numpy(), [2.0 * gain, 2.5 * gain, 1.0 * gain], rtol=0.03)
        # without lateral noise the head centre (world origin) projects where it did: t' is parallel to t
        t0, t1 = w0[:, :3, 3], w1[:, :3, 3]
        torch.testing.assert_close(torch.linalg.cross(t0, t1).norm(dim=-1), torch.zeros(n, dtype=torch.float64), atol=1e-12, rtol=0)


def test_zero_magnitudes_are_the_identity_and_bad_values_are_refused():
    w0 = torch.cat([_ring(0, 2), _ring(45, 2)])
    w1 = perturb_w2c(w0.float(), InputCameraNoise(True, 0, 0, 0, 0, 0, 0), torch.Generator().manual_seed(0))
    torch.testing.assert_close(w1, w0.float(), atol=1e-6, rtol=0)
    assert w1.dtype == torch.float32
    with pytest.raises(ValueError, match="yaw_std_deg must be a finite number >= 0"):
        InputCameraNoise(yaw_std_deg=-1.0)
    with pytest.raises(ValueError, match="depth_std must be < 0.5"):
        InputCameraNoise(depth_std=0.7)
    with pytest.raises(ValueError, match=r"expects w2c of shape \[V, 4, 4\]"):
        perturb_w2c(torch.eye(4), InputCameraNoise(), torch.Generator())


def _fake_dataset(seed=4):
    def make(seed, timesteps, num_cameras, resolution, sequence):
        return FakeSource(T=timesteps, C=num_cameras, w=resolution, h=resolution, name=str(seed))

    return SyntheticTrainingDataset(range(100, 110), resolution=16, timesteps=5, num_cameras=10, make_sequence=make,
                                    length=32, samples_per_subject=8, cache_size=2, seed=seed)


def test_only_the_input_cameras_change():
    base = _fake_dataset()
    ds = InputCameraNoiseDataset(base, InputCameraNoise(enabled=True), seed=7)
    for i in (0, 5, 13):
        a, b = base[i], ds[i]
        assert not torch.allclose(a.input_w2c, b.input_w2c, atol=1e-5)
        # every supervision camera keeps its exact pose, including the targets that are the input cameras
        assert torch.equal(a.target_w2c, b.target_w2c)
        assert torch.equal(a.target_K, b.target_K) and torch.equal(a.input_K, b.input_K)
        for f in ("input_images", "target_images", "target_masks", "target_depths", "expression", "input_expressions", "is_input_camera"):
            assert torch.equal(getattr(a, f), getattr(b, f)), f


def test_noise_is_deterministic_per_seed_and_index_and_across_workers():
    noise = InputCameraNoise(enabled=True)
    ds = InputCameraNoiseDataset(_fake_dataset(), noise, seed=7)
    again = InputCameraNoiseDataset(_fake_dataset(), noise, seed=7)
    other = InputCameraNoiseDataset(_fake_dataset(), noise, seed=8)
    assert torch.equal(ds[3].input_w2c, again[3].input_w2c)
    assert not torch.allclose(ds[3].input_w2c, other[3].input_w2c)
    assert not torch.allclose(ds[3].input_w2c, ds[4].input_w2c)
    batch = next(iter(DataLoader(ds, batch_size=4, num_workers=2, collate_fn=collate_samples)))
    assert torch.equal(batch.input_w2c[3], ds[3].input_w2c)


def test_off_by_default_and_in_the_presets_on_from_a_config_file(tmp_path):
    from fastgha_core.config import get_preset
    from fastgha_core.train.builders import build_training_data

    assert TrainConfig().input_camera_noise.enabled is False
    assert all(not p.input_camera_noise.enabled for p in TRAIN_PRESETS.values())
    cfg = load_train_config("tiny")
    train, _, _ = build_training_data("synthetic", cfg, get_preset("tiny"))
    assert isinstance(train, SyntheticTrainingDataset)

    path = tmp_path / "robust.json"
    path.write_text(json.dumps({"preset": "tiny", "input_camera_noise": {"enabled": True, "yaw_std_deg": 4.0}}))
    cfg = load_train_config(str(path))
    assert cfg.input_camera_noise.enabled and cfg.input_camera_noise.yaw_std_deg == 4.0
    assert cfg.input_camera_noise.depth_std == InputCameraNoise().depth_std  # the other fields keep their defaults
    assert TrainConfig.from_dict(cfg.to_dict()).input_camera_noise == cfg.input_camera_noise  # round trip (train_config.json)
    train, val, _ = build_training_data("synthetic", cfg, get_preset("tiny"))
    assert isinstance(train, InputCameraNoiseDataset) and train.seed == cfg.seed
    assert isinstance(val, SyntheticTrainingDataset)  # validation keeps exact cameras
    path.write_text(json.dumps({"preset": "tiny", "input_camera_noise": {"yaw_deg": 4.0}}))
    with pytest.raises(ValueError, match=r"unknown input_camera_noise field\(s\) \['yaw_deg'\]"):
        load_train_config(str(path))


def test_cli_flag_turns_the_noise_on():
    import argparse

    from fastgha_core.commands import train as train_cmd

    p = argparse.ArgumentParser()
    train_cmd.add_arguments(p)
    assert p.parse_args(["--data", "synthetic", "--out", "x"]).input_camera_noise is False
    assert p.parse_args(["--data", "synthetic", "--out", "x", "--input-camera-noise"]).input_camera_noise is True


# ---------------------------------------------------------------------------- inputs matted by our matting
@pytest.fixture(scope="module")
def synthetic_pair():
    from fastgha_core.data.augment import InputMatting, InputMattingDataset
    from fastgha_core.data.synthetic import TRAIN_SEEDS

    base = SyntheticTrainingDataset(TRAIN_SEEDS, resolution=96, timesteps=6, num_cameras=8, num_targets=6, seed=3, length=4)
    cfg = InputMatting(enabled=True, method="mixture")  # no MediaPipe needed
    return base, InputMattingDataset(base, cfg, seed=3), cfg


def test_matting_changes_only_the_input_images_and_is_deterministic(synthetic_pair):
    base, ds, cfg = synthetic_pair
    a, b = base[0], ds[0]
    assert not torch.equal(a.input_images, b.input_images)
    for f in ("input_w2c", "input_K", "target_images", "target_masks", "target_depths", "target_w2c", "target_K", "expression"):
        assert torch.equal(getattr(a, f), getattr(b, f)), f
    assert b.input_images.shape == a.input_images.shape and b.input_images.dtype == a.input_images.dtype
    # the same index gives the same wall, shadow and head error; the inside of the head is the render's
    assert torch.equal(ds[0].input_images, b.input_images)
    assert float((a.input_images - b.input_images).abs().median()) < 0.01


def test_matte_of_a_fit_like_head_follows_the_true_alpha(synthetic_pair):
    from fastgha_core.data.augment import matte_input_view

    base, _, cfg = synthetic_pair
    src, plan = base.plan(1)
    for i, (t, c) in enumerate(zip(plan.input_timesteps, plan.input_cameras)):
        view = src.view(t, c)
        cam = src.cameras(t)[c : c + 1]
        img, matte = matte_input_view(src.synthetic_subject, src.expressions[t], view, cam.w2c[0], cam.K[0], cfg, np.random.default_rng(i))
        truth, ours = view.mask[0] > 0.5, matte[0] > 0.5
        iou = float((truth & ours).sum() / (truth | ours).sum())
        assert iou > 0.9, (i, iou)
        # outside our matte the image is the plain background, inside it the photo (no wall left where the truth is head)
        assert float((img - view.image).abs()[:, truth & ours].mean()) < 0.02


def test_matting_is_off_by_default_and_refuses_other_data(tmp_path):
    from fastgha_core.data.augment import InputMatting, InputMattingDataset
    from fastgha_core.train.builders import build_training_data

    assert TrainConfig().input_matting.enabled is False
    assert all(not p.input_matting.enabled for p in TRAIN_PRESETS.values())
    with pytest.raises(ValueError, match="needs the synthetic training data"):
        InputMattingDataset([1, 2, 3], InputMatting(enabled=True))
    cfg = load_train_config("tiny")
    cfg.input_matting = InputMatting(enabled=True)
    with pytest.raises(ValueError, match="input_matting needs --data synthetic"):
        build_training_data(str(tmp_path), cfg, None)
    with pytest.raises(ValueError, match="method must be"):
        InputMatting(method="magic")
    # both options compose: the matting inside, the camera noise on top (it sees the exact cameras it perturbs)
    from fastgha_core.config import get_preset

    cfg.input_camera_noise = InputCameraNoise(enabled=True)
    train, val, _ = build_training_data("synthetic", cfg, get_preset("tiny"))
    assert isinstance(train, InputCameraNoiseDataset) and isinstance(train.base, InputMattingDataset)
    assert isinstance(val, SyntheticTrainingDataset)
