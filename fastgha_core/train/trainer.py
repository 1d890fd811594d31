"""The training loop (paper §4.1): Adam with its own learning rate for the deformation MLP, the
§3.3 loss on renders of each sample's deformed Gaussians into its S target cameras, gradient
clipping and optional warmup, bf16 autocast on GPU, DistributedDataParallel under ``torchrun``,
resumable checkpoints, validation renders, a progress bar and a CSV log.

Run layout (``RUN_DIR``)::

    train_config.json           the TrainConfig and the model config of this run
    log.csv                     one row per logged step (loss terms, lr, throughput, timings)
    val.csv, val/step_<step:08d>.png   validation PSNR and render grids (inputs | ground truth | ours)
    checkpoints/step_<step:08d>/  model.safetensors, trainer_state.pt (optimizer, scheduler, RNG, step)
    model/                      the final model (FastGHA.save_pretrained)

Data order is a pure function of (seed, step, rank): sample ``p`` of the global stream is index
``perm_e[p mod L]`` of a map-style dataset, where ``perm_e`` is the permutation of epoch
``e = p // L`` drawn from ``seed + e`` (or index ``p mod L`` with ``shuffle=False``, for datasets
that are already in random order and cache consecutive items, like ``SyntheticTrainingDataset``), and rank ``r`` of ``W`` takes the positions
``step·W·B + r·B + j``. Together with the saved RNG states this makes ``--resume`` continue exactly
where a run stopped (bit-exact on CPU with a deterministic renderer).
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import random
import shutil
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch
from torch import Tensor, nn

from ..cameras import Cameras
from ..constants import BACKGROUND_RGB
from ..data.augment import InputCameraNoise, InputMatting
from .losses import LOSS_TERMS, FastGHALoss, LossConfig

__all__ = [
    "TrainConfig",
    "TRAIN_PRESETS",
    "get_train_preset",
    "load_train_config",
    "Trainer",
    "DistInfo",
    "init_distributed",
    "StreamSampler",
    "latest_checkpoint",
    "checkpoint_to_start_from",
    "resize_sample",
]

log = logging.getLogger(__name__)


@dataclass
class TrainConfig:
    """Everything about a training run except the network (that is ``model``)."""

    model: str = "paper"  # model preset name ("tiny" | "paper") or a FastGHAConfig JSON file
    steps: int = 400_000  # optimiser steps (paper: 400k at batch 1 on 4 GPUs)
    batch_size: int = 1  # samples per rank and step (paper: 1)
    lr: float = 5e-5  # Adam learning rate of everything but the deformation MLP (paper)
    lr_deform: float = 5e-4  # Adam learning rate of model.deform (paper)
    betas: tuple[float, float] = (0.9, 0.999)  # Adam betas
    weight_decay: float = 0.0  # Adam (L2) weight decay
    warmup_steps: int = 0  # linear learning-rate warmup from 0 over this many steps
    lr_schedule: str = "constant"  # after warmup: "constant" | "cosine" (anneal to min_lr_ratio * lr at `steps`)
    min_lr_ratio: float = 0.1  # final learning rate of the cosine schedule, as a fraction of lr
    grad_clip: float = 1.0  # max global gradient norm (0 = no clipping)
    num_inputs: int = 4  # input images per sample (paper: 4)
    num_targets: int = 8  # supervision views per sample (paper: 8 = 4 input cameras + 4 novel)
    seed: int = 0  # model init, data order, per-rank RNG streams
    workers: int = 0  # DataLoader worker processes per rank
    log_every: int = 10  # CSV row every this many steps
    val_every: int = 1000  # validation renders every this many steps (0 = never)
    val_samples: int = 2  # samples in the validation grid
    ckpt_every: int = 5000  # checkpoint every this many steps (and at the end)
    keep_checkpoints: int = 3  # keep the last K checkpoints
    render_backend: str = "auto"  # fastgha_core.render backend ("auto" = gsplat on CUDA, else cpu)
    bf16: bool = True  # bf16 autocast of the network on CUDA (never on CPU)
    find_unused_parameters: bool = True  # DDP option; True because the DINOv3 ViT holds a mask_token the forward never uses
    synthetic_resolution: int = 0  # image size of --data synthetic samples (0 = model render size)
    synthetic_timesteps: int = 16  # timesteps per synthetic sequence
    synthetic_cameras: int = 16  # cameras per synthetic sequence
    vgg_weights: str | None = None  # torchvision VGG16 weights file for L_perc (None: L_perc off)
    train_only: str = ""  # "deform": freeze the reconstruction network, train the deformation MLP only
    loss: LossConfig = field(default_factory=LossConfig)
    # pose noise on the cameras given to the encoder (not the supervision cameras), shaped like
    # tracking errors (data/augment.py); off by default and in every preset
    input_camera_noise: InputCameraNoise = field(default_factory=InputCameraNoise)
    # input images matted by our own matting from a fit-like head instead of the exact alpha
    # (data/augment.py; --data synthetic only); off by default and in every preset
    input_matting: InputMatting = field(default_factory=InputMatting)

    def __post_init__(self) -> None:
        if self.lr_schedule not in ("constant", "cosine"):
            raise ValueError(f"train config: lr_schedule must be 'constant' or 'cosine', got {self.lr_schedule!r}")
        if self.train_only not in ("", "deform"):
            raise ValueError(f"train config: train_only must be '' or 'deform', got {self.train_only!r}")
        if not 0.0 <= self.min_lr_ratio <= 1.0:
            raise ValueError(f"train config: min_lr_ratio must be in [0, 1], got {self.min_lr_ratio}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "TrainConfig":
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"train config: unknown field(s) {unknown}; expected some of {sorted(names)}")
        from ..config import check_field_types

        check_field_types(cls, data, "train config")
        kw = dict(data)
        if "loss" in kw and isinstance(kw["loss"], dict):
            lnames = {f.name for f in fields(LossConfig)}
            bad = sorted(set(kw["loss"]) - lnames)
            if bad:
                raise ValueError(f"train config: unknown loss field(s) {bad}; expected some of {sorted(lnames)}")
            check_field_types(LossConfig, kw["loss"], "train config: loss")
            lk = dict(kw["loss"])
            if "perc_layers" in lk:
                lk["perc_layers"] = tuple(lk["perc_layers"])
            kw["loss"] = LossConfig(**lk)
        if "betas" in kw:
            kw["betas"] = tuple(kw["betas"])
        if "input_camera_noise" in kw and not isinstance(kw["input_camera_noise"], InputCameraNoise):
            kw["input_camera_noise"] = InputCameraNoise.from_dict(kw["input_camera_noise"])
        if "input_matting" in kw and not isinstance(kw["input_matting"], InputMatting):
            kw["input_matting"] = InputMatting.from_dict(kw["input_matting"])
        return cls(**kw)


def lr_factor(config: TrainConfig, step: int) -> float:
    """Learning-rate multiplier at optimiser step ``step`` (0-based): linear warmup, then constant or cosine."""
    warm = max(0, int(config.warmup_steps))
    if step < warm:
        return (step + 1) / warm
    if config.lr_schedule == "constant":
        return 1.0
    if config.lr_schedule == "cosine":
        span = max(1, int(config.steps) - warm)
        t = min(1.0, (step - warm) / span)
        return config.min_lr_ratio + (1.0 - config.min_lr_ratio) * 0.5 * (1.0 + math.cos(math.pi * t))
    raise ValueError(f"train config: lr_schedule must be 'constant' or 'cosine', got {config.lr_schedule!r}")


def _paper_train() -> TrainConfig:
    return TrainConfig(model="paper")


def _tiny_train() -> TrainConfig:
    # CPU-sized run on synthetic heads: the paper's 5e-5 / 5e-4 learn far too slowly for the few
    # thousand steps a CPU session buys, so the tiny preset uses 3e-4 (network) / 1e-3 (deformation)
    # with a short warmup.
    return TrainConfig(
        model="tiny", steps=3000, lr=3e-4, lr_deform=1e-3, warmup_steps=100, log_every=1, val_every=250, ckpt_every=250
    )


TRAIN_PRESETS: dict[str, TrainConfig] = {"paper": _paper_train(), "tiny": _tiny_train()}


def get_train_preset(name: str) -> TrainConfig:
    if name not in TRAIN_PRESETS:
        raise ValueError(f"unknown training preset {name!r}; expected one of {sorted(TRAIN_PRESETS)} or a JSON file")
    return TrainConfig.from_dict(json.loads(json.dumps(TRAIN_PRESETS[name].to_dict())))


def load_train_config(spec: str) -> TrainConfig:
    """``"tiny"`` / ``"paper"`` or a JSON file holding TrainConfig fields (``"model"`` names the
    model preset or a FastGHAConfig JSON file; an optional ``"preset"`` key picks the base)."""
    if spec in TRAIN_PRESETS:
        return get_train_preset(spec)
    path = Path(spec)
    if not path.is_file():
        raise ValueError(f"--config must be one of {sorted(TRAIN_PRESETS)} or a JSON file, got {spec!r} (no such file)")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"--config {path} is not valid JSON ({e}); expected an object of TrainConfig fields") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object of TrainConfig fields, got {type(data).__name__}")
    preset = data.pop("preset", None) or (data.get("model") if data.get("model") in TRAIN_PRESETS else "paper")
    base = get_train_preset(preset)
    merged = base.to_dict()
    for key in ("loss", "input_camera_noise", "input_matting"):
        if not isinstance(data.get(key, {}), dict):
            raise ValueError(f"{path}: {key} must be an object of fields, got {data[key]!r}")
    loss = dict(merged["loss"])
    loss.update(data.pop("loss", {}) or {})
    nested = {}
    for key in ("input_camera_noise", "input_matting"):
        nested[key] = dict(merged[key])
        nested[key].update(data.pop(key, {}) or {})
    merged.update(data)
    merged["loss"] = loss
    merged.update(nested)
    return TrainConfig.from_dict(merged)


# ---------------------------------------------------------------------------- distributed
@dataclass
class DistInfo:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def init_distributed(device: str | None = None) -> DistInfo:
    """Join the process group when launched by ``torchrun`` (``WORLD_SIZE`` > 1): NCCL on CUDA,
    gloo on CPU. ``device`` None picks ``cuda:LOCAL_RANK`` when CUDA is available, else CPU."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", str(rank)))
    if device is None:
        dev = torch.device(f"cuda:{local}") if torch.cuda.is_available() else torch.device("cpu")
    else:
        dev = torch.device(device)
        if dev.type == "cuda" and dev.index is None:
            dev = torch.device(f"cuda:{local}")
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
    if world > 1 and not torch.distributed.is_initialized():
        backend = "nccl" if dev.type == "cuda" else "gloo"
        torch.distributed.init_process_group(backend=backend, rank=rank, world_size=world)
        log.info("joined process group: rank %d of %d (%s)", rank, world, backend)
    return DistInfo(rank=rank, world_size=world, local_rank=local, device=dev)


