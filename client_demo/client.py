"""A small, copyable Python client for the FastGHA server (``docs/protocol.md``).

Depends only on ``httpx``, ``websockets``, ``numpy`` and ``pillow`` (not on ``fastgha_core``
or ``server``), so it can be copied into an application as one file::

    from client_demo.client import FastGHAClient, orbit_camera

    client = FastGHAClient("http://127.0.0.1:8000", api_key="...")
    avatar = client.create_avatar(["0.jpg", "1.jpg", "2.jpg", "3.jpg"], cameras)   # cameras: list of dicts
    avatar = client.create_avatar(["me.jpg"])   # no cameras: the server tracks the photo (its `faces` extra)
    avatar = client.create_avatar_from_dir("out/me")  # a `fastgha track` folder: photos, cameras, masks, head.json
    avatar = client.create_avatar(paths, progress=lambda st: print(st["stage"], st["progress"]))
    cam = orbit_camera(yaw_deg=20, width=256, height=256)
    frames = client.stream_sync(avatar, [{"expression": {"jawOpen": w}, "camera": cam} for w in (0, .5, 1)])
    frames[0].image()            # uint8 [H, W, 3]
    client.delete(avatar)

Cameras are our JSON camera objects ``{"K": 3x3, "w2c": 4x4, "width", "height"}`` (OpenCV:
x right, y down, z forward; metres; head-centric world with +y up and +z out of the face).

Creation is a job on the server: ``create_avatar`` asks for it with ``Prefer: respond-async``,
gets ``202`` with the avatar's id and token at once, polls ``GET /v1/avatars/{id}/status`` and
hands every status (``stage``, ``progress`` in [0, 1], ``queue_position``) to ``progress``
until the avatar is ready. A server whose creation queue is full answers 429 / 503 with
``Retry-After``: ``ServerBusy`` carries it, and ``busy_wait_s`` retries for that long.

Streaming (``stream`` / ``stream_sync``) keeps at most ``max_in_flight`` requests unanswered.
The default 1 (lock-step) gets every request rendered; 2 (one rendering, one waiting) hides
the round trip and raises throughput, but the server renders latest-wins, so a request that
is still waiting when the next one arrives is dropped and never answered. Dropped requests
are counted in ``StreamStats.dropped`` and the stream goes on.
"""

from __future__ import annotations

import asyncio
import io
import json
import logging
import math
import struct
import time
from collections.abc import AsyncIterator, Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit, urlunsplit

import httpx
import numpy as np
from PIL import Image

log = logging.getLogger(__name__)

__all__ = [
    "FastGHAClient",
    "Avatar",
    "describe_avatar",
    "Frame",
    "StreamStats",
    "StreamError",
    "CreationError",
    "ServerBusy",
    "look_at_camera",
    "orbit_camera",
    "load_request_dir",
    "pack_request",
    "unpack_frame",
]

FRAME_MAGIC = b"FGHA"
REQUEST_MAGIC = b"FGHQ"
_CAM = struct.Struct("<9f16fHH")  # K, w2c, width, height
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


class StreamError(RuntimeError):
    """The server answered a stream request with a typed error, or closed the socket."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


class CreationError(RuntimeError):
    """The server refused a creation or its job failed: ``status`` (HTTP), ``code``, ``message``."""

    def __init__(self, status: int, code: str, message: str, what: str = "POST /v1/avatars") -> None:
        super().__init__(f"{what} -> HTTP {status} {code}: {message}")
        self.status, self.code, self.message = status, code, message


class ServerBusy(CreationError):
    """429 / 503: the server's creation queue is full; ``retry_after`` seconds (its ``Retry-After``)."""

    def __init__(self, status: int, code: str, message: str, retry_after: float) -> None:
        super().__init__(status, code, message)
        self.retry_after = retry_after


