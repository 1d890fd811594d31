"""``fastgha animate``: render an avatar under a sequence of expressions to a video or PNG frames."""

NAME = "animate"
HELP = "animate an avatar with an expression sequence and write a video (mp4) or a folder of PNG frames"


def add_arguments(parser) -> None:
    parser.add_argument("--avatar", required=True, help="avatar file written by `fastgha reconstruct`")
    parser.add_argument("--expressions", required=True, help="expression sequence: .npy [T, E] or .json (list of vectors or name->weight maps, or {'frames': [...]} or `fastgha track`'s expressions.json)")
    parser.add_argument("--cameras", default="orbit", help="camera path; default 'orbit': a left-right swing around the head at --radius and --fov; "
                        "or a cameras JSON file (one camera, or one per frame, cycled; a non-square camera keeps its aspect, padded to the square --size frame)")
    parser.add_argument("--out", required=True, help="output .mp4 (imageio-ffmpeg) or a folder for PNG frames")
    parser.add_argument("--model", default=None, help="model for the deformation MLP (default: the avatar's model name)")
    parser.add_argument("--size", type=int, default=256, help="output width and height in pixels (default 256)")
    parser.add_argument("--fps", type=float, default=25.0, help="frames per second of the video (default 25)")
    parser.add_argument("--radius", type=float, default=1.0, help="orbit camera distance in metres (default 1.0)")
    parser.add_argument("--fov", type=float, default=20.0, help="orbit vertical field of view in degrees (default 20)")
    parser.add_argument(
        "--view-blend-tau-deg", type=float, default=None, metavar="DEG",
        help="avatars with per-view data (built on a tracked head): weight each input view's Gaussians by "
        "exp(-angle difference / DEG); 0 = off; default: the model's gaussians.view_blend_tau_deg (20); at most 360",
    )
    parser.add_argument("--backend", default="auto", help="render backend (default auto)")
    parser.add_argument("--device", default="cpu", help="torch device (default: cpu)")


def load_expressions(path, space):
    """``[T, E]`` codes from a .npy or .json file, validated by the expression space."""
    import json
    from pathlib import Path

    import numpy as np
    import torch

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"expressions file {str(path)!r} does not exist")
    if path.suffix.lower() == ".npy":
        arr = np.load(path)
        if arr.ndim == 1:
            arr = arr[None]
        if arr.ndim != 2:
            raise ValueError(f"expressions file {str(path)!r}: expected an array [T, {space.dim}], got shape {list(arr.shape)}")
        return _parse_frames(space, list(torch.from_numpy(np.asarray(arr, dtype=np.float32))), path)
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"expressions file {str(path)!r} does not parse as JSON: {e}") from None
        if isinstance(data, dict):  # `fastgha track`'s expressions.json, or the server's sample {"frames": ...}
            key = next((k for k in ("expressions", "frames") if k in data), None)
            if key is None:
                raise ValueError(
                    f"expressions file {str(path)!r}: expected a list of codes, or an object with 'expressions' or 'frames', "
                    f"got an object with keys {sorted(data)[:8]}"
                )
            data = data[key]
        if not isinstance(data, list) or not data:
            raise ValueError(f"expressions JSON must be a non-empty list of codes, got {type(data).__name__}")
        return _parse_frames(space, data, path)
    raise ValueError(f"expressions must be a .npy or .json file, got {path.name!r}")


def _parse_frames(space, frames: list, path):
    """``[T, E]`` codes of ``frames`` (vectors or name->weight maps); a bad one is named by its index
    (``expressions file 'seq.json': frame 7: ...``), as ``fastgha client`` does."""
    import torch

    if not len(frames):
        raise ValueError(f"expressions file {str(path)!r} holds no frames")
    out = []
    for i, frame in enumerate(frames):
        try:
            out.append(space.parse(frame))
        except ValueError as e:
            raise ValueError(f"expressions file {str(path)!r}: frame {i}: {e}") from None
    return torch.stack(out)


def frame_cameras(spec: str, num_frames: int, size: int, radius: float, fov: float):
    """One camera per frame, each a ``Cameras`` of size ``size x size``."""
    from pathlib import Path

    from ..cameras import cameras_from_json, orbit_cameras

    if spec == "orbit":
        cams = orbit_cameras(num_frames, radius=radius, fov_deg=fov, width=size, height=size)
        return [cams[i : i + 1] for i in range(num_frames)]
    path = Path(spec)
    if not path.is_file():
        raise ValueError(f"--cameras must be 'orbit' or a cameras JSON file, got {spec!r}")
    cams = [_fit_square(c, size) for c in cameras_from_json(path.read_text())]
    return [cams[i % len(cams)] for i in range(num_frames)]