# ---------------------------------------------------------------------------- data order
class StreamSampler(torch.utils.data.Sampler):
    """Indices of a map-style dataset for one rank, from a given step on (see module docstring)."""

    def __init__(self, length: int, batch_size: int, rank: int, world_size: int, seed: int, start_step: int, steps: int, shuffle: bool = True):
        if length <= 0:
            raise ValueError(f"the training dataset is empty (length {length})")
        self.length, self.batch, self.rank, self.world = length, batch_size, rank, world_size
        self.seed, self.start_step, self.steps, self.shuffle = seed, start_step, steps, shuffle
        self._perm_epoch, self._perm = -1, None

    def _index(self, p: int) -> int:
        epoch, i = divmod(p, self.length)
        if not self.shuffle:
            return i
        if epoch != self._perm_epoch:
            g = torch.Generator().manual_seed(self.seed * 1_000_003 + epoch)
            self._perm, self._perm_epoch = torch.randperm(self.length, generator=g), epoch
        return int(self._perm[i])

    def __iter__(self) -> Iterator[int]:
        for step in range(self.start_step, self.steps):
            base = step * self.world * self.batch + self.rank * self.batch
            for j in range(self.batch):
                yield self._index(base + j)

    def __len__(self) -> int:
        return max(0, self.steps - self.start_step) * self.batch