@dataclass(frozen=True)
class Avatar:
    """What ``POST /v1/avatars`` returned. Keep the token: the server stores only its hash."""

    avatar_id: str
    token: str
    num_gaussians: int
    reconstruction_ms: float
    expression_space: str
    round_trip_ms: float = 0.0  # client-side time of the create call (upload, queue, reconstruction)
    tracking_ms: float | None = None  # server-side photo tracking, when the photos came without cameras
    refining_ms: float | None = None  # server-side test-time refinement (FASTGHA_REFINE_STEPS), when it ran
    # what the server reports about the avatar's frames and photos (docs/protocol.md, GET /v1/avatars/{id}):
    # "view_blend", "expression_prior", "same_person" (empty from a server that predates them), and "num_images" (photos sent)
    info: dict = field(default_factory=dict, hash=False)

    def describe(self) -> str:
        """One line for people: whether frames are view-blended, the expression prior, what the
        same-person check compared (``docs/protocol.md``); empty when the server reported none."""
        return describe_avatar(self.info)


def describe_avatar(info: dict) -> str:
    """``"view blending on (4 views, tau 20 deg); expression prior on; same person: 4 photos compared
    (largest distance 0.47)"`` from the ``view_blend`` / ``expression_prior`` / ``same_person`` of a
    creation answer or ``GET /v1/avatars/{id}``; parts the server did not report are left out. With
    ``num_images`` too, blended views beyond the photos are named as mirrored views of turned photos
    (``"6 views: 4 photos + 2 mirrored"``)."""
    parts = []
    vb = info.get("view_blend")
    if isinstance(vb, dict):
        if vb.get("active"):
            views, photos = vb.get("views"), info.get("num_images")
            what = f"{views} views"
            if isinstance(views, int) and isinstance(photos, int) and views > photos:  # mirrored views of turned photos
                what += f": {photos} photo{'s' if photos != 1 else ''} + {views - photos} mirrored"
            parts.append(f"view blending on ({what}, tau {vb.get('tau_deg'):g} deg)")
        elif not vb.get("per_view_data"):
            parts.append("view blending off (no per-view data: photos sent with cameras alone)")
        elif int(vb.get("views", 0)) < 2:
            parts.append("view blending off (one input view)")
        else:
            parts.append("view blending off (the server's tau is 0)")
    pr = info.get("expression_prior")
    if isinstance(pr, dict):
        parts.append("expression prior " + ("on" if pr.get("enabled") else "off (the deformation MLP alone)"))
    sp = info.get("same_person")
    if isinstance(sp, dict):
        if not sp.get("checked"):
            parts.append(f"same person: not checked ({sp.get('reason', 'no reason given')})")
        else:
            n, skipped = int(sp.get("photos_compared", 0)), sp.get("photos_without_face") or []
            md = sp.get("max_distance")
            if n < 2:
                txt = "same person: fewer than two photos with a frontal face, nothing compared"
            else:
                txt = f"same person: {n} photos compared" + (f" (largest distance {md:.2f})" if md is not None else "")
                if skipped:
                    txt += f"; no frontal face in {', '.join(skipped)} (not compared)"
            parts.append(txt)
    return "; ".join(parts)


@dataclass
class Frame:
    """One rendered frame: the server's header, the JPEG bytes and the client-side latency."""

    seq: int
    header: dict
    jpeg: bytes
    latency_ms: float  # request sent -> frame received, client clock

    @property
    def width(self) -> int:
        return int(self.header["width"])

    @property
    def height(self) -> int:
        return int(self.header["height"])

    def image(self) -> np.ndarray:
        """The decoded frame, uint8 ``[H, W, 3]``."""
        return np.asarray(Image.open(io.BytesIO(self.jpeg)).convert("RGB"))


@dataclass
class StreamStats:
    """Counters of one ``stream`` call (filled in while it runs)."""

    sent: int = 0
    received: int = 0
    dropped: int = 0  # requests the server dropped (latest wins), never answered
    bytes_received: int = 0
    errors: list[str] = field(default_factory=list)
    started: float = 0.0
    finished: float = 0.0
    latencies_ms: list[float] = field(default_factory=list)

    @property
    def fps(self) -> float:
        dt = self.finished - self.started
        return self.received / dt if dt > 0 else 0.0

    def latency_percentile(self, q: float) -> float:
        return float(np.percentile(self.latencies_ms, q)) if self.latencies_ms else float("nan")


