"""``fastgha client``: create an avatar on a running server, stream a sequence, save frames + MP4.

The sequence is an expression file, a built-in clip, or a video (``--from-video clip.mp4`` /
``--webcam``): then every frame is tracked (``fastgha_core.tracking.VideoTracker``: ``ict53``
expression + head pose, smoothed) and streamed with the head pose folded into the render camera
(``fastgha_core.tracking.drive``). See docs/tracking.md.
"""

NAME = "client"
HELP = (
    "stream an expression sequence (or expressions and head pose tracked from a video or webcam) from a running server: "
    "create an avatar, save the frames and an MP4, print FPS and latency"
)
QUIET_NATIVE_LOGS = True  # MediaPipe's C++ start-up lines are dropped from stderr (fastgha_core/commands/_stderr.py)


def add_arguments(parser) -> None:
    parser.add_argument("--url", default="http://127.0.0.1:8000", help="server base URL (default http://127.0.0.1:8000)")
    parser.add_argument("--input", required=True, help="request folder: photos (+ cameras.json, + *_mask.png, + head.json and expressions.json of `fastgha track`: "
                        "sent as the tracked head); without cameras.json the server tracks the photos (its 'faces' extra)")
    parser.add_argument(
        "--expressions",
        default=None,
        help="sequence .npy [T, E] or .json (list of vectors or name->weight maps, or {'frames': [...]}); "
        "default: expressions.npy beside the request folder, else a built-in jaw/blink/smile clip",
    )
    parser.add_argument("--orbit", action="store_true", help="swing the camera around the head during the sequence")
    src = parser.add_mutually_exclusive_group()
    src.add_argument(
        "--from-video",
        default=None,
        metavar="CLIP",
        help="drive the avatar from a video: track the ict53 expression and head pose of every frame (needs the 'faces' extra)",
    )
    src.add_argument(
        "--webcam",
        nargs="?",
        const="/dev/video0",
        default=None,
        metavar="DEVICE",
        help="drive the avatar live from a V4L2 webcam (Linux; default device /dev/video0); stop with Ctrl-C or --frames",
    )
    parser.add_argument(
        "--pose-reference",
        choices=("first", "camera"),
        default="first",
        help="video driving: which head pose shows the avatar frontally: the first tracked frame (default) or facing the camera",
    )
    parser.add_argument("--save-track", default=None, metavar="NPZ", help="video driving: save the tracked expressions, poses and cameras (.npz)")
    parser.add_argument("--out", required=True, help="output MP4 path")
    parser.add_argument("--frames-dir", default=None, help="also save every received frame here as JPEG")
    parser.add_argument("--size", type=int, default=256, help="frame width and height (default 256)")
    parser.add_argument("--fps", type=float, default=None, help="frame rate of the MP4 (default: the video's, else 25)")
    parser.add_argument("--frames", type=int, default=None, help="use at most this many frames of the sequence or video")
    parser.add_argument("--api-key", default=None, help="API key for creating avatars (default: $FASTGHA_API_KEY, else the first of $FASTGHA_API_KEYS)")
    parser.add_argument(
        "--in-flight", type=int, default=1, help="unanswered requests at a time: 1 renders every frame, 2 is faster but may drop some (default 1)"
    )
    parser.add_argument("--keep", action="store_true", help="do not delete the avatar afterwards; prints its id and token")


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


def api_key_from(explicit: str | None) -> str | None:
    """The key a client sends: ``--api-key``, else ``$FASTGHA_API_KEY``, else the first key of
    ``$FASTGHA_API_KEYS`` (the server's own variable, when client and server share a shell)."""
    import os

    if explicit:
        return explicit
    if os.environ.get("FASTGHA_API_KEY"):
        return os.environ["FASTGHA_API_KEY"]
    keys = [k.strip() for k in os.environ.get("FASTGHA_API_KEYS", "").split(",") if k.strip()]
    return keys[0] if keys else None


def key_hint(message: str) -> str:
    """``message`` of a refused creation, with how to send a key when the refusal is about one."""
    if "api_key_required" in message or "invalid_api_key" in message:
        return f"{message} (pass --api-key KEY, or set FASTGHA_API_KEY)"
    return message


