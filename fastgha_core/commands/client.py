"""``fastgha client``: create an avatar on a running server, stream a sequence, save frames + MP4."""

NAME = "client"
HELP = "stream an expression sequence from a running server: create an avatar, save the frames and an MP4, print FPS and latency"


def add_arguments(parser) -> None:
    parser.add_argument("--url", default="http://127.0.0.1:8000", help="server base URL (default http://127.0.0.1:8000)")
    parser.add_argument("--input", required=True, help="request folder: photos + cameras.json (+ *_mask.png)")
    parser.add_argument(
        "--expressions",
        default=None,
        help="sequence .npy [T, E] or .json (list of vectors or name->weight maps, or {'frames': [...]}); "
        "default: expressions.npy beside the request folder, else a built-in jaw/blink/smile clip",
    )
    parser.add_argument("--orbit", action="store_true", help="swing the camera around the head during the sequence")
    parser.add_argument("--out", required=True, help="output MP4 path")
    parser.add_argument("--frames-dir", default=None, help="also save every received frame here as JPEG")
    parser.add_argument("--size", type=int, default=256, help="frame width and height (default 256)")
    parser.add_argument("--fps", type=float, default=25.0, help="frame rate of the MP4 (default 25)")
    parser.add_argument("--frames", type=int, default=None, help="use at most this many frames of the sequence")
    parser.add_argument("--api-key", default=None, help="API key for creating avatars (default: $FASTGHA_API_KEY)")
    parser.add_argument(
        "--in-flight", type=int, default=1, help="unanswered requests at a time: 1 renders every frame, 2 is faster but may drop some (default 1)"
    )
    parser.add_argument("--keep", action="store_true", help="do not delete the avatar afterwards")


_BUILTIN_FRAMES = 48


def _builtin_sequence(n: int) -> list[dict]:
    """A short clip as name->weight maps: open the jaw, blink, smile."""
    import math

    out = []
    for i in range(n):
        s = i / max(1, n - 1)
        out.append(
            {
                "jawOpen": 0.8 * math.sin(math.pi * min(1.0, 2 * s)) ** 2,
                "eyeBlink_L": 1.0 if 0.45 < s < 0.55 else 0.0,
                "eyeBlink_R": 1.0 if 0.45 < s < 0.55 else 0.0,
                "mouthSmile_L": 0.9 * max(0.0, math.sin(math.pi * (2 * s - 1))) if s > 0.5 else 0.0,
                "mouthSmile_R": 0.9 * max(0.0, math.sin(math.pi * (2 * s - 1))) if s > 0.5 else 0.0,
            }
        )
    return out


def _load_sequence(path, dim: int) -> list:
    import json
    from pathlib import Path

    import numpy as np

    from ..cli import CLIError

    p = Path(path)
    if not p.is_file():
        raise CLIError(f"--expressions: no such file {p}")
    if p.suffix.lower() == ".npy":
        arr = np.load(p)
        if arr.ndim != 2 or arr.shape[1] != dim:
            raise CLIError(f"--expressions {p}: expected an array [T, {dim}], got shape {list(arr.shape)}")
        return arr.astype(np.float32).tolist()
    try:
        obj = json.loads(p.read_text())
    except ValueError as e:
        raise CLIError(f"--expressions {p} is not valid JSON ({e})") from None
    if isinstance(obj, dict):
        obj = obj.get("frames")
    if not isinstance(obj, list) or not obj or not all(isinstance(f, (list, dict)) for f in obj):
        raise CLIError(f"--expressions {p}: expected a non-empty list of vectors or name->weight maps (or {{'frames': [...]}})")
    for i, f in enumerate(obj):
        if isinstance(f, list) and len(f) != dim:
            raise CLIError(f"--expressions {p}: frame {i} has {len(f)} values, the server's space needs {dim}")
    return obj


