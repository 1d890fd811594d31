"""``fastgha demo``: the main job. Reconstruct a shipped held-out subject from its 4 photos with the
shipped model, refine it against them (test-time refinement, ``fastgha_core.refine``; the preset
``refine_config_for`` picks, ``--refine-steps 0`` skips it), animate its expression sequence along
an orbit, and compare with ground truth."""

NAME = "demo"
HELP = "reconstruct a shipped sample subject, animate it along an orbit, write an MP4 + contact sheet, print timings and PSNR"


def add_arguments(parser) -> None:
    parser.add_argument("--model", default="tiny", help="model preset with shipped weights or a model folder (default: tiny)")
    parser.add_argument("--sample", default=None, help="shipped sample subject (default: the first; see --list)")
    parser.add_argument("--list", action="store_true", help="list the shipped sample subjects and exit")
    parser.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    parser.add_argument("--frames", type=int, default=None, help="animate only the first N frames, N >= 1 (default: all)")
    parser.add_argument("--json", default=None, metavar="PATH", help="also write the figures as JSON (keys reconstruction_s, refine_s, fps, psnr)")
    parser.add_argument("--backend", default="auto", help="render backend (default: auto)")
    parser.add_argument(
        "--refine-steps", type=int, default=None,
        help="test-time refinement steps against the sample's 4 photos after the feed-forward pass (default: the count of the "
        "preset refine_config_for picks, 60 for the samples: the sharper eyes and brows of docs/images/demo.png, about 4-5 s on "
        "2 idle cores; 0 = the feed-forward avatar alone)",
    )  # fmt: skip


MIN_VIDEO_SECONDS = 6.5  # long enough to watch the expressions change
MAX_VIDEO_FPS = 25.0


def video_schedule(n: int, min_seconds: float = MIN_VIDEO_SECONDS, max_fps: float = MAX_VIDEO_FPS) -> tuple[list[int], float]:
    """Frame order and frame rate of the demo video: ``n`` rendered frames played forward then
    back (a loop without a jump), slowed down so that the video lasts at least ``min_seconds``,
    at most ``max_fps`` frames per second. Raises ``ValueError`` when ``n < 1``."""
    if n < 1:
        raise ValueError(f"need at least one frame, got {n}")
    order = list(range(n)) + list(range(n - 2, 0, -1))  # 0..n-1, n-2..1
    fps = min(max_fps, len(order) / min_seconds)
    return order, fps


def _to_uint8(img):  # [3, H, W] float -> [H, W, 3] uint8
    import numpy as np

    return (img.clamp(0, 1).permute(1, 2, 0).numpy() * 255.0 + 0.5).astype(np.uint8)


def _label(img, text):  # draw a caption on an [H, W, 3] uint8 image
    import numpy as np
    from PIL import Image, ImageDraw

    im = Image.fromarray(img)
    d = ImageDraw.Draw(im)
    d.rectangle([0, 0, 7 * len(text) + 6, 14], fill=(0, 0, 0))
    d.text((3, 1), text, fill=(255, 255, 255))
    return np.asarray(im)


