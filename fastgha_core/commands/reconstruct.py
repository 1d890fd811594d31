"""``fastgha reconstruct``: build a canonical avatar from a request folder (photos + cameras.json)."""

NAME = "reconstruct"
HELP = "reconstruct a canonical Gaussian avatar from a folder of photos + cameras.json"
QUIET_NATIVE_LOGS = True  # MediaPipe's C++ start-up lines are dropped from stderr (fastgha_core/commands/_stderr.py)


def add_arguments(parser) -> None:
    parser.add_argument("--input", required=True, help="request folder: images (sorted by name), cameras.json, optional <name>_mask.png")
    parser.add_argument("--model", default="tiny", help="preset name (tiny, paper) or a folder written by save_pretrained (default: tiny)")
    parser.add_argument("--out", required=True, help="output avatar file (.safetensors)")
    parser.add_argument("--ply", default=None, help="also export the canonical Gaussians as a 3DGS PLY")
    parser.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    parser.add_argument(
        "--refine-steps",
        type=int,
        default=0,
        help="test-time refinement steps against the input photos after the feed-forward pass (0 = off, the default; "
        "60 raise held-out synthetic novel views from 19.97 to 21.74 dB (and the sample's inputs from 19.87 to 29.33 dB) in ~8 s for 4 views on "
        "2 idle cores; on real photos (a folder from `fastgha track`) colours only, see --refine-preset; docs/model-card.md, test-time refinement). "
        "Uses the inputs' expressions from info.json or expressions.json when present",
    )
    parser.add_argument(
        "--refine-preset",
        default="auto",
        help="with --refine-steps: a fastgha_core.refine.REFINE_PRESETS name, or auto (default): photos (colours only, inside the masks) for "
        "avatars on a tracked head (head.json), default (colours, opacities, scales) for avatars on the network's depth",
    )
    parser.add_argument(
        "--no-surface",
        action="store_true",
        help="ignore head.json (written by `fastgha track`): use the network's depth instead of the tracked head surface",
    )
    parser.add_argument(
        "--surface-fit",
        default="off",
        choices=["off", "replace", "blend"],
        help="without head.json: fit the head to the photos through the folder's own cameras (needs the faces extra) and "
        "put the Gaussians on it, every pixel (replace) or the face only (blend); off (default) = the network's depth, "
        "which measured as good or better on held-out synthetic subjects (docs/model-card.md)",
    )
    parser.add_argument(
        "--refine-cameras",
        action="store_true",
        help="with --refine-steps: also learn per-view camera corrections (off by default: on exact synthetic cameras they drifted)",
    )
    parser.add_argument(
        "--cameras-out", default=None, help="with --refine-steps and --refine-cameras: write the corrected input cameras (cameras.json layout) here"
    )
    parser.add_argument("--dino-weights", default=None, help="local DINOv3 folder (Hugging Face format) to load into the model")
    parser.add_argument("--vae-weights", default=None, help="local AutoencoderKL folder (Hugging Face format) to load into the model")


def _read_image(path):
    """``[3, H, W]`` uint8, upright (fastgha_core.images: EXIF orientation, every pixel mode)."""
    import torch

    from ..images import read_image

    return torch.from_numpy(read_image(path).rgb).permute(2, 0, 1)  # [3, H, W] uint8


def _read_mask(path):
    """``[H, W]`` uint8 foreground mask, upright (16-bit masks scaled, not clipped)."""
    import torch

    from ..images import read_mask

    return torch.from_numpy(read_mask(path))  # [H, W] uint8


def _tracked_expressions(paths):
    """``[V, 53]`` ict53 codes of the images from ``expressions.json`` (``fastgha track``), or None."""
    import json

    import numpy as np

    f = paths[0].parent / "expressions.json"
    if not f.exists():
        return None
    data = json.loads(f.read_text())
    by_name = dict(zip(data.get("images", []), data.get("expressions", [])))
    missing = [p.name for p in paths if p.name not in by_name]
    if data.get("space") != "ict53" or missing:
        raise ValueError(f"{f}: expected ict53 expressions for every image, missing {missing} (space {data.get('space')!r})")
    return np.asarray([by_name[p.name] for p in paths], dtype=np.float32)


def _read_surface(path, expressions, names=None):
    """The tracked head of ``head.json`` (``{"identity": [100 ICT coefficients], "frames": {...}}``)
    with each image's expression and frame (``names``: the images' file names; ``fastgha_core.headfile``:
    the same reading as the server's ``head`` part)."""
    import json

    from ..headfile import head_surface_from_json

    if expressions is None:
        raise ValueError(f"{path} needs expressions.json beside it (both are written by `fastgha track`)")
    return head_surface_from_json(json.loads(path.read_text()), expressions, source=str(path), names=names)