# ---------------------------------------------------------------------------- batch helpers
def _resize(x: Tensor, size: int, mode: str) -> Tensor:  # [N, C, H, W] -> [N, C, size, size]
    if tuple(x.shape[-2:]) == (size, size):
        return x
    if mode == "nearest":
        return torch.nn.functional.interpolate(x, size=(size, size), mode="nearest")
    return torch.nn.functional.interpolate(x, size=(size, size), mode="bilinear", antialias=True, align_corners=False)


def _scale_K(K: Tensor, sx: float, sy: float) -> Tensor:  # [..., 3, 3]
    K = K.clone()
    K[..., 0, :] *= sx
    K[..., 1, :] *= sy
    return K


def resize_sample(batch, input_size: int, render_size: int):
    """Resize a collated batch (square images) to the model's input and render sizes, adjusting K.
    Depth priors are resized with nearest neighbours so that no 0 (= no value) mixes into them."""
    from dataclasses import replace

    B, V, _, H, W = batch.input_images.shape
    if H != W or batch.target_images.shape[-1] != batch.target_images.shape[-2]:
        raise ValueError(f"training images must be square, got inputs {H}x{W} and targets {list(batch.target_images.shape[-2:])}")
    S = batch.target_images.shape[1]
    Ht = batch.target_images.shape[-1]
    changes: dict[str, Tensor] = {}
    if H != input_size:
        changes["input_images"] = _resize(batch.input_images.flatten(0, 1), input_size, "area").unflatten(0, (B, V))
        if getattr(batch, "input_depths", None) is not None:
            changes["input_depths"] = _resize(batch.input_depths.flatten(0, 1), input_size, "nearest").unflatten(0, (B, V))
        changes["input_K"] = _scale_K(batch.input_K, input_size / W, input_size / H)
    if Ht != render_size:
        flat = lambda t: t.flatten(0, 1)  # noqa: E731
        changes["target_images"] = _resize(flat(batch.target_images), render_size, "area").unflatten(0, (B, S))
        changes["target_masks"] = _resize(flat(batch.target_masks), render_size, "area").unflatten(0, (B, S))
        changes["target_depths"] = _resize(flat(batch.target_depths), render_size, "nearest").unflatten(0, (B, S))
        changes["target_K"] = _scale_K(batch.target_K, render_size / Ht, render_size / Ht)
    return replace(batch, **changes) if changes else batch