def run(args) -> int:
    import json
    import statistics
    import time
    from pathlib import Path

    import imageio.v3 as iio
    import numpy as np
    import torch
    from PIL import Image
    from tqdm import tqdm

    from ..constants import BACKGROUND_RGB
    from ..data.samples import list_samples, load_sample
    from ..model.fastgha import load_model
    from . import check_model_has_weights, loading
    from ..render import render
    from ..train.metrics import psnr

    if args.frames is not None and args.frames < 1:
        raise ValueError(f"--frames must be >= 1, got {args.frames} (leave it out for all frames)")
    if args.refine_steps is not None and args.refine_steps < 0:
        raise ValueError(f"--refine-steps must be >= 0, got {args.refine_steps} (0 = no refinement)")
    names = list_samples()
    if args.list:
        print("\n".join(names))
        return 0
    if not names:
        raise ValueError("no shipped sample subjects found in fastgha_core/assets/samples")
    name = args.sample or names[0]
    if name not in names:
        raise ValueError(f"unknown sample {name!r}; shipped samples: {', '.join(names)}")
    from ._paths import output_dir, output_file

    out = output_dir(args.out, "--out")
    if args.json:
        output_file(args.json, "--json")
    check_model_has_weights(args.model)
    out.mkdir(parents=True, exist_ok=True)

    torch.manual_seed(0)
    loading(args.model)
    model = load_model(args.model)
    sample = load_sample(name)
    if sample.expression_space != model.config.expression_space:
        raise ValueError(
            f"sample {name!r} uses expression space {sample.expression_space!r}, model {model.config.name!r} uses {model.config.expression_space!r}"
        )

    images, cams = model.prepare(sample.request_images, sample.request_cameras, sample.request_masks)
    model.reconstruct(images, cams)  # warm-up: numba/torch first-call costs are not reconstruction time
    t0 = time.perf_counter()
    avatar = model.reconstruct(images, cams)
    recon_s = time.perf_counter() - t0
    print(f"reconstructed {name} from {len(images)} photos in {recon_s:.3f} s: {len(avatar):,} Gaussians")
    from ..refine import REFINE_PRESETS, refine_avatar, refine_config_for, refine_preset_for

    preset = refine_preset_for(avatar)
    steps = REFINE_PRESETS[preset].steps if args.refine_steps is None else args.refine_steps
    refine_s = 0.0
    if steps > 0:
        # warm-up: one step compiles the gradient kernels (numba, on first use in a fresh checkout),
        # which is not refinement time
        refine_avatar(
            model, avatar, sample.request_images, sample.request_cameras, sample.request_masks,
            config=refine_config_for(avatar, 1, preset), expressions=sample.request_expressions,
        )  # fmt: skip
        with tqdm(total=steps, desc="refining", unit="step") as bar:
            res = refine_avatar(
                model, avatar, sample.request_images, sample.request_cameras, sample.request_masks,
                config=refine_config_for(avatar, steps, preset), progress=lambda i, k: bar.update(1), expressions=sample.request_expressions,
            )  # fmt: skip
        avatar, refine_s = res.avatar, res.timings["total"]
        print(f"refined against the {len(images)} photos in {refine_s:.1f} s ({steps} steps, preset {preset!r}): {len(avatar):,} Gaussians")

    expr = sample.expressions
    orbit = sample.orbit_cameras
    n = min(len(expr), orbit.K.shape[0])
    if args.frames is not None:
        n = min(n, args.frames)
    gt = sample.gt_frames
    bg = torch.tensor(BACKGROUND_RGB)
    frames, times, scores = [], [], []
    with torch.inference_mode():  # frames as the server draws them: no autograd bookkeeping in the FPS
        # one warm-up frame so that compilation does not count in the FPS
        render(model.animate(avatar, expr[0], camera=orbit[0:1]), orbit[0:1], background=bg, backend=args.backend)
        for t in tqdm(range(n), desc="animate", unit="frame"):
            t1 = time.perf_counter()
            g = model.animate(avatar, expr[t], camera=orbit[t : t + 1])  # camera: view blending, as the server draws
            rgb = render(g, orbit[t : t + 1], background=bg, backend=args.backend).rgb[0]  # [3, H, W]
            times.append(time.perf_counter() - t1)
            frames.append(rgb)
            if gt is not None and t < len(gt):
                scores.append(float(psnr(rgb[None], gt[t][None])))
    fps = 1.0 / statistics.median(times)
    mean_psnr = float(np.mean(scores)) if scores else None

    # video: ground truth | ours, side by side
    video = []
    for t, rgb in enumerate(frames):
        ours = _label(_to_uint8(rgb), "FastGHA")
        row = [_label(_to_uint8(gt[t]), "ground truth"), ours] if gt is not None and t < len(gt) else [ours]
        video.append(np.concatenate(row, axis=1))
    mp4 = out / "demo.mp4"
    import imageio_ffmpeg

    h, w = video[0].shape[:2]
    order, video_fps = video_schedule(len(video))
    writer = imageio_ffmpeg.write_frames(str(mp4), (w, h), fps=video_fps, macro_block_size=1, quality=8)
    writer.send(None)
    for i in order:
        writer.send(np.ascontiguousarray(video[i]))
    writer.close()
    video_s = len(order) / video_fps

    # contact sheet: rows = a few frames (gt | ours); last row = the 4 inputs
    pick = np.linspace(0, n - 1, num=min(6, n)).round().astype(int)
    rows = [video[i] for i in pick]
    inputs = [_label(_to_uint8(img), f"input {i}") for i, img in enumerate(images)]
    size = rows[0].shape[0]
    inputs = [np.asarray(Image.fromarray(x).resize((size, size))) for x in inputs]
    sheet_rows = []
    for i in range(0, len(rows), 2):
        pair = rows[i : i + 2]
        while len(pair) < 2:
            pair.append(np.full_like(rows[0], 255))
        sheet_rows.append(np.concatenate(pair, axis=1))
    width = sheet_rows[0].shape[1]
    inp = np.concatenate(inputs, axis=1)
    pad = np.full((size, max(0, width - inp.shape[1]), 3), 255, np.uint8)
    sheet_rows.append(np.concatenate([inp, pad], axis=1)[:, :width])
    sheet = np.concatenate(sheet_rows, axis=0)
    png = out / "contact_sheet.png"
    iio.imwrite(png, sheet)

    figures = {
        "sample": name,
        "model": model.config.name,
        "num_gaussians": len(avatar),
        "reconstruction_s": recon_s,
        "refine_steps": steps,
        "refine_s": refine_s,
        "fps": fps,
        "psnr": mean_psnr,
        "frames": n,
        "render_size": [int(orbit.width), int(orbit.height)],
        "video": str(mp4),
        "video_seconds": video_s,
        "contact_sheet": str(png),
    }
    print(f"reconstruction: {recon_s:.3f} s   animation: {fps:.1f} FPS (deform + render, median of {n} frames)")
    print(f"PSNR vs ground truth: {mean_psnr:.2f} dB over {len(scores)} frames" if mean_psnr is not None else "PSNR: no ground truth")
    print(f"wrote {mp4} ({video_s:.1f} s: {n} frames forward and back at {video_fps:.1f} fps) and {png}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(figures, indent=2))
    return 0