def unreachable(url: str, error: BaseException | str) -> str:
    """One line for a server that could not be asked its model (``GET /v1/model``) at ``url``, with
    what to do for the usual causes: nothing listening yet (``fastgha serve`` opens its port only
    after its start-up), ``https://`` to the plain-HTTP server, a path such as ``/v1`` in ``--url``."""
    text = str(error)
    if "Connection refused" in text or "Errno 111" in text:
        return (f"cannot reach the server at {url}: {text} (nothing listens there: start one with `fastgha serve`; "
                "it opens its port only after its start-up, 10-40 s, when its log says 'start-up done')")  # fmt: skip
    if url.lower().startswith("https://") and ("SSL" in text or "WRONG_VERSION_NUMBER" in text):
        return (f"cannot reach the server at {url}: {text} (`fastgha serve` speaks plain HTTP: use http://; "
                "TLS belongs to a reverse proxy in front of it, docs/deploy.md)")  # fmt: skip
    if "/v1/model -> HTTP 404" in text:  # the rest is that server's 404 page
        asked = text.split(" -> HTTP 404")[0]
        return f"{url} answers, but not as a FastGHA server: --url is the server's root, http://host:port, without a path such as /v1 ({asked} -> HTTP 404)"
    return f"cannot reach the server at {url}: {text}"


def _load_sequence(path, dim: int, space: str | None = None) -> list:
    """Frames of ``--expressions`` (``.npy`` ``[T, dim]`` or JSON), checked against the server's
    space ``space`` (when this install knows it) before any avatar is created: an unknown name
    fails here, not mid-stream."""
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
    if isinstance(obj, dict):  # {"frames": [...]} (the server's sample route) or `fastgha track`'s expressions.json
        obj = obj.get("frames", obj.get("expressions"))
    if not isinstance(obj, list) or not obj or not all(isinstance(f, (list, dict)) for f in obj):
        raise CLIError(f"--expressions {p}: expected a non-empty list of vectors or name->weight maps (or {{'frames': [...]}}, or `fastgha track`'s expressions.json)")
    for i, f in enumerate(obj):
        if isinstance(f, list) and len(f) != dim:
            raise CLIError(f"--expressions {p}: frame {i} has {len(f)} values, the server's space needs {dim}")
    if space is not None:
        from ..expressions import get_space

        try:
            expr_space = get_space(space)
        except ValueError:  # a space this install does not know: the server checks each frame
            return obj
        for i, f in enumerate(obj):
            try:
                expr_space.parse(f)
            except ValueError as e:
                raise CLIError(f"--expressions {p}: frame {i}: {e}") from None
    return obj


class _VideoDriver:
    """Video frames -> tracked stream requests, with timings.

    A worker thread tracks up to ``ahead`` frames ahead of the stream, so tracking the next frame
    overlaps with the server rendering the current one; ``requests()`` is the generator the
    client pulls. Frames before the first face send nothing; a frame without a face repeats the
    last request.
    """

    def __init__(self, frames, width: int, height: int, reference: str, ahead: int = 2) -> None:
        from ..tracking.drive import DriveConfig, HeadPoseCamera
        from ..tracking.video import VideoTracker

        self.frames = frames  # iterator of (frame [H, W, 3] uint8, timestamp s)
        self.tracker = VideoTracker()
        self.camera = HeadPoseCamera(DriveConfig(width=width, height=height, reference=reference))
        self.ahead = ahead
        self.track_seconds = 0.0
        self.read = self.tracked = self.lost = 0
        self.record: dict[str, list] = {"frame": [], "expression": [], "R": [], "t": [], "w2c": [], "K": [], "detected": [], "rms_px": []}

    def _track(self, index: int, frame, ts: float) -> dict | None:
        import time

        t0 = time.perf_counter()
        self.read += 1
        ft = self.tracker.track(frame, ts)
        req = None
        if ft is not None:
            cam = self.camera.camera_object(ft.R, ft.t)
            req = {"expression": ft.expression.astype("float32").tolist(), "camera": cam}
            self.tracked += 1
            for k, v in (("frame", index), ("expression", ft.expression), ("R", ft.R), ("t", ft.t), ("w2c", cam["w2c"]),
                         ("K", cam["K"]), ("detected", ft.detected), ("rms_px", ft.rms_px)):  # fmt: skip
                self.record[k].append(v)
        else:
            self.lost += 1
        self.track_seconds += time.perf_counter() - t0
        return req

    def requests(self):
        import queue
        import threading

        q: queue.Queue = queue.Queue(maxsize=self.ahead)
        stop = threading.Event()

        def put(item) -> None:
            while not stop.is_set():
                try:
                    q.put(item, timeout=0.1)
                    return
                except queue.Full:
                    continue

        def work() -> None:
            try:
                for index, (frame, ts) in enumerate(self.frames):
                    if stop.is_set():
                        break
                    put(("frame", self._track(index, frame, ts)))
                put(("end", None))
            except BaseException as e:  # handed to the consumer
                put(("error", e))
            finally:
                close = getattr(self.frames, "close", None)
                if close is not None:
                    close()

        worker = threading.Thread(target=work, name="fastgha-video-track", daemon=True)
        worker.start()
        last = None
        try:
            while True:
                kind, item = q.get()
                if kind == "end":
                    return
                if kind == "error":
                    raise item
                last = item if item is not None else last
                if last is not None:
                    yield last
        finally:
            stop.set()
            worker.join(timeout=10.0)

    def save(self, path) -> None:
        import numpy as np

        np.savez(path, **{k: np.asarray(v) for k, v in self.record.items()})