def _to_device(batch, device: torch.device):
    from dataclasses import replace

    return replace(batch, **{f.name: getattr(batch, f.name).to(device, non_blocking=True) for f in fields(batch) if getattr(batch, f.name) is not None})


def _unwrap(model: nn.Module) -> nn.Module:
    return model.module if isinstance(model, nn.parallel.DistributedDataParallel) else model


def render_batch(gaussians: list, target_K: Tensor, target_w2c: Tensor, size: int, backend: str):
    """Render sample b's Gaussians into its S target cameras over ``BACKGROUND_RGB``.

    Returns ``(rgb [B*S, 3, H, W], alpha [B*S, 1, H, W], depth [B*S, 1, H, W])``.
    """
    from ..render import render

    rgbs, alphas, depths = [], [], []
    for b, g in enumerate(gaussians):
        cams = Cameras(target_K[b].float(), target_w2c[b].float(), size, size)
        out = render(g.to(dtype=torch.float32), cams, background=BACKGROUND_RGB, backend=backend)
        rgbs.append(out.rgb)
        alphas.append(out.alpha)
        depths.append(out.depth)
    return torch.cat(rgbs), torch.cat(alphas), torch.cat(depths)


def capture_rng(device: torch.device) -> dict[str, Any]:
    state: dict[str, Any] = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if device.type == "cuda":
        state["cuda"] = torch.cuda.get_rng_state(device)
    return state


def restore_rng(state: dict[str, Any], device: torch.device) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if device.type == "cuda" and "cuda" in state:
        torch.cuda.set_rng_state(state["cuda"], device)


def _seed_all(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)
    random.seed(seed)


def checkpoint_to_start_from(run_dir: str | Path, resume: bool) -> Path | None:
    """The checkpoint a run in ``run_dir`` continues from: the newest one with ``resume``, None without.

    Raises:
        ValueError: ``run_dir`` holds a run's checkpoint and ``resume`` is False. A fresh run there
            would mix with the old one: the checkpoint pruning keeps the newest steps, so it deleted the
            new run's own checkpoint and left the old run's for a later ``--resume``.
    """
    ck = latest_checkpoint(run_dir)
    if ck is not None and not resume:
        raise ValueError(f"{run_dir} already holds a training run (checkpoint {ck.name}): add --resume to continue it, or choose another --out for a new run")
    return ck