def _fit_square(cam, size: int):
    """``cam`` scaled uniformly so that its longer side is ``size``, then padded to a ``size`` x
    ``size`` frame (the video's): the view keeps its aspect instead of being stretched square."""
    w, h = int(cam.width), int(cam.height)
    s = size / max(w, h)
    sw, sh = max(1, round(w * s)), max(1, round(h * s))
    return cam.resize(sw, sh).crop(-((size - sw) // 2), -((size - sh) // 2), size, size)


def blend_summary(model, avatar) -> str:
    """How the frames drew the input views (``model/viewblend.py``): a few words for the summary line."""
    tau = float(model.config.gaussians.view_blend_tau_deg)
    if avatar.view_blend is None:
        return "views unweighted (no per-view data in the avatar file: written before view blending, or built without a tracked head)"
    if tau <= 0:
        return "views unweighted (tau 0: --view-blend-tau-deg 0, or the model's gaussians.view_blend_tau_deg is 0)"
    if avatar.view_blend.directions.shape[0] == 1:
        return "one input view"
    return f"views blended by angle (tau {tau:g} deg)"


_VIDEO_SUFFIXES = (".mp4", ".mkv", ".mov", ".webm")
# file types a user may ask for that we do not write: refused rather than made into a folder of PNGs
_NOT_A_FOLDER = (".gif", ".avi", ".wmv", ".flv", ".mpg", ".mpeg", ".m4v", ".png", ".jpg", ".jpeg", ".webp", ".apng", ".bmp", ".tif", ".tiff")


def run(args) -> int:
    import time
    from pathlib import Path

    import numpy as np
    from tqdm import tqdm

    from ..constants import BACKGROUND_RGB
    from ..model.avatar import CanonicalAvatar
    from ..model.fastgha import load_model
    from . import check_model_has_weights, loading, note_first_compilation
    from ..render import render

    if not 16 <= args.size <= 4096:
        raise ValueError(f"--size must be in 16..4096 pixels (as fastgha client's), got {args.size}")
    if args.fps <= 0:
        raise ValueError(f"--fps must be positive, got {args.fps}")
    if not args.radius > 0:
        raise ValueError(f"--radius must be > 0 metres, got {args.radius}")
    if not 0 < args.fov < 180:
        raise ValueError(f"--fov must be in (0, 180) degrees, got {args.fov}")
    from . import view_blend_tau_problem

    problem = None if args.view_blend_tau_deg is None else view_blend_tau_problem(args.view_blend_tau_deg)
    if problem:
        raise ValueError(f"--view-blend-tau-deg: {problem}")
    from ._paths import output_dir, output_file

    out = Path(args.out)
    (output_file if out.suffix.lower() in _VIDEO_SUFFIXES else output_dir)(out, "--out")
    if out.suffix.lower() in _NOT_A_FOLDER and not out.is_dir():
        raise ValueError(
            f"--out must be a video file ({', '.join(_VIDEO_SUFFIXES)}) or a folder for PNG frames, got {str(out)!r} "
            f"({out.suffix} files are not written; a folder of that name would be made)"
        )
    avatar = CanonicalAvatar.load(args.avatar)
    from ..cli import check_device

    check_device(args.device)
    check_model_has_weights(args.model or avatar.model_name)
    loading(args.model or avatar.model_name)
    note_first_compilation(args.device)
    model = load_model(args.model or avatar.model_name, device=args.device)
    if (model.config.name, model.config.expression_space) != (avatar.model_name, avatar.expression_space):
        raise ValueError(  # as the server's avatar_model_mismatch: the MLP reads the reconstructing model's features
            f"--model {args.model!r} is model {model.config.name!r} ({model.config.expression_space}), but {args.avatar} was "
            f"reconstructed by model {avatar.model_name!r} ({avatar.expression_space}), whose deformation it needs: "
            "animate it with that model (without --model for a shipped one)"
        )
    if args.view_blend_tau_deg is not None:  # as the server's FASTGHA_VIEW_BLEND_TAU_DEG
        model.config.gaussians.view_blend_tau_deg = float(args.view_blend_tau_deg)
    codes = load_expressions(args.expressions, model.expression_space)  # [T, E]
    cams = frame_cameras(args.cameras, len(codes), args.size, args.radius, args.fov)

    video = out.suffix.lower() in _VIDEO_SUFFIXES
    writer = None
    if video:
        import imageio_ffmpeg

        out.parent.mkdir(parents=True, exist_ok=True)
        writer = imageio_ffmpeg.write_frames(str(out), (args.size, args.size), fps=args.fps, macro_block_size=1, quality=8)
        writer.send(None)
    else:
        from PIL import Image

        out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    try:
        for i in tqdm(range(len(codes)), desc="animate", unit="frame"):
            cam = cams[i].to(avatar.gaussians.device)
            g = model.animate(avatar, codes[i], camera=cam)  # camera: view blending, as the server draws (model/viewblend.py)
            rgb = render(g, cam, background=BACKGROUND_RGB, backend=args.backend).rgb[0]  # [3, S, S]
            frame = (rgb.clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)  # [S, S, 3]
            if writer is not None:
                writer.send(np.ascontiguousarray(frame))
            else:
                Image.fromarray(frame).save(out / f"frame_{i:05d}.png")
    finally:
        if writer is not None:
            writer.close()
    dt = time.perf_counter() - t0
    print(f"rendered {len(codes)} frame{'s' if len(codes) != 1 else ''} at {args.size}^2 in {dt:.2f} s ({len(codes) / max(dt, 1e-9):.1f} fps), {blend_summary(model, avatar)} -> {out}")
    return 0
