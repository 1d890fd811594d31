NAME = "train"
HELP = "train a FastGHA model (paper §3.3 losses; single process or DDP under torchrun)"


def add_arguments(parser) -> None:
    parser.add_argument("--config", default="tiny", help="training preset 'tiny' | 'paper' or a JSON file of TrainConfig fields (default: tiny)")
    parser.add_argument("--data", required=True, help="'synthetic' (samples generated on the fly) or a dataset folder in our layout (docs/data-format.md)")
    parser.add_argument("--out", required=True, help="run folder: log.csv, val/, checkpoints/, model/")
    parser.add_argument("--steps", type=int, default=None, help="total optimiser steps (default: the config's)")
    parser.add_argument("--resume", action="store_true", help="continue from the newest checkpoint in --out")
    parser.add_argument("--batch-size", type=int, default=None, help="samples per process and step")
    parser.add_argument("--workers", type=int, default=None, help="DataLoader worker processes per rank")
    parser.add_argument("--val-every", type=int, default=None, help="validation renders every N steps (0 = never)")
    parser.add_argument("--ckpt-every", type=int, default=None, help="checkpoint every N steps")
    parser.add_argument("--lr", type=float, default=None, help="learning rate of the network (paper: 5e-5)")
    parser.add_argument("--lr-deform", type=float, default=None, help="learning rate of the deformation MLP (paper: 5e-4)")
    parser.add_argument("--warmup-steps", type=int, default=None, help="linear learning-rate warmup over this many steps")
    parser.add_argument("--lr-schedule", choices=("constant", "cosine"), default=None, help="after warmup: constant, or cosine annealing to --min-lr-ratio x lr at --steps")
    parser.add_argument("--min-lr-ratio", type=float, default=None, help="final learning rate of the cosine schedule as a fraction of the initial one (default 0.1)")
    parser.add_argument("--seed", type=int, default=None, help="model init and data order seed")
    parser.add_argument("--render-backend", default=None, help="rasterizer backend (auto | cpu | reference | torch_tiles | gsplat)")
    parser.add_argument("--device", default=None, help="torch device (default: cuda:LOCAL_RANK when available, else cpu)")
    parser.add_argument("--dino-weights", default=None, help="local Hugging Face DINOv3 folder (loaded, frozen)")
    parser.add_argument("--vae-weights", default=None, help="local Hugging Face AutoencoderKL folder (loaded, frozen encoder)")
    parser.add_argument("--vgg-weights", default=None, help="torchvision VGG16 weights (.pth/.safetensors) for the perceptual loss; without it the loss is off")
    parser.add_argument("--input-camera-noise", action="store_true", help="perturb the input cameras given to the encoder with tracking-shaped pose noise (magnitudes: the config's input_camera_noise, docs/training.md); off by default")
    parser.add_argument("--input-matting", action="store_true", help="matte the synthetic input images with our own matting from a fit-like head instead of the exact alpha (docs/training.md); off by default")
    parser.add_argument("--init-from", default=None, help="start from a model folder written by save_pretrained (e.g. a previous run's model/)")


def run(args) -> int:
    from ..cli import CLIError
    from ..train.builders import build_model, build_training_data
    from ..train.trainer import Trainer, checkpoint_to_start_from, init_distributed, load_train_config

    cfg = load_train_config(args.config)
    overrides = {
        "steps": args.steps,
        "batch_size": args.batch_size,
        "workers": args.workers,
        "val_every": args.val_every,
        "ckpt_every": args.ckpt_every,
        "lr": args.lr,
        "lr_deform": args.lr_deform,
        "warmup_steps": args.warmup_steps,
        "lr_schedule": args.lr_schedule,
        "min_lr_ratio": args.min_lr_ratio,
        "seed": args.seed,
        "render_backend": args.render_backend,
        "vgg_weights": args.vgg_weights,
    }
    for k, v in overrides.items():
        if v is not None:
            setattr(cfg, k, v)
    if args.input_camera_noise:
        cfg.input_camera_noise.enabled = True
    if args.input_matting:
        cfg.input_matting.enabled = True
    if not 0.0 <= cfg.min_lr_ratio <= 1.0:
        raise CLIError(f"--min-lr-ratio must be in [0, 1], got {cfg.min_lr_ratio}")
    if cfg.steps < 1 or cfg.batch_size < 1:
        raise CLIError(f"--steps and --batch-size must be >= 1, got {cfg.steps} and {cfg.batch_size}")
    if not cfg.lr > 0 or not cfg.lr_deform >= 0:
        raise CLIError(f"--lr must be > 0 and --lr-deform >= 0 (0 freezes the deformation MLP), got {cfg.lr} and {cfg.lr_deform}")
    for flag, value in (("--workers", cfg.workers), ("--warmup-steps", cfg.warmup_steps), ("--val-every", cfg.val_every), ("--ckpt-every", cfg.ckpt_every)):
        if value < 0:
            raise CLIError(f"{flag} must be >= 0, got {value}")
    from ._paths import output_dir

    output_dir(args.out, "--out")
    checkpoint_to_start_from(args.out, args.resume)  # before the model is built (Trainer.fit checks it too)
    dist = init_distributed(args.device)
    try:
        model = build_model(cfg, args.dino_weights, args.vae_weights, args.init_from)
        train, val, shuffle = build_training_data(args.data, cfg, model.config)
        trainer = Trainer(cfg, model, train, args.out, val_dataset=val, dist=dist, shuffle=shuffle)
        last = trainer.fit(resume=args.resume)
        if dist.is_main:
            loss = last.get("loss_total")
            print(f"trained to step {trainer.step}; last loss {loss:.4f}; model in {args.out}/model" if loss is not None else f"trained to step {trainer.step}; model in {args.out}/model")
    finally:
        import torch

        if dist.distributed and torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()
    return 0