def _fit_surface(images, cams, masks):
    """The head fitted through the folder's cameras (``tracking.pipeline.track_known_cameras``)."""
    import numpy as np

    from ..cli import CLIError
    from ..tracking.faces import FacesUnavailableError
    from ..tracking.pipeline import track_known_cameras

    try:
        surface, fit = track_known_cameras(
            [im.permute(1, 2, 0).numpy() for im in images], [c.flatten()[0:1] for c in cams],
            masks=None if masks[0] is None else [m.numpy() for m in masks],
        )  # fmt: skip
    except FacesUnavailableError as e:
        raise CLIError(f"--surface-fit needs the faces extra: {e}") from None
    except ValueError as e:
        raise CLIError(f"--surface-fit: no head could be fitted through the cameras ({e}); use --surface-fit off") from None
    rms = ", ".join("-" if not np.isfinite(r) else f"{r:.1f}" for r in fit.rms_px)
    print(f"fitted the head through the cameras: landmarks in {int(fit.detected.sum())} of {len(images)} photos, RMS {rms} px")
    return surface


def _blend_note(model, avatar, on_surface: bool, photos: int | None = None) -> str:
    """One line: whether the avatar's frames are view-blended (``model/viewblend.py``) and, if not, why.
    ``photos``: the input photos; blended views beyond them are mirrored views of turned photos
    (``model/mirror.py``), named as such (None: every view counted as an input view)."""
    tau = float(model.config.gaussians.view_blend_tau_deg)
    if avatar.view_blend is None:
        if not on_surface and model.config.gaussians.view_blend_surface_only:
            why = "built on the network's depth; only avatars on a tracked head (head.json) record the per-view data"
        else:
            why = "no per-view data recorded"
        return f"view blending: off for this avatar ({why}): frames draw every input view's Gaussians unweighted"
    if tau <= 0:
        return "view blending: per-view data saved, but the model's gaussians.view_blend_tau_deg is 0: frames draw unweighted"
    if avatar.view_blend.directions.shape[0] == 1:
        return "view blending: one input view, nothing to weight (2 or more photos from different angles use it)"
    v = int(avatar.view_blend.directions.shape[0])
    views = f"{v} input views"
    if photos is not None and v > photos:
        m = v - photos
        views = (f"{v} views ({photos} photo{'s' if photos != 1 else ''} + {m} mirrored "
                 f"view{'s' if m != 1 else ''} of {'turned photos' if m != 1 else 'a turned photo'})")  # fmt: skip
    return (
        f"view blending: on (tau {tau:g} deg): each frame weights the Gaussians of the {views} "
        "by their camera's angle to the frame's camera (server, animate; not the PLY)"
    )