def latest_checkpoint(run_dir: str | Path) -> Path | None:
    """The newest complete checkpoint folder of a run (one with ``trainer_state.pt``), or None."""
    ck = Path(run_dir) / "checkpoints"
    if not ck.is_dir():
        return None
    done = sorted(p for p in ck.glob("step_*") if (p / "trainer_state.pt").is_file() and (p / "model.safetensors").is_file())
    return done[-1] if done else None


# ---------------------------------------------------------------------------- trainer
class Trainer:
    """Trains ``model`` (a ``FastGHA``) on a map-style dataset of ``TrainingSample``.

    Args:
        config: the run's :class:`TrainConfig`.
        model: the network (on CPU; moved to the rank's device here).
        dataset: map-style dataset (``__len__``/``__getitem__``) of ``TrainingSample``.
        run_dir: output folder (see module docstring).
        val_dataset: samples for the validation grid (default: the first items of ``dataset``).
        dist: process-group info (default: :func:`init_distributed`).
        collate_fn: batch collation (default: ``fastgha_core.data.sampling.collate_samples``).
        shuffle: permute the dataset per epoch (False: read it in index order).
    """

    def __init__(self, config: TrainConfig, model: nn.Module, dataset, run_dir: str | Path, val_dataset=None, dist: DistInfo | None = None, collate_fn=None, shuffle: bool = True):
        self.config = config
        self.dist = dist or init_distributed()
        self.device = self.dist.device
        self.run_dir = Path(run_dir)
        self.dataset = dataset
        self.shuffle = bool(shuffle)
        self.val_dataset = val_dataset if val_dataset is not None else dataset
        if collate_fn is None:
            from ..data.sampling import collate_samples

            collate_fn = collate_samples
        self.collate_fn = collate_fn
        self.model = model.to(self.device)
        self.model.train()
        core = self.model
        self.model_config = core.config
        if config.train_only == "deform":  # the reconstruction stays as it is: no gradient reaches it
            deform_ids = {id(p) for p in core.deform.parameters()}
            for p in core.parameters():
                p.requires_grad_(id(p) in deform_ids)
        deform_params = [p for p in core.deform.parameters() if p.requires_grad]
        deform_ids = {id(p) for p in deform_params}
        other = [p for p in core.parameters() if p.requires_grad and id(p) not in deform_ids]
        groups = [{"params": other, "lr": config.lr, "name": "net"}, {"params": deform_params, "lr": config.lr_deform, "name": "deform"}]
        groups = [g for g in groups if g["params"]]
        if not groups:
            raise ValueError("the model has no trainable parameters")
        self.trainable = [p for g in groups for p in g["params"]]
        self.optimizer = torch.optim.Adam(groups, betas=tuple(config.betas), weight_decay=config.weight_decay)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, lambda s: lr_factor(config, s))
        vgg = None
        if config.vgg_weights and config.loss.w_perc > 0:
            from .vgg import load_vgg16

            vgg = load_vgg16(config.vgg_weights, self.device)
        self.loss_fn = FastGHALoss(config.loss, vgg=vgg)
        self.step = 0
        self._last_ckpt_step = -1
        # per-rank random streams (the model was initialised identically on every rank before this)
        _seed_all(config.seed * 7919 + 1 + self.dist.rank)
        self.use_bf16 = bool(config.bf16 and self.device.type == "cuda")
        if self.dist.distributed:
            kw = {"device_ids": [self.device.index]} if self.device.type == "cuda" else {}
            self.ddp: nn.Module = nn.parallel.DistributedDataParallel(self.model, find_unused_parameters=config.find_unused_parameters, **kw)
        else:
            self.ddp = self.model

    # ------------------------------------------------------------ checkpoints
    def save_checkpoint(self) -> Path | None:
        """Write ``checkpoints/step_<step:08d>`` atomically (rank 0) and prune old ones."""
        rng = capture_rng(self.device)
        if self.dist.distributed:  # every rank's RNG streams go into the checkpoint
            all_rng: list[Any] = [None] * self.dist.world_size
            torch.distributed.all_gather_object(all_rng, rng)
        else:
            all_rng = [rng]
        self._last_ckpt_step = self.step
        if not self.dist.is_main:
            return None
        ck_root = self.run_dir / "checkpoints"
        ck_root.mkdir(parents=True, exist_ok=True)
        final = ck_root / f"step_{self.step:08d}"
        tmp = ck_root / f".tmp-step_{self.step:08d}-{os.getpid()}"
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir()
        self.model.save_pretrained(tmp)  # config.json + model.safetensors: a loadable model folder
        state = {
            "step": self.step,
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "rng": all_rng,
            "world_size": self.dist.world_size,
            "train_config": self.config.to_dict(),
            "model_config": self.model_config.to_dict(),
        }
        torch.save(state, tmp / "trainer_state.pt")
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
        keep = max(1, int(self.config.keep_checkpoints))
        done = sorted(p for p in ck_root.glob("step_*") if p.is_dir())
        for old in done[:-keep]:
            shutil.rmtree(old, ignore_errors=True)
        log.info("saved checkpoint %s", final)
        self._last_ckpt_step = self.step
        return final

    def load_checkpoint(self, path: str | Path) -> None:
        """Restore model, optimizer, scheduler, step and RNG states from a checkpoint folder."""
        from safetensors.torch import load_file

        path = Path(path)
        saved = load_file(str(path / "model.safetensors"), device=str(self.device))
        own = self.model.state_dict()
        missing, unexpected = sorted(own.keys() - saved.keys()), sorted(saved.keys() - own.keys())
        reshaped = sorted(k for k in own.keys() & saved.keys() if own[k].shape != saved[k].shape)
        if missing or unexpected or reshaped:  # torch's own message lists every tensor: thousands of characters
            example = (missing or unexpected or reshaped)[0]
            raise ValueError(
                f"checkpoint {path} holds another model than this run's: {len(missing)} tensors missing, "
                f"{len(unexpected)} unexpected, {len(reshaped)} of other shapes (e.g. {example}); the --config it "
                "was trained with differs (the run folder's train_config.json says which)"
            )
        self.model.load_state_dict(saved, strict=True)
        state = torch.load(path / "trainer_state.pt", map_location="cpu", weights_only=False)
        if state.get("world_size", 1) != self.dist.world_size:
            log.warning("resuming a run saved with %d ranks on %d ranks: data order continues but is not identical", state.get("world_size"), self.dist.world_size)
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.step = int(state["step"])
        self._last_ckpt_step = self.step
        rngs = state["rng"]
        if self.dist.rank < len(rngs):
            restore_rng(rngs[self.dist.rank], self.device)
        else:  # more ranks than when saved: a fresh per-rank stream
            _seed_all(self.config.seed * 7919 + 1000 * self.dist.rank + self.step)
        log.info("resumed from %s at step %d", path, self.step)

    # ------------------------------------------------------------ one step
    def compute_losses(self, batch) -> tuple[dict[str, Tensor], dict[str, float]]:
        """Forward, render and the §3.3 loss of one collated batch (already on the device)."""
        t0 = time.perf_counter()
        with torch.autocast(device_type="cuda", dtype=torch.bfloat16, enabled=self.use_bf16):
            prior = bool(getattr(self.model_config.deform, "prior", False))
            extra = {"input_expressions": batch.input_expressions} if prior and getattr(batch, "input_expressions", None) is not None else {}
            out = self.ddp(batch.input_images, batch.input_K, batch.input_w2c, batch.expression, **extra)
        t1 = time.perf_counter()
        size = int(batch.target_images.shape[-1])
        rgb, alpha, depth = render_batch(out.gaussians, batch.target_K, batch.target_w2c, size, self.config.render_backend)
        t2 = time.perf_counter()
        terms = self.loss_fn(
            rgb,
            alpha,
            depth,
            batch.target_images.flatten(0, 1).float(),
            batch.target_masks.flatten(0, 1).float(),
            batch.target_depths.flatten(0, 1).float(),
            view_depth=None if out.view_depth is None else out.view_depth.flatten(0, 1).float(),
            view_images=batch.input_images.flatten(0, 1).float(),
            view_true_depth=self._input_true_depth(batch),
            view_K=batch.input_K.float(),
            view_w2c=batch.input_w2c.float(),
        )
        t3 = time.perf_counter()
        return terms, {"t_forward": t1 - t0, "t_render": t2 - t1, "t_loss": t3 - t2}

    def _input_true_depth(self, batch) -> Tensor | None:
        """``[B*V, H, W]`` the input views' true depth along their pixel rays (``L_indepth``), or None
        when the term is off or the batch has none (``TrainingSample.input_depths``)."""
        from .losses import ray_depth_from_z

        depths = getattr(batch, "input_depths", None)
        if not self.config.loss.w_input_depth or depths is None:
            return None
        return ray_depth_from_z(depths[:, :, 0].float(), batch.input_K.float()).flatten(0, 1)

    def train_step(self, batch) -> tuple[dict[str, Tensor], dict[str, float]]:
        batch = _to_device(resize_sample(batch, self.model_config.input_size, self.model_config.render_size), self.device)
        self.optimizer.zero_grad(set_to_none=True)
        terms, timing = self.compute_losses(batch)
        t0 = time.perf_counter()
        terms["total"].backward()
        t1 = time.perf_counter()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.trainable, self.config.grad_clip if self.config.grad_clip > 0 else float("inf"))
        self.optimizer.step()
        self.scheduler.step()
        self.step += 1
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        timing.update(t_backward=t1 - t0, t_optim=time.perf_counter() - t1, grad_norm=float(grad_norm))
        return {k: v.detach() for k, v in terms.items()}, timing

    # ------------------------------------------------------------ loop
    def _loader(self, start_step: int, steps: int):
        sampler = StreamSampler(len(self.dataset), self.config.batch_size, self.dist.rank, self.dist.world_size, self.config.seed, start_step, steps, self.shuffle)
        return torch.utils.data.DataLoader(
            self.dataset,
            batch_size=self.config.batch_size,
            sampler=sampler,
            num_workers=self.config.workers,
            collate_fn=self.collate_fn,
            persistent_workers=False,
            drop_last=True,
        )

    def fit(self, steps: int | None = None, resume: bool = False) -> dict[str, float]:
        """Train until ``steps`` (default ``config.steps``) and export the model; returns the last
        logged row."""
        from tqdm.auto import tqdm

        cfg = self.config
        steps = int(cfg.steps if steps is None else steps)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        ck = checkpoint_to_start_from(self.run_dir, resume)
        if resume:
            if ck is None:
                log.warning("--resume: no checkpoint in %s; starting from step 0", self.run_dir / "checkpoints")
            else:
                self.load_checkpoint(ck)
        if self.dist.is_main:
            _trim_csv(self.run_dir / "val.csv", self.step)  # a resumed run re-validates the steps past its checkpoint
            (self.run_dir / "train_config.json").write_text(
                json.dumps({"train": cfg.to_dict(), "model": self.model_config.to_dict(), "world_size": self.dist.world_size}, indent=2)
            )
        csv_log = _CSVLog(self.run_dir / "log.csv", self.step) if self.dist.is_main else None
        last: dict[str, float] = {}
        bar = tqdm(total=steps, initial=self.step, disable=not self.dist.is_main, desc="train", dynamic_ncols=True)
        it = iter(self._loader(self.step, steps))
        samples_per_step = cfg.batch_size * self.dist.world_size
        try:
            while self.step < steps:
                t0 = time.perf_counter()
                batch = next(it)
                t_data = time.perf_counter() - t0
                terms, timing = self.train_step(batch)
                dt = time.perf_counter() - t0
                timing["t_data"] = t_data
                bar.update(1)
                if self.step % max(1, cfg.log_every) == 0 or self.step == steps:
                    vals = self._reduce(terms)
                    row = {"step": self.step, **{f"loss_{k}": v for k, v in vals.items()}}
                    row.update({f"lr_{g.get('name', i)}": g["lr"] for i, g in enumerate(self.optimizer.param_groups)})
                    row.update(samples_per_s=samples_per_step / dt, **timing)
                    last = row
                    bar.set_postfix(loss=f"{vals['total']:.4f}", sps=f"{samples_per_step / dt:.2f}")
                    if csv_log:
                        csv_log.write(row)
                if not math.isfinite(float(terms["total"])):
                    raise FloatingPointError(f"loss became non-finite at step {self.step}: {({k: float(v) for k, v in terms.items()})}")
                if cfg.val_every and self.step % cfg.val_every == 0 and self.dist.is_main:
                    self.validate()
                if cfg.ckpt_every and self.step % cfg.ckpt_every == 0:
                    self.save_checkpoint()
        finally:
            bar.close()
            if csv_log:
                csv_log.close()
        if self._last_ckpt_step != self.step:
            self.save_checkpoint()
        if self.dist.is_main:
            self.model.save_pretrained(self.run_dir / "model")
            log.info("exported the model to %s", self.run_dir / "model")
        if self.dist.distributed:
            torch.distributed.barrier()
        return last

    def _reduce(self, terms: dict[str, Tensor]) -> dict[str, float]:
        keys = ["total", *LOSS_TERMS]
        vec = torch.stack([terms[k].float() for k in keys]).to(self.device)
        if self.dist.distributed:
            torch.distributed.all_reduce(vec)
            vec /= self.dist.world_size
        return dict(zip(keys, vec.tolist()))

    # ------------------------------------------------------------ validation
    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """Render the first ``val_samples`` validation samples, write ``val/step_<step:08d>.png``
        (rows: inputs | ground truth | ours) and a ``val.csv`` row with their PSNR. The training
        RNG streams are left untouched."""
        from .metrics import psnr
        from .visualize import save_grid

        rng = capture_rng(self.device)
        was_training = self.model.training
        self.model.eval()
        try:
            n = min(self.config.val_samples, len(self.val_dataset))
            batch = self.collate_fn([self.val_dataset[i] for i in range(n)])
            batch = _to_device(resize_sample(batch, self.model_config.input_size, self.model_config.render_size), self.device)
            with torch.autocast(device_type="cuda", dtype=torch.bfloat16, enabled=self.use_bf16):
                out = self.model(batch.input_images, batch.input_K, batch.input_w2c, batch.expression)
            size = int(batch.target_images.shape[-1])
            rgb, _, _ = render_batch(out.gaussians, batch.target_K, batch.target_w2c, size, self.config.render_backend)
            gt = batch.target_images.flatten(0, 1).float()
            value = float(psnr(rgb.clamp(0, 1), gt).mean())
            S = batch.target_images.shape[1]
            rows = []
            for b in range(n):
                rows += [list(batch.input_images[b]), list(gt[b * S : (b + 1) * S]), list(rgb[b * S : (b + 1) * S])]
            out_dir = self.run_dir / "val"
            out_dir.mkdir(parents=True, exist_ok=True)
            save_grid(out_dir / f"step_{self.step:08d}.png", rows)
            with open(self.run_dir / "val.csv", "a", newline="") as f:
                w = csv.writer(f)
                if f.tell() == 0:
                    w.writerow(["step", "psnr"])
                w.writerow([self.step, f"{value:.4f}"])
            log.info("step %d: validation PSNR %.2f dB", self.step, value)
            return {"psnr": value}
        finally:
            self.model.train(was_training)
            restore_rng(rng, self.device)