# ---------------------------------------------------------------- cameras
def look_at_camera(
    eye: Sequence[float],
    target: Sequence[float] = (0.0, 0.0, 0.0),
    up: Sequence[float] = (0.0, 1.0, 0.0),
    *,
    fov_deg: float = 20.0,
    width: int = 256,
    height: int = 256,
) -> dict:
    """A camera object at ``eye`` looking at ``target`` (OpenCV; right = down x forward)."""
    eye_v = np.asarray(eye, np.float64)
    z = np.asarray(target, np.float64) - eye_v
    z /= np.linalg.norm(z)  # forward
    x = np.cross(-np.asarray(up, np.float64), z)  # right = down x forward
    n = np.linalg.norm(x)
    if n < 1e-8:
        raise ValueError("look_at_camera: the viewing direction is parallel to `up`; choose another up vector")
    x /= n
    y = np.cross(z, x)  # down
    R = np.stack([x, y, z])  # [3, 3] rows: camera axes in world
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye_v
    f = 0.5 * height / math.tan(math.radians(fov_deg) / 2)
    K = [[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]]
    return {"K": K, "w2c": w2c.tolist(), "width": int(width), "height": int(height)}


def orbit_camera(
    yaw_deg: float = 0.0,
    pitch_deg: float = 0.0,
    radius: float = 1.0,
    *,
    fov_deg: float = 20.0,
    width: int = 256,
    height: int = 256,
    target: Sequence[float] = (0.0, 0.0, 0.0),
) -> dict:
    """A camera on a sphere around ``target``: yaw about +y (positive = towards the subject's left), pitch up."""
    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    t = np.asarray(target, np.float64)
    eye = t + radius * np.array([math.cos(pitch) * math.sin(yaw), math.sin(pitch), math.cos(pitch) * math.cos(yaw)])
    return look_at_camera(eye, t, fov_deg=fov_deg, width=width, height=height)


# ---------------------------------------------------------------- wire format
def pack_request(seq: int, expression: Sequence[float], camera: dict | None = None) -> bytes:
    """The compact binary frame request: ``FGHQ | u32 seq | u16 E | E x f32 | u8 has_camera [| camera]``."""
    expr = np.asarray(expression, dtype="<f4").reshape(-1)
    out = [struct.pack("<4sIH", REQUEST_MAGIC, seq, expr.shape[0]), expr.tobytes()]
    if camera is None:
        out.append(b"\x00")
    else:
        K = np.asarray(camera["K"], np.float64).reshape(-1)
        w2c = np.asarray(camera["w2c"], np.float64)
        if w2c.shape == (3, 4):
            w2c = np.vstack([w2c, [0.0, 0.0, 0.0, 1.0]])
        out += [b"\x01", _CAM.pack(*K.tolist(), *w2c.reshape(-1).tolist(), int(camera["width"]), int(camera["height"]))]
    return b"".join(out)


def unpack_frame(data: bytes) -> tuple[dict, bytes]:
    """``FGHA | u32 L | L bytes JSON header | JPEG`` -> ``(header, jpeg)``; ``ValueError`` if malformed."""
    if len(data) < 8 or data[:4] != FRAME_MAGIC:
        raise ValueError(f"frame messages start with {FRAME_MAGIC!r}, got {bytes(data[:4])!r}")
    (n,) = struct.unpack_from("<I", data, 4)
    if 8 + n > len(data):
        raise ValueError(f"frame header length {n} exceeds the message ({len(data)} bytes)")
    return json.loads(bytes(data[8 : 8 + n]).decode("utf-8")), bytes(data[8 + n :])