def run(args) -> int:
    import time

    import torch

    from ..cameras import load_request_folder
    from ..cli import CLIError, check_device
    from ..model.fastgha import load_model
    from . import MAX_REFINE_STEPS, check_model_has_weights, loading, note_first_compilation

    if not 0 <= args.refine_steps <= MAX_REFINE_STEPS:
        raise CLIError(f"--refine-steps must be in 0..{MAX_REFINE_STEPS} (the server's bound), got {args.refine_steps}")
    if (args.refine_cameras or args.cameras_out) and args.refine_steps == 0:
        raise CLIError("--refine-cameras and --cameras-out need --refine-steps N > 0")
    from ..refine import REFINE_PRESETS

    if args.refine_preset != "auto" and args.refine_preset not in REFINE_PRESETS:
        raise CLIError(f"--refine-preset must be auto or one of {', '.join(REFINE_PRESETS)}, got {args.refine_preset!r}")
    if args.cameras_out and not args.refine_cameras:
        raise CLIError("--cameras-out writes the corrected cameras: add --refine-cameras (without it the cameras are not refined)")
    from ._paths import output_file

    for option, path in (("--out", args.out), ("--ply", args.ply), ("--cameras-out", args.cameras_out)):
        if path:
            output_file(path, option)
    if not str(args.out).lower().endswith(".safetensors"):
        raise CLIError(
            f"--out is the avatar file (.safetensors: what animate, export and the server read), got {args.out!r}"
            + ("; for a PLY of the Gaussians add --ply FILE" if str(args.out).lower().endswith(".ply") else "")
        )
    if args.ply is not None and not str(args.ply).lower().endswith(".ply"):
        raise CLIError(f"--ply must name a .ply file, got {args.ply!r}")
    check_device(args.device)
    check_model_has_weights(args.model)
    paths, cams = load_request_folder(args.input)
    images = [_read_image(p) for p in paths]
    masks = []
    for p in paths:
        mp = p.with_name(p.stem + "_mask.png")
        if not mp.exists():
            mp = p.parent / "masks" / (p.stem + ".png")
        masks.append(_read_mask(mp) if mp.exists() else None)
    if any(m is None for m in masks) and any(m is not None for m in masks):
        missing = [p.name for p, m in zip(paths, masks) if m is None]
        raise ValueError(f"some images have masks and some do not; missing masks for {missing}")
    loading(args.model)
    model = load_model(args.model, device=args.device, dino_weights=args.dino_weights, vae_weights=args.vae_weights)
    imgs, cameras = model.prepare(images, cams, masks if masks[0] is not None else None)
    if not 1 <= len(imgs) <= model.config.max_views:
        raise ValueError(f"model {model.config.name!r} takes 1 to {model.config.max_views} images, the folder has {len(imgs)}")
    expr_ict53 = _tracked_expressions(paths)
    surface = None
    head_file = paths[0].parent / "head.json"
    if head_file.exists() and not args.no_surface:
        surface = _read_surface(head_file, expr_ict53, [p.name for p in paths])
    mode = "replace"
    if surface is None and args.surface_fit != "off" and not args.no_surface:
        surface = _fit_surface(images, cams, masks)
        mode = args.surface_fit
    expressions = expr_ict53 if expr_ict53 is not None and model.config.expression_space == "ict53" else None
    if surface is not None or args.refine_steps > 0:  # both render the inputs (the network's depth alone does not)
        note_first_compilation(args.device)
    t0 = time.perf_counter()
    avatar = model.reconstruct(
        imgs, cameras, expressions=None if expressions is None else torch.from_numpy(expressions), surface=surface, surface_mode=mode
    )
    if torch.device(args.device).type == "cuda":
        torch.cuda.synchronize()
    dt = time.perf_counter() - t0
    refine_note = ""
    if args.refine_steps > 0:
        avatar, refine_note = _refine(args, model, avatar, paths, images, cams, masks, expressions)
    avatar.save(args.out)
    print(
        f"reconstructed {len(avatar)} Gaussians from {len(imgs)} view{'s' if len(imgs) != 1 else ''} at {model.config.input_size}^2 "
        f"in {dt * 1000:.0f} ms{refine_note} (model {model.config.name!r}, expression space {model.config.expression_space}) -> {args.out}"
    )
    print(_blend_note(model, avatar, surface is not None, photos=len(imgs)))
    if args.ply:
        avatar.to_ply(args.ply)
        print(f"wrote the canonical Gaussians as a 3DGS PLY (static: unweighted opacities, no view blending) -> {args.ply}")
    return 0


def _refine(args, model, avatar, paths, images, cams, masks, tracked=None):
    """Run ``fastgha_core.refine.refine_avatar`` with a tqdm bar; returns the avatar and a note for the summary.

    The inputs' expressions: ``info.json``'s (the synthetic samples), else ``tracked`` (``[V, E]``, the
    folder's ``expressions.json`` written by ``fastgha track``), else none (neutral)."""
    import json

    import torch
    from tqdm.auto import tqdm

    from ..cameras import Cameras, cameras_to_json
    from ..data.samples import info_expressions
    from ..refine import refine_avatar, refine_config_for, refine_preset_for

    sizes = {tuple(im.shape[-2:]) for im in images}
    if len(sizes) != 1:
        raise ValueError(f"--refine-steps needs input photos of one size, got sizes {sorted(sizes)}")
    try:
        expressions = info_expressions(paths[0].parent, len(paths), model.config.expression_dim)
    except ValueError as e:
        raise ValueError(f"{e} (model {model.config.name!r})") from None
    if expressions is None and tracked is not None:
        expressions = torch.as_tensor(tracked, dtype=torch.float32)
    config = refine_config_for(avatar, args.refine_steps, args.refine_preset, **({"optimize_cameras": True} if args.refine_cameras else {}))
    cam_batch = Cameras.stack([c.flatten()[0] for c in cams])
    mask_t = torch.stack(masks) if masks[0] is not None else None
    with tqdm(total=args.refine_steps, desc="refining", unit="step") as bar:
        res = refine_avatar(
            model, avatar, torch.stack(images), cam_batch, mask_t,
            config=config, progress=lambda i, n: bar.update(1), expressions=expressions,
        )
    if args.cameras_out:
        from pathlib import Path

        Path(args.cameras_out).parent.mkdir(parents=True, exist_ok=True)  # as --out's folder is made
        Path(args.cameras_out).write_text(json.dumps(cameras_to_json(res.cameras), indent=1) + "\n")
    return res.avatar, f", refined in {res.timings['total']:.1f} s ({args.refine_steps} steps, preset {refine_preset_for(avatar, args.refine_preset)!r})"