def _trim_csv(path: Path, last_step: int) -> None:
    """Drop the rows of the CSV at ``path`` whose ``step`` is past ``last_step`` (all of them for a
    fresh run, ``last_step`` 0); nothing when the file does not exist."""
    if not path.is_file():
        return
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        fields, rows = list(reader.fieldnames or []), [r for r in reader if int(r["step"]) <= last_step]
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)


class _CSVLog:
    """Append-only CSV; on resume, rows past the resumed step are dropped first."""

    def __init__(self, path: Path, start_step: int) -> None:
        self.path = path
        self.fields: list[str] | None = None
        rows: list[dict[str, str]] = []
        if path.is_file() and start_step > 0:
            with open(path, newline="") as f:
                reader = csv.DictReader(f)
                self.fields = list(reader.fieldnames or [])
                rows = [r for r in reader if int(r["step"]) <= start_step]
        self.f = open(path, "w", newline="")
        self.writer: csv.DictWriter | None = None
        if self.fields:
            self.writer = csv.DictWriter(self.f, fieldnames=self.fields, extrasaction="ignore")
            self.writer.writeheader()
            self.writer.writerows(rows)

    def write(self, row: dict[str, Any]) -> None:
        if self.writer is None:
            self.fields = list(row)
            self.writer = csv.DictWriter(self.f, fieldnames=self.fields, extrasaction="ignore")
            self.writer.writeheader()
        self.writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
        self.f.flush()

    def close(self) -> None:
        self.f.close()