# ---------------------------------------------------------------- request folders
def load_request_dir(folder: str | Path) -> tuple[list[Path], list[dict] | None, list[Path] | None]:
    """``(image paths, camera objects | None, mask paths | None)`` of a request folder.

    Images are the JPEG/PNG files sorted by name, ``cameras.json`` holds one camera object per
    image in the same order, and masks are ``<stem>_mask.png`` beside them or ``masks/<stem>.png``.
    Without ``cameras.json`` the cameras are None: the server then tracks the photos (its
    ``faces`` extra), as ``fastgha track`` would.
    """
    folder = Path(folder)
    if folder.is_file():
        raise ValueError(f"request folder {folder} is a file; expected a folder of photos (+ cameras.json): put the photo in one")
    if not folder.is_dir():
        raise ValueError(f"request folder {folder} does not exist")
    cam_file = folder / "cameras.json"
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.stem.endswith("_mask"))
    if not images:
        raise ValueError(f"request folder {folder} has no .jpg/.jpeg/.png photos")
    try:
        cams = json.loads(cam_file.read_text()) if cam_file.is_file() else None
    except json.JSONDecodeError as e:
        raise ValueError(f"{cam_file} does not parse as JSON: {e}") from None
    if isinstance(cams, dict) and "cameras" in cams:
        cams = cams["cameras"]
    if cams is not None and (not isinstance(cams, list) or len(cams) != len(images)):
        n = len(cams) if isinstance(cams, list) else type(cams).__name__
        shown = ", ".join(p.name for p in images[:8]) + (", ..." if len(images) > 8 else "")
        raise ValueError(f"request folder {folder}: {len(images)} images ({shown}) but cameras.json holds {n} cameras, one per image in file-name order")
    masks = []
    for p in images:
        cands = [folder / f"{p.stem}_mask.png", folder / "masks" / f"{p.stem}.png"]
        masks.append(next((c for c in cands if c.is_file()), None))
    if all(m is None for m in masks):
        return images, cams, None
    if any(m is None for m in masks):
        raise ValueError(f"request folder {folder}: some images have masks and some do not; give none or one per image")
    return images, cams, masks  # type: ignore[return-value]


def load_head(folder: str | Path, images: Sequence[Path]) -> dict | None:
    """The ``head`` part of a tracked request folder, or None when it has no ``head.json``.

    ``fastgha track`` writes ``head.json`` (``{"model": "ict_facekit", "identity": [...], "frames":
    {crop file name: [left, top, right, bottom]}}``) and ``expressions.json`` (each crop's ``ict53``
    expression, by file name); the server takes both as one object, head.json's with
    ``"expressions"``: one list of 53 weights per image of ``images``, in their order, and ``"frames"``
    likewise (``docs/protocol.md``, the ``head`` part). ValueError when head.json comes without
    cameras.json or without an expression for every image.
    """
    folder = Path(folder)
    head_file = folder / "head.json"
    if not head_file.is_file():
        return None
    if not (folder / "cameras.json").is_file():
        raise ValueError(f"request folder {folder}: head.json needs the cameras.json it was tracked with (both are written by `fastgha track`)")
    head = json.loads(head_file.read_text())
    expr_file = folder / "expressions.json"
    if not expr_file.is_file():
        raise ValueError(f"request folder {folder}: head.json needs expressions.json beside it (both are written by `fastgha track`)")
    tracked = json.loads(expr_file.read_text())
    by_name = dict(zip(tracked.get("images", []), tracked.get("expressions", []))) if isinstance(tracked, dict) else {}
    missing = [Path(p).name for p in images if Path(p).name not in by_name]
    if not isinstance(head, dict) or missing:
        why = f"no tracked expression for {missing}" if missing else "head.json is not a JSON object"
        raise ValueError(f"request folder {folder}: {why} (expressions.json and head.json of `fastgha track` go with its crops)")
    part = {**head, "expressions": [by_name[Path(p).name] for p in images]}
    frames = head.get("frames")
    if isinstance(frames, dict):  # head.json's by crop file name -> one per image, in their order (none when one is missing)
        names = [Path(p).name for p in images]
        missing = [n for n in names if n not in frames]
        if not missing:
            part["frames"] = [frames[n] for n in names]
        else:  # a photo added after tracking: its padding is unknown, so none is sent
            log.warning("request folder %s: head.json's frames have no entry for %s; sending none (the crops' padding reads as background)", folder, ", ".join(missing[:4]))
            part.pop("frames")
    return part


def _as_bytes(item: Any) -> tuple[bytes, str]:
    """(encoded bytes, content type) of a path, raw bytes, a PIL image or a uint8 [H, W, 3|4] array."""
    if isinstance(item, (str, Path)):
        p = Path(item)
        return p.read_bytes(), "image/png" if p.suffix.lower() == ".png" else "image/jpeg"
    if isinstance(item, (bytes, bytearray)):
        return bytes(item), "image/png" if bytes(item[:4]) == b"\x89PNG" else "image/jpeg"
    if isinstance(item, np.ndarray):
        item = Image.fromarray(item)
    if isinstance(item, Image.Image):
        buf = io.BytesIO()
        item.save(buf, format="PNG")
        return buf.getvalue(), "image/png"
    raise ValueError(f"an image must be a path, bytes, a PIL image or a uint8 array, got {type(item).__name__}")