def _open_video_source(args, stop):
    from ..cli import CLIError
    from ..tracking.drive import video_frames, webcam_frames

    try:
        if args.from_video:
            return video_frames(args.from_video, max_frames=args.frames)
        return webcam_frames(args.webcam, max_frames=args.frames, stop=stop)
    except ValueError as e:
        raise CLIError(str(e)) from None


class _ProgressPrinter:
    """Prints the creation job's progress: one line per stage (and per queue position)."""

    def __init__(self) -> None:
        self.last = None

    def __call__(self, st: dict) -> None:
        if st.get("status") == "busy":
            print(f"creating the avatar: the server is busy, retrying in {st['retry_after']:g} s", flush=True)
            return
        key = (st.get("stage"), st.get("queue_position"))
        if key == self.last or st.get("status") == "ready":
            return
        self.last = key
        where = f" (position {st['queue_position']} in the queue)" if st.get("queue_position") else ""
        print(f"creating the avatar: {st.get('stage')}{where}, {100 * float(st.get('progress', 0)):.0f} %", flush=True)


def run(args) -> int:
    import threading
    from pathlib import Path

    import numpy as np

    from client_demo.client import FastGHAClient, StreamError, StreamStats, load_head, load_request_dir, orbit_camera

    from ..cli import CLIError

    if not 16 <= args.size <= 4096:
        raise CLIError(f"--size must be in 16..4096, got {args.size}")
    if not 1 <= args.in_flight <= 16:
        raise CLIError(f"--in-flight must be in 1..16, got {args.in_flight}")
    if args.fps is not None and not 0 < args.fps <= 240:
        raise CLIError(f"--fps must be in (0, 240], got {args.fps}")
    if args.frames is not None and args.frames < 1:
        raise CLIError(f"--frames must be >= 1, got {args.frames}")
    video = bool(args.from_video or args.webcam)
    if video and (args.expressions or args.orbit):
        raise CLIError("--expressions and --orbit cannot be combined with --from-video / --webcam (the video drives expression and pose)")
    if args.save_track and not video:
        raise CLIError("--save-track needs --from-video or --webcam")
    from ._paths import output_dir, output_file

    out = output_file(args.out, "--out")
    if args.save_track:
        output_file(args.save_track, "--save-track")
    if args.frames_dir:
        output_dir(args.frames_dir, "--frames-dir")
    if out.suffix.lower() != ".mp4":
        raise CLIError(f"--out must be an .mp4 path, got {out}")
    import logging

    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per HTTP request is noise here
    images, cams, masks = load_request_dir(args.input)
    try:  # a `fastgha track` folder: its head goes with the cameras (the server reconstructs on it, as `fastgha reconstruct` does)
        head = load_head(args.input, images)
    except ValueError as e:
        raise CLIError(str(e)) from None
    client = FastGHAClient(args.url, api_key=api_key_from(args.api_key))
    try:
        info = client.model_info()
    except Exception as e:
        raise CLIError(unreachable(args.url, e)) from None
    most = info.get("max_images")
    if isinstance(most, int) and len(images) > most:  # before any upload, in the folder's terms (not the multipart's)
        raise CLIError(f"--input {args.input} holds {len(images)} photos; this server takes 1 to {most}: keep the best {most} "
                       "(different angles of the one face) in a folder of their own")  # fmt: skip
    dim = int(info["expression_dim"])
    driver, stop, fps_out = None, threading.Event(), args.fps
    if video:
        if info["expression_space"] != "ict53":
            raise CLIError(f"video driving tracks ict53 expressions, but the server's model uses {info['expression_space']!r}")
        vinfo, frames = _open_video_source(args, stop)
        try:
            driver = _VideoDriver(frames, args.size, args.size, args.pose_reference)
        except ImportError as e:  # FacesUnavailableError names the extra
            raise CLIError(str(e)) from None
        fps_out = fps_out or (vinfo.fps if 0 < vinfo.fps <= 240 else 25.0)
        src = args.from_video or args.webcam
        print(f"driving from {src}: {vinfo.width}x{vinfo.height} at {vinfo.fps:.1f} fps" + ("" if args.from_video else " (Ctrl-C stops)"))
    else:
        if args.expressions:
            seq = _load_sequence(args.expressions, dim, info.get("expression_space"))
        elif (Path(args.input).parent / "expressions.npy").is_file():
            seq = _load_sequence(Path(args.input).parent / "expressions.npy", dim)
        else:
            seq = _builtin_sequence(_BUILTIN_FRAMES)
        if args.frames is not None:
            seq = seq[: args.frames]
    fps_out = fps_out or 25.0

    try:
        if head is not None:
            print(f"sending the tracked head (head.json + expressions.json of {args.input}): the Gaussians go on it")
        avatar = client.create_avatar(images, cams, masks, head=head, progress=_ProgressPrinter(), busy_wait_s=120.0)
    except RuntimeError as e:  # an HTTP error answer (e.g. a wrong API key), as one line
        raise CLIError(key_hint(str(e))) from None
    refined = f", refinement {avatar.refining_ms:.0f} ms" if avatar.refining_ms is not None else ""
    print(f"avatar {avatar.avatar_id}: {avatar.num_gaussians} Gaussians, reconstruction {avatar.reconstruction_ms:.0f} ms{refined} "
          f"(round trip {avatar.round_trip_ms:.0f} ms)")  # fmt: skip
    if avatar.describe():
        print(avatar.describe())  # view blending, expression prior, same-person check (docs/protocol.md)
    if driver is not None:
        requests = driver.requests()
    else:
        n = len(seq)
        requests = []
        for i, expr in enumerate(seq):
            yaw = 30.0 * np.sin(2 * np.pi * i / max(1, n)) if args.orbit else 0.0
            cam = orbit_camera(yaw, 0.0, 1.0, width=args.size, height=args.size) if (args.orbit or i == 0) else None
            requests.append({"expression": expr, "camera": cam})
    stats = StreamStats()
    frames_dir = Path(args.frames_dir) if args.frames_dir else None
    if frames_dir:
        frames_dir.mkdir(parents=True, exist_ok=True)
    restore = None
    if args.webcam:  # Ctrl-C ends the live stream cleanly (the frames so far are still written)
        import signal

        restore = signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        frames = client.stream_sync(avatar, requests, stats=stats, max_in_flight=args.in_flight)
    except ValueError as e:  # e.g. the webcam stopped sending
        raise CLIError(str(e)) from None
    except StreamError as e:  # a typed error or close from the server (code: message), as one line
        raise CLIError(f"the stream failed: {e}") from None
    finally:
        stop.set()
        if restore is not None:
            import signal

            signal.signal(signal.SIGINT, restore)
        if not args.keep:
            client.delete(avatar)
        else:  # the server shows a token once: without it the kept avatar cannot be reached again
            print(f"kept avatar {avatar.avatar_id} on {args.url}, token {avatar.token} "
                  "(shown once: needed to stream, export or delete it)", flush=True)  # fmt: skip
    if driver is not None:
        n = stats.sent
        if args.save_track:
            driver.save(args.save_track)
        if not driver.tracked:
            raise CLIError(f"no face was found in the {driver.read} video frame(s) read")
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
    writer = imageio_ffmpeg.write_frames(str(out), (w, h), fps=fps_out, codec="libx264", macro_block_size=2, quality=7)
    writer.send(None)
    img = first
    for i in range(n):
        if i in by_seq:
            img = by_seq[i].image()
        writer.send(np.ascontiguousarray(img))
    writer.close()
    print(f"{stats.received} frames of {n} requested ({stats.dropped} dropped) at {w}x{h} in {stats.finished - stats.started:.2f} s: "
          f"{stats.fps:.1f} fps, latency p50 {stats.latency_percentile(50):.1f} ms, p95 {stats.latency_percentile(95):.1f} ms")  # fmt: skip
    if driver is not None:
        ms = 1e3 * driver.track_seconds / max(1, driver.read)
        print(f"tracking: {driver.tracked} of {driver.read} video frames tracked ({driver.lost} without a face), "
              f"{ms:.1f} ms per frame ({1e3 / ms if ms > 0 else float('inf'):.1f} FPS alone); "
              f"tracking + streaming end to end: {stats.fps:.1f} FPS")  # fmt: skip
        if args.save_track:
            print(f"wrote the tracked poses and expressions to {args.save_track}")
    print(f"wrote {out}" + (f" and {len(frames)} frames to {frames_dir}" if frames_dir else ""))
    return 0