def run(args) -> int:
    import os
    from pathlib import Path

    import numpy as np

    from client_demo.client import FastGHAClient, StreamStats, load_request_dir, orbit_camera

    from ..cli import CLIError

    if not 16 <= args.size <= 4096:
        raise CLIError(f"--size must be in 16..4096, got {args.size}")
    if not 1 <= args.in_flight <= 16:
        raise CLIError(f"--in-flight must be in 1..16, got {args.in_flight}")
    if not 0 < args.fps <= 240:
        raise CLIError(f"--fps must be in (0, 240], got {args.fps}")
    out = Path(args.out)
    if out.suffix.lower() != ".mp4":
        raise CLIError(f"--out must be an .mp4 path, got {out}")
    import logging

    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per HTTP request is noise here
    images, cams, masks = load_request_dir(args.input)
    client = FastGHAClient(args.url, api_key=args.api_key or os.environ.get("FASTGHA_API_KEY"))
    try:
        info = client.model_info()
    except Exception as e:
        raise CLIError(f"cannot reach the server at {args.url}: {e}") from None
    dim = int(info["expression_dim"])
    if args.expressions:
        seq = _load_sequence(args.expressions, dim)
    elif (Path(args.input).parent / "expressions.npy").is_file():
        seq = _load_sequence(Path(args.input).parent / "expressions.npy", dim)
    else:
        seq = _builtin_sequence(_BUILTIN_FRAMES)
    if args.frames is not None:
        if args.frames < 1:
            raise CLIError(f"--frames must be >= 1, got {args.frames}")
        seq = seq[: args.frames]
    n = len(seq)

    try:
        avatar = client.create_avatar(images, cams, masks)
    except RuntimeError as e:  # an HTTP error answer (e.g. a wrong API key), as one line
        raise CLIError(str(e)) from None
    print(f"avatar {avatar.avatar_id}: {avatar.num_gaussians} Gaussians, reconstruction {avatar.reconstruction_ms:.0f} ms "
          f"(round trip {avatar.round_trip_ms:.0f} ms)")  # fmt: skip
    requests = []
    for i, expr in enumerate(seq):
        yaw = 30.0 * np.sin(2 * np.pi * i / max(1, n)) if args.orbit else 0.0
        cam = orbit_camera(yaw, 0.0, 1.0, width=args.size, height=args.size) if (args.orbit or i == 0) else None
        requests.append({"expression": expr, "camera": cam})
    stats = StreamStats()
    frames_dir = Path(args.frames_dir) if args.frames_dir else None
    if frames_dir:
        frames_dir.mkdir(parents=True, exist_ok=True)
    try:
        frames = client.stream_sync(avatar, requests, stats=stats, max_in_flight=args.in_flight)
    finally:
        if not args.keep:
            client.delete(avatar)
    if not frames:
        raise CLIError("the server returned no frames")
    if frames_dir:
        for f in frames:
            (frames_dir / f"frame_{f.seq:05d}.jpg").write_bytes(f.jpeg)
    # the MP4 keeps the sequence's timing: a request the server dropped repeats the previous frame
    by_seq = {f.seq: f for f in frames}
    import imageio_ffmpeg

    out.parent.mkdir(parents=True, exist_ok=True)
    first = frames[0].image()
    h, w = first.shape[:2]
    writer = imageio_ffmpeg.write_frames(str(out), (w, h), fps=args.fps, codec="libx264", macro_block_size=2, quality=7)
    writer.send(None)
    img = first
    for i in range(n):
        if i in by_seq:
            img = by_seq[i].image()
        writer.send(np.ascontiguousarray(img))
    writer.close()
    print(f"{stats.received} frames of {n} requested ({stats.dropped} dropped) at {w}x{h} in {stats.finished - stats.started:.2f} s: "
          f"{stats.fps:.1f} fps, latency p50 {stats.latency_percentile(50):.1f} ms, p95 {stats.latency_percentile(95):.1f} ms")  # fmt: skip
    print(f"wrote {out}" + (f" and {len(frames)} frames to {frames_dir}" if frames_dir else ""))
    return 0