def _upload_name(item: Any, index: int, ctype: str, suffix: str = "") -> str:
    """The filename sent with an upload: a path's own name, else ``photo<N><suffix>.<ext>`` (1-based),
    so that the server's error messages name the file the caller knows."""
    if isinstance(item, (str, Path)):
        return Path(item).name
    return f"photo{index + 1}{suffix}.{ctype.split('/')[1]}"


def _ws_url(base: str, path: str) -> str:
    parts = urlsplit(base)
    scheme = {"http": "ws", "https": "wss", "ws": "ws", "wss": "wss"}.get(parts.scheme)
    if scheme is None:
        raise ValueError(f"server URL must start with http://, https://, ws:// or wss://, got {base!r}")
    return urlunsplit((scheme, parts.netloc, parts.path.rstrip("/") + path, "", ""))


# ---------------------------------------------------------------- the client
class FastGHAClient:
    """HTTP + WebSocket client of one FastGHA server.

    Args:
        url: server base URL, e.g. ``http://127.0.0.1:8000``.
        api_key: key for creating avatars (``X-API-Key``) when the server requires one.
        timeout: HTTP timeout in seconds (reconstruction of a big model can take a while).
    """

    def __init__(self, url: str, api_key: str | None = None, timeout: float = 120.0) -> None:
        parts = urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.netloc:
            raise ValueError(f"server URL must look like http://host:port, got {url!r}")
        self.url = url.rstrip("/")
        self.api_key = api_key
        self.timeout = timeout

    # ------------------------------------------------------------ HTTP
    def _check(self, r: httpx.Response) -> httpx.Response:
        if r.status_code >= 400:
            try:
                err = r.json()["error"]
                msg = f"{err['code']}: {err['message']}"
            except Exception:  # not the server's JSON error (a proxy's or another server's page): one line of it
                msg = " ".join(r.text[:200].split())
            raise RuntimeError(f"{r.request.method} {r.request.url.path} -> HTTP {r.status_code} {msg}")
        return r

    def _auth(self, avatar: Avatar) -> dict:
        return {"Authorization": f"Bearer {avatar.token}"}

    def health(self) -> dict:
        return self._check(httpx.get(self.url + "/healthz", timeout=self.timeout)).json()

    def model_info(self) -> dict:
        """``GET /v1/model``: name, expression space and names, sizes, device."""
        return self._check(httpx.get(self.url + "/v1/model", timeout=self.timeout)).json()

    def _error_of(self, r: httpx.Response) -> CreationError:
        try:
            err = r.json()["error"]
            code, msg = str(err["code"]), str(err["message"])
        except Exception:
            code, msg = "http_error", " ".join(r.text[:200].split())  # one line of a page that is not ours
        if r.status_code in (429, 503):
            try:
                retry = float(r.headers.get("retry-after", "1"))
            except ValueError:
                retry = 1.0
            return ServerBusy(r.status_code, code, msg, retry)
        return CreationError(r.status_code, code, msg, f"{r.request.method} {r.request.url.path}")

    def create_avatar(
        self,
        images: Sequence[Any],
        cameras: Sequence[dict] | None = None,
        masks: Sequence[Any] | None = None,
        *,
        head: dict | None = None,
        progress: Callable[[dict], None] | None = None,
        busy_wait_s: float = 0.0,
        poll_s: float = 0.25,
    ) -> Avatar:
        """Reconstruct an avatar from 1-8 photos (paths, bytes, PIL images or uint8 arrays) and their cameras.

        Without ``cameras`` the server finds the face in each photo and estimates them (it needs its
        ``faces`` extra, and answers ``cameras_required`` otherwise). Files are sent under their own
        names (``photo<N>.png`` for arrays and bytes), which the server's error messages use.

        Args:
            head: the tracked head of ``fastgha track`` (``load_head``), sent with ``cameras``: the server
                then puts every pixel's Gaussian on it, as ``fastgha reconstruct`` does with head.json.
            progress: called with every status of the creation job (``status`` queued / running /
                ready, ``stage``, ``progress`` in [0, 1], ``queue_position``).
            busy_wait_s: when the server's queue is full (429 / 503), retry after its ``Retry-After``
                for up to this many seconds; 0 raises ``ServerBusy`` at once.
            poll_s: seconds between status polls.
        Raises:
            ServerBusy: the queue stayed full. CreationError: the request was refused or the job failed.
        """
        if cameras is not None and len(images) != len(cameras):
            raise ValueError(f"need one camera per image, got {len(images)} images and {len(cameras)} cameras")
        if head is not None and cameras is None:
            raise ValueError("a head needs the cameras it was tracked with (cameras.json of the same `fastgha track` folder)")
        if masks is not None and len(masks) != len(images):
            raise ValueError(f"need none or one mask per image, got {len(images)} images and {len(masks)} masks")
        files = []
        for i, img in enumerate(images):
            data, ctype = _as_bytes(img)
            files.append(("images", (_upload_name(img, i, ctype), data, ctype)))
        for i, m in enumerate(masks or []):
            data, ctype = _as_bytes(m)
            files.append(("masks", (_upload_name(m, i, ctype, "_mask"), data, ctype)))
        headers = {"Prefer": "respond-async", **({"X-API-Key": self.api_key} if self.api_key else {})}
        data = {"cameras": json.dumps(list(cameras))} if cameras is not None else {}
        if head is not None:
            data["head"] = json.dumps(head)
        t0 = time.perf_counter()
        deadline = time.monotonic() + busy_wait_s
        while True:
            r = httpx.post(self.url + "/v1/avatars", files=files, data=data, headers=headers, timeout=self.timeout)
            if r.status_code < 400:
                break
            err = self._error_of(r)
            if isinstance(err, ServerBusy) and time.monotonic() + err.retry_after <= deadline:
                if progress is not None:
                    progress({"status": "busy", "stage": "queued", "progress": 0.0, "queue_position": None, "retry_after": err.retry_after})
                time.sleep(err.retry_after)
                continue
            raise err
        d = r.json()
        if r.status_code == 202:  # a job: poll its status until the avatar is ready
            token, aid = d["token"], d["avatar_id"]
            auth = {"Authorization": f"Bearer {token}"}
            while True:
                if progress is not None:
                    progress({k: v for k, v in d.items() if k != "token"})
                if d["status"] == "failed":
                    e = d.get("error") or {}
                    raise CreationError(int(e.get("status", 500)), e.get("code", "failed"), e.get("message", ""), "creating the avatar")
                if d["status"] == "ready":
                    d = {**d["avatar"], "token": token}
                    break
                time.sleep(poll_s)
                r = httpx.get(f"{self.url}/v1/avatars/{aid}/status", headers=auth, timeout=self.timeout)
                if r.status_code >= 400:
                    raise self._error_of(r)
                d = r.json()
        rt = 1e3 * (time.perf_counter() - t0)
        tracking, refining = d.get("tracking_ms"), d.get("refining_ms")
        return Avatar(
            d["avatar_id"], d["token"], int(d["num_gaussians"]), float(d["reconstruction_ms"]), d["expression_space"], rt,
            float(tracking) if tracking is not None else None,
            float(refining) if refining is not None else None,
            {"num_images": len(images), **{k: d[k] for k in ("view_blend", "expression_prior", "same_person", "num_images") if k in d}},
        )

    def create_avatar_from_dir(self, folder: str | Path, **kw: Any) -> Avatar:
        """``create_avatar`` of a request folder (``load_request_dir``); ``kw`` as ``create_avatar``'s."""
        images, cams, masks = load_request_dir(folder)
        kw.setdefault("head", load_head(folder, images))
        return self.create_avatar(images, cams, masks, **kw)

    def avatar_info(self, avatar: Avatar) -> dict:
        return self._check(httpx.get(f"{self.url}/v1/avatars/{avatar.avatar_id}", headers=self._auth(avatar), timeout=self.timeout)).json()

    def download_ply(self, avatar: Avatar) -> bytes:
        """The canonical Gaussians as a standard 3DGS PLY file."""
        r = httpx.get(f"{self.url}/v1/avatars/{avatar.avatar_id}/ply", headers=self._auth(avatar), timeout=self.timeout)
        return self._check(r).content

    def delete(self, avatar: Avatar) -> None:
        self._check(httpx.delete(f"{self.url}/v1/avatars/{avatar.avatar_id}", headers=self._auth(avatar), timeout=self.timeout))

    # ------------------------------------------------------------ WebSocket
    def stream_url(self, avatar: Avatar) -> str:
        return _ws_url(self.url, f"/v1/avatars/{avatar.avatar_id}/stream")

    def connect(self, avatar: Avatar, open_timeout: float = 30.0):
        """An async ``websockets`` connection to the avatar's stream (use ``async with``); token in the header."""
        from websockets.asyncio.client import connect

        return connect(
            self.stream_url(avatar), additional_headers=self._auth(avatar), open_timeout=open_timeout, max_size=64 * 1024 * 1024
        )

    async def stream(
        self,
        avatar: Avatar,
        requests: Iterable[dict],
        *,
        max_in_flight: int = 1,
        options: dict | None = None,
        stats: StreamStats | None = None,
        frame_timeout: float = 60.0,
    ) -> AsyncIterator[Frame]:
        """Send ``requests`` and yield the frames answering them, in order.

        Each request is ``{"expression": [E] | {name: weight}, "camera": camera object (optional, sticky)}``.
        Vectors go in the compact binary form, name maps as JSON. At most ``max_in_flight``
        requests are unanswered at a time; dropped ones (latest wins) are counted in ``stats``.
        ``options`` (``jpeg_quality``, ``max_size``) are sent first.
        """
        if max_in_flight < 1:
            raise ValueError(f"max_in_flight must be >= 1, got {max_in_flight}")
        st = stats if stats is not None else StreamStats()
        it = iter(requests)
        sent_at: dict[int, float] = {}
        async with self.connect(avatar) as ws:
            ready = json.loads(await asyncio.wait_for(ws.recv(), frame_timeout))
            while ready.get("type") == "progress":  # opened before the avatar was ready: creation progress
                ready = json.loads(await asyncio.wait_for(ws.recv(), frame_timeout))
            if ready.get("type") != "ready":
                raise StreamError(ready.get("code", "unexpected_message"), str(ready.get("message", ready)))
            if options:
                await ws.send(json.dumps({"type": "options", **options}))
            st.started = time.perf_counter()
            seq, exhausted = 0, False
            try:
                while True:
                    while not exhausted and len(sent_at) < max_in_flight:
                        req = next(it, None)
                        if req is None:
                            exhausted = True
                            break
                        expr = req.get("expression", [])
                        if isinstance(expr, dict):
                            msg: str | bytes = json.dumps({"seq": seq, "expression": expr, **({"camera": req["camera"]} if req.get("camera") else {})})
                        else:
                            msg = pack_request(seq, expr, req.get("camera"))
                        sent_at[seq] = time.perf_counter()
                        await ws.send(msg)
                        st.sent += 1
                        seq += 1
                    if not sent_at:
                        break
                    msg = await asyncio.wait_for(ws.recv(), frame_timeout)
                    now = time.perf_counter()
                    if isinstance(msg, str):
                        obj = json.loads(msg)
                        if obj.get("type") == "error":
                            st.errors.append(f"{obj.get('code')}: {obj.get('message')}")
                            if obj.get("code") not in ("rate_limited",):
                                raise StreamError(obj.get("code", "error"), obj.get("message", ""))
                        continue
                    header, jpeg = unpack_frame(msg)
                    fseq = int(header["seq"])
                    for s in [s for s in sent_at if s < fseq]:  # older requests were dropped by the server
                        del sent_at[s]
                        st.dropped += 1
                    t_sent = sent_at.pop(fseq, now)
                    st.received += 1
                    st.bytes_received += len(msg)
                    lat = 1e3 * (now - t_sent)
                    st.latencies_ms.append(lat)
                    st.finished = now
                    yield Frame(fseq, header, jpeg, lat)
            finally:
                st.finished = st.finished or time.perf_counter()

    def stream_sync(self, avatar: Avatar, requests: Iterable[dict], **kw: Any) -> list[Frame]:
        """``stream`` run to completion in a fresh event loop: the list of frames received."""

        async def collect() -> list[Frame]:
            return [f async for f in self.stream(avatar, requests, **kw)]

        return asyncio.run(collect())
