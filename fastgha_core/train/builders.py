"""Build the pieces of a training or evaluation run from command-line style specs:
the model (preset, config file or pretrained folder, with optional pretrained encoders) and the
datasets (``synthetic`` / ``synthetic-heldout`` or an on-disk layout folder)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import torch

from .trainer import TrainConfig

__all__ = ["build_model", "build_training_data", "build_eval_sources", "check_expression_space", "model_config_from_spec"]

log = logging.getLogger(__name__)


def model_config_from_spec(spec: str):
    """A ``FastGHAConfig`` from a preset name or a JSON file (a config.json of a model folder works)."""
    from ..config import PRESETS, FastGHAConfig, get_preset

    if spec in PRESETS:
        return get_preset(spec)
    path = Path(spec)
    if path.is_dir():
        path = path / "config.json"
    if not path.is_file():
        raise ValueError(f"model must be one of {sorted(PRESETS)} or a FastGHAConfig JSON file, got {spec!r} (no such file)")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"model config {path} is not valid JSON ({e}); expected an object of FastGHAConfig fields") from None
    try:
        return FastGHAConfig.from_dict(data)
    except (ValueError, TypeError) as e:  # an unknown field, or one out of its range (FastGHAConfig.validate)
        raise ValueError(f"model config {path}: {e}") from None


def build_model(cfg: TrainConfig, dino_weights: str | None = None, vae_weights: str | None = None, init_from: str | None = None):
    """A fresh ``FastGHA`` (seeded with ``cfg.seed`` so that every DDP rank builds the same one), or
    the model in ``init_from``; pretrained encoder folders are loaded when given."""
    from ..model.fastgha import FastGHA

    if init_from:
        model = FastGHA.from_pretrained(init_from)
        log.info("initialised from %s (model config %r)", init_from, model.config.name)
    else:
        torch.manual_seed(cfg.seed)
        model = FastGHA(model_config_from_spec(cfg.model))
    if dino_weights or vae_weights:
        model.load_pretrained_encoders(dino_weights=dino_weights, vae_weights=vae_weights)
    model.train()
    return model


def build_training_data(data: str, cfg: TrainConfig, model_config):
    """``(train_dataset, val_dataset, shuffle)`` for ``--data synthetic`` or an on-disk layout folder.
    Synthetic samples are read in index order (``shuffle=False``): the dataset is already in random
    subject order and caches the subject that consecutive indices share. With
    ``cfg.input_matting.enabled`` the training inputs are matted by our own matting, with
    ``cfg.input_camera_noise.enabled`` their cameras get tracking-shaped pose noise
    (``data/augment.py``); the validation samples keep exact inputs and cameras."""
    if cfg.input_matting.enabled and data != "synthetic":
        raise ValueError(f"input_matting needs --data synthetic (it re-mattes rendered heads), got {data!r}")
    train, val, shuffle = _training_data(data, cfg, model_config)
    if cfg.input_matting.enabled:
        from ..data.augment import InputMattingDataset

        train = InputMattingDataset(train, cfg.input_matting, seed=cfg.seed)
        log.info("input matting on: %s", cfg.input_matting)
    if cfg.input_camera_noise.enabled:
        from ..data.augment import InputCameraNoiseDataset

        train = InputCameraNoiseDataset(train, cfg.input_camera_noise, seed=cfg.seed)
        log.info("input camera noise on: %s", cfg.input_camera_noise)
    return train, val, shuffle


def _training_data(data: str, cfg: TrainConfig, model_config):
    from ..data import sampling

    if data == "synthetic":
        from ..data.synthetic import HELDOUT_SEEDS, TRAIN_SEEDS

        res = cfg.synthetic_resolution or int(model_config.render_size)
        kw = dict(resolution=res, num_inputs=cfg.num_inputs, num_targets=cfg.num_targets, timesteps=cfg.synthetic_timesteps, num_cameras=cfg.synthetic_cameras)
        train = sampling.SyntheticTrainingDataset(TRAIN_SEEDS, seed=cfg.seed, **kw)
        val = sampling.SyntheticTrainingDataset(HELDOUT_SEEDS, seed=cfg.seed + 1, **kw)
        return train, val, False
    from ..data.layout import open_dataset

    root = Path(data)
    if not root.is_dir():
        raise ValueError(f"--data must be 'synthetic' or a dataset folder (docs/data-format.md), got {data!r} (no such folder)")
    sources = open_dataset(root)
    if not sources:
        raise ValueError(f"{root}: no sequences found")
    check_expression_space(sources, model_config.expression_space, root)
    res = int(model_config.render_size)
    train = sampling.TrainingDataset(sources, num_inputs=cfg.num_inputs, num_targets=cfg.num_targets, seed=cfg.seed, resolution=res)
    val = sampling.TrainingDataset(sources, num_inputs=cfg.num_inputs, num_targets=cfg.num_targets, seed=cfg.seed + 1, resolution=res)
    return train, val, True


def check_expression_space(sources: list, space: str, where) -> None:
    """``ValueError`` when a sequence's expression codes are not in the model's ``space``: a model
    trained or evaluated on them failed at its first sample, after the model and data were built,
    with "expression must have shape [B=1, E=53], got [1, 120]"."""
    other = sorted({str(s.expression_space) for s in sources} - {str(space)})
    if other:
        raise ValueError(
            f"{where}: the sequences' expression space {', '.join(other)} is not the model's {space!r}; "
            f"use a model whose config has that expression_space (docs/model.md)"
        )


def build_eval_sources(data: str, subjects: int | None, resolution: int, timesteps: int = 16, num_cameras: int = 16,
                       first_seed: int | None = None) -> list:
    """Held-out ``SequenceSource`` objects: ``synthetic-heldout`` or a dataset folder.

    Synthetic subjects are the seeds ``first_seed, first_seed + 1, ...`` (default: the first of
    ``data.synthetic.HELDOUT_SEEDS``, 1000000); every one must be a held-out seed, else ``ValueError``
    (a training seed would measure memorisation). ``first_seed`` with a dataset folder raises too.
    """
    if data in ("synthetic-heldout", "synthetic"):
        from ..data.synthetic import HELDOUT_SEEDS, make_sequence

        start = HELDOUT_SEEDS.start if first_seed is None else int(first_seed)
        seeds = list(range(start, start + (subjects or 4)))
        if seeds[0] not in HELDOUT_SEEDS or seeds[-1] not in HELDOUT_SEEDS:
            raise ValueError(
                f"held-out synthetic seeds must lie in [{HELDOUT_SEEDS.start}, {HELDOUT_SEEDS.stop}), got {seeds[0]}..{seeds[-1]}"
            )
        return [make_sequence(s, timesteps=timesteps, num_cameras=num_cameras, resolution=resolution) for s in seeds]
    from ..data.layout import open_dataset

    if first_seed is not None:
        raise ValueError(f"--first-seed applies to synthetic held-out data only, got --data {data!r}")
    root = Path(data)
    if not root.is_dir():
        raise ValueError(f"--data must be 'synthetic-heldout' or a dataset folder, got {data!r} (no such folder)")
    sources = open_dataset(root)
    return sources[:subjects] if subjects else sources
