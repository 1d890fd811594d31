"""Avatar creation as a job: a bounded queue, progress by stages, memory bounded in flight.

``POST /v1/avatars`` hands a :class:`CreationRequest` (the uploaded bytes, checked from their
headers only) to the app's :class:`JobQueue`. The queue runs at most
``FASTGHA_MAX_CONCURRENT_RECONSTRUCTIONS`` jobs at once in its own threads; each job decodes the
photos (downscaled while decoding), tracks them when they came without cameras, reconstructs,
runs the optional extra stages (test-time refinement) and saves the avatar. Every step reports
progress through ``progress(stage, fraction)`` with the stages of :data:`STAGES`.

Memory: nothing is decoded before a job starts, so the decoded pixels in flight are those of
the running jobs only, and a photo is downscaled to ``FASTGHA_DECODE_MAX_SIDE`` while it is
decoded (JPEG: DCT scaling, never the full raster; PNG: one full raster at a time, freed before
the next photo). Admission is decided before the request body is read: a client over
``FASTGHA_MAX_JOBS_PER_CLIENT`` gets 429, a full queue (``FASTGHA_MAX_QUEUED_JOBS`` waiting, or
``FASTGHA_MAX_QUEUED_UPLOAD_BYTES`` of uploads held) gets 503, both with ``Retry-After``.

Threads: the job threads run under Linux's ``SCHED_IDLE`` policy (``FASTGHA_CREATION_SCHED_IDLE``;
else at the nice value ``FASTGHA_CREATION_NICE``; on Linux both are the thread's own, and the
threads it starts, such as torch's OpenMP team, inherit them), so the render threads of open
streams keep the CPU while an avatar is being created (``_lower_priority``). The price: while
streams keep every core busy, creations advance only in the gaps between frames.

Durability: a job reports ``ready`` only after ``AvatarStore.put`` has fsynced the avatar and
its metadata; a job that has not reported ``ready`` when the process dies is lost (the client
creates it again), an avatar that has is never lost.

The HTTP and WebSocket contracts are in ``docs/protocol.md`` ("Creation jobs").
"""

from __future__ import annotations

import asyncio
import collections
import io
import json
import logging
import math
import os
import re
import threading
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, AsyncIterator, Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from fastgha_core import images as _shared  # the one decoder of every ingest path

from . import auth
from .errors import ApiError

__all__ = [
    "STAGES",
    "CreationRequest",
    "CreationState",
    "ExtraStage",
    "Job",
    "JobQueue",
    "Photo",
    "decode_photo",
    "extra_stages_for",
    "probe_request",
    "safe_filename",
]

log = logging.getLogger(__name__)

#: Stages reported by ``progress(stage, fraction)``, in order (contract 3 of the project).
STAGES = ("queued", "decoding", "tracking", "reconstructing", "refining", "saving", "ready", "failed")
_WEIGHTS = {"decoding": 0.05, "tracking": 0.3, "reconstructing": 0.45, "saving": 0.05}
_EXTRA_WEIGHT = 0.3  # each extra stage (refining)
_FORMATS = ("JPEG", "PNG")
_REPR = re.compile(r"<[^<>]*\bat 0x[0-9a-fA-F]+>")

Progress = Callable[[str, float], None]


# ---------------------------------------------------------------- names and decoding
def safe_filename(name: str | None, ordinal: int, what: str = "image") -> str:
    """The name an upload is called by in messages: its filename without folders, at most 80
    characters, printable only; ``"unnamed image 3"`` (1-based) when the part carries none."""
    if name:
        base = re.split(r"[\\/]", str(name))[-1]
        base = "".join(ch if ch.isprintable() else "?" for ch in base).strip()
        if base:
            return base if len(base) <= 80 else base[:77] + "..."
    return f"unnamed {what} {ordinal + 1}"


@dataclass
class Photo:
    """One uploaded file as received: its display name and bytes; ``size`` once probed."""

    name: str
    data: bytes
    size: tuple[int, int] = (0, 0)  # (width, height) of the image shown upright (EXIF applied), from the header
    orientation: int = 1  # its EXIF orientation (1 = none), from the header

    def described(self) -> str:
        """``"512x600"``, and for a photo stored sideways how it is stored, for size messages."""
        w, h = self.size
        if self.orientation not in (5, 6, 7, 8):
            return f"{w}x{h}"
        return f"{w}x{h} upright (stored as {h}x{w} with EXIF orientation {self.orientation}, which the server applies)"


def _orientation(im) -> int:
    """The EXIF orientation tag of a Pillow image (1 when absent or unreadable: the decoder ignores it too)."""
    try:
        return int(im.getexif().get(0x0112, 1))
    except Exception:
        return 1


def _upright_size(im) -> tuple[int, int]:
    """``(width, height)`` of the image as decoded: the shared decoder applies EXIF orientation,
    so cameras describe the upright image (orientations 5-8 swap the sides); read from the header."""
    w, h = im.size
    return (h, w) if _orientation(im) in (5, 6, 7, 8) else (w, h)


def _open_checked(data: bytes, name: str, max_pixels: int):
    """Pillow image with only the header read; 400/413 ``ApiError`` naming ``name``."""
    from PIL import Image

    if not data:
        raise ApiError(400, "invalid_image", f"{name} is empty")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            im = Image.open(io.BytesIO(data), formats=_FORMATS)
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as e:
        raise ApiError(413, "image_too_large", _shared.too_large_error(name, e, max_pixels).message) from None
    except Exception as e:  # Pillow raises many types; never print its object reprs
        raise ApiError(400, "invalid_image", f"{name} is not a readable JPEG or PNG image{_why(e)}") from None
    w, h = im.size
    if w * h > max_pixels:
        raise ApiError(413, "image_too_large", f"{name} has {w}x{h} = {w * h} pixels; the server's limit is {max_pixels} "
                                               "per image (FASTGHA_MAX_IMAGE_PIXELS): send it downscaled")  # fmt: skip
    return im


def _why(e: Exception) -> str:
    from PIL import UnidentifiedImageError

    if isinstance(e, UnidentifiedImageError):
        return ""
    msg = _REPR.sub("the upload", str(e)).strip()
    return f" ({type(e).__name__}: {msg[:200]})" if msg else f" ({type(e).__name__})"


def probe_request(
    images: list[Photo], masks: list[Photo] | None, cameras: list | None, *, max_pixels: int, max_request_pixels: int
) -> None:
    """Read every header (no pixel is decoded) and check sizes before the request queues.

    Sets ``Photo.size``. Raises ``ApiError``: 400 ``invalid_image`` (not a JPEG/PNG), 413
    ``image_too_large`` (one file over ``max_pixels``), 413 ``request_too_large`` (the files
    together over ``max_request_pixels``), 400 ``camera_size_mismatch`` / ``mask_size_mismatch``.
    Every message names the file by its filename.
    """
    total = 0
    for p in images + (masks or []):
        im = _open_checked(p.data, p.name, max_pixels)
        p.size, p.orientation = _upright_size(im), _orientation(im)
        im.close()
        total += p.size[0] * p.size[1]
    if total > max_request_pixels:
        raise ApiError(
            413, "request_too_large", f"the {len(images) + len(masks or [])} files hold {total} pixels together; the server's limit per request is {max_request_pixels} (FASTGHA_MAX_REQUEST_PIXELS): send fewer or downscaled photos"
        )
    for i, p in enumerate(images):
        w, h = p.size
        if cameras is not None:
            cam = cameras[i]
            if (cam.width, cam.height) != (w, h):
                raise ApiError(400, "camera_size_mismatch", f"camera {i} describes a {cam.width}x{cam.height} image but {p.name} is {p.described()}")
        if masks is not None and masks[i].size != (w, h):
            raise ApiError(400, "mask_size_mismatch", f"mask {masks[i].name} is {masks[i].described()} but its photo {p.name} is {p.described()}")


def decode_photo(photo: Photo, *, max_pixels: int, max_side: int, mask: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """Decode one upload, downscaled while decoding so that its longer side is <= ``max_side``.

    The one place the creation path decodes pixels (JPEG and PNG; the pixel limit is checked
    from the header before decoding). A JPEG is decoded at a reduced DCT scale (1/2, 1/4,
    1/8) when that suffices, so its full raster never exists in memory.

    Returns:
        ``mask=False``: ``rgb [h, w, 3]`` uint8 and ``alpha [h, w]`` uint8 or None.
        ``mask=True``: ``(mask [h, w] uint8, None)``: the alpha channel when there is one, else luminance.
    Raises:
        ApiError 400 ``invalid_image`` / 413 ``image_too_large``, naming ``photo.name``.

    Decoding is ``fastgha_core.images`` (downscale while decoding, EXIF orientation applied,
    every pixel mode normalised); its errors become the same ApiErrors, and 400
    ``unsupported_image_mode``.
    """
    kw = {"max_pixels": max_pixels, "max_side": max_side, "formats": _FORMATS}
    try:
        if mask:
            return _shared.decode_mask_bytes(photo.data, photo.name, **kw), None
        d = _shared.decode_image_bytes(photo.data, photo.name, **kw)
        return d.rgb, d.alpha
    except _shared.ImageDecodeError as e:
        raise ApiError(413 if e.code == "image_too_large" else 400, e.code, e.message) from None


def _to_float(arr: np.ndarray) -> Tensor:
    """``[h, w, 3]`` uint8 -> ``[3, h, w]``, or ``[h, w]`` -> ``[1, h, w]``, float32 in [0, 1]."""
    t = torch.from_numpy(np.ascontiguousarray(arr))
    t = t.permute(2, 0, 1) if t.ndim == 3 else t[None]
    return t.float().div_(255.0)


# ---------------------------------------------------------------- requests, state, stages
@dataclass
class CreationRequest:
    """What ``POST /v1/avatars`` queues: the files (headers probed), cameras or None (track them), and
    the head ``fastgha track`` fitted to them when the client sent it (with the cameras)."""

    images: list[Photo]
    masks: list[Photo] | None
    cameras: list | None  # list[Cameras] (one per image, stored-pixel sizes) or None
    head: Any = None  # the client's tracked head (model.surface.HeadSurface, the ``head`` part) or None

    @property
    def nbytes(self) -> int:
        return sum(len(p.data) for p in self.images + (self.masks or []))


@dataclass
class CreationState:
    """What the stages share. An extra stage reads ``images`` ``[V, 3, S, S]`` (matted, in [0, 1]),
    ``cameras`` (``Cameras [V]``, S x S), ``masks`` ``[V, 1, S, S]`` or None, and may replace ``avatar``."""

    model: Any
    device: str
    names: list[str]
    images: Tensor | None = None
    cameras: Any = None
    masks: Tensor | None = None
    expressions: Tensor | None = None  # [V, E] the photos' tracked expressions, or None
    # photos with cameras and no head: fits the photos' expressions through their cameras when a stage
    # needs them (``PhotoTracker.fit_known_cameras``; None without the faces extra or a face)
    fit_expressions: Callable[[], Tensor | None] | None = None
    avatar: Any = None
    timings_ms: dict[str, float] = field(default_factory=dict)


#: ``(stage name, fn(state, fraction_callback))``; the stage name is one of :data:`STAGES` (``"refining"``).
ExtraStage = tuple[str, Callable[[CreationState, Callable[[float], None]], None]]


def extra_stages_for(ctx) -> list[ExtraStage]:
    """Stages run after reconstruction and before saving: test-time refinement
    (``fastgha_core.refine.refine_avatar``) as ``("refining", fn)`` unless ``FASTGHA_REFINE_STEPS`` is 0.
    ``auto`` (the default) refines every avatar with the preset ``refine_preset_for`` picks for it,
    with that preset's own steps: avatars on a tracked head with ``REFINE_PRESETS["photos"]`` (colours
    only, 30 steps), avatars on the network's depth (photos posted with cameras) with
    ``REFINE_PRESETS["default"]`` (60 steps). A number N refines every avatar N steps with that preset.
    The refinement compares each photo with the avatar animated to the photo's own expression: the
    tracked ones, or for photos with cameras the ones ``state.fit_expressions`` fits through the
    cameras (none without the ``faces`` extra). ``fn`` replaces ``state.avatar`` and reports its steps
    as the stage's fraction in [0, 1]. The figures behind ``auto``: docs/model-card-log.md, "Colours-only
    refinement on real photos" and "Photos with cameras: refined by the server too"."""
    setting = ctx.settings.refine_steps
    if setting == 0:
        return []

    def refine(state: CreationState, fraction: Callable[[float], None]) -> None:
        from fastgha_core.refine import REFINE_PRESETS, refine_avatar, refine_config_for, refine_preset_for

        preset = refine_preset_for(state.avatar)
        steps = REFINE_PRESETS[preset].steps if setting == "auto" else int(setting)
        expressions = state.expressions
        if expressions is None and state.fit_expressions is not None:
            expressions = _in_model_space(state.fit_expressions(), len(state.images), state.model)
        result = refine_avatar(
            state.model, state.avatar, state.images, state.cameras, state.masks,
            config=refine_config_for(state.avatar, steps, preset), progress=lambda i, n: fraction(i / n), expressions=expressions,
        )  # fmt: skip
        state.avatar = result.avatar

    return [("refining", refine)]


def _in_model_space(expressions: Tensor | None, views: int, model) -> Tensor | None:
    """``expressions`` when they are ``[views, model.config.expression_dim]``, else None (tracked or
    fitted in another expression space than the model's: nothing to undo or to refine with)."""
    if expressions is None or tuple(expressions.shape) != (views, model.config.expression_dim):
        return None
    return expressions


FIT_MAX_SIDE = 512  # photos kept for the expression fit are shrunk to this longer side (memory while the job runs)


def _expression_fitter(tracker, photos: list[Tensor], cameras: list, names: list[str], masks) -> Callable[[], Tensor | None]:
    """``CreationState.fit_expressions`` for photos posted with cameras: the photos' ``ict53``
    expressions ``[V, 53]`` of the head fitted through the given cameras (``PhotoTracker.fit_known_cameras``;
    None without the ``faces`` extra or when no photo shows a face). ``photos``: V x ``[3, H_i, W_i]``,
    ``cameras``: V single ``Cameras`` of those sizes, ``masks``: per photo ``[1, H_i, W_i]``/None, or None.
    The photos, masks and cameras are kept shrunk to ``FIT_MAX_SIDE`` until the fit runs."""

    def shrink(x: Tensor | None, size: tuple[int, int]) -> Tensor | None:
        if x is None or tuple(x.shape[-2:]) == size:
            return x
        return torch.nn.functional.interpolate(x[None], size=size, mode="area")[0]

    sizes = []
    for im in photos:
        h, w = im.shape[-2:]
        s = min(1.0, FIT_MAX_SIDE / max(h, w))
        sizes.append((max(1, round(h * s)), max(1, round(w * s))))
    photos = [shrink(im, hw) for im, hw in zip(photos, sizes)]
    cameras = [cam if (cam.height, cam.width) == hw else cam.resize(hw[1], hw[0]) for cam, hw in zip(cameras, sizes)]
    masks = None if masks is None else [shrink(m, hw) for m, hw in zip(masks, sizes)]

    def fit() -> Tensor | None:
        surface = tracker.fit_known_cameras(photos, cameras, names=names, masks=masks)
        return None if surface is None else torch.from_numpy(surface.expressions).float()

    return fit


class JobCancelled(Exception):
    pass


# ---------------------------------------------------------------- jobs
class Job:
    """One creation. Mutated on the event loop only (the worker thread posts its updates there)."""

    def __init__(self, avatar_id: str, token_sha256: str, client: str, nbytes: int, request: CreationRequest, stages: list[str]) -> None:
        self.id = avatar_id
        self.token_sha256 = token_sha256
        self.client = client
        self.nbytes = nbytes
        self.request: CreationRequest | None = request
        self.stages = stages  # the stages this job will pass through (weights of its progress)
        self.status = "queued"  # queued | running | ready | failed
        self.stage = "queued"
        self.stage_fraction = 0.0
        self.queue_position: int | None = None
        self.created = time.time()
        self.started: float | None = None
        self.finished: float | None = None
        self.result: dict | None = None
        self.error: ApiError | None = None
        self.cancel_requested = False
        self._failed_at = 0.0  # progress when the job failed
        self._changed = asyncio.Event()
        self._done = asyncio.Event()

    @property
    def done(self) -> bool:
        return self.status in ("ready", "failed")

    @property
    def progress(self) -> float:
        if self.status == "ready":
            return 1.0
        if self.status == "failed":  # where it stopped: the whole job's progress never decreases
            return self._failed_at
        if self.stage not in self.stages:
            return 0.0
        w = {s: _WEIGHTS.get(s, _EXTRA_WEIGHT) for s in self.stages}
        total = sum(w.values())
        i = self.stages.index(self.stage)
        return round(min(1.0, (sum(w[s] for s in self.stages[:i]) + w[self.stage] * self.stage_fraction) / total), 4)

    def _notify(self) -> None:
        old, self._changed = self._changed, asyncio.Event()
        old.set()

    def update(self, stage: str, fraction: float) -> None:
        if self.done:
            return
        self.stage = stage
        self.stage_fraction = max(0.0, min(1.0, float(fraction)))
        if stage != "queued":
            self.status = "running"
            self.queue_position = None
        self._notify()

    def finish(self, result: dict | None, error: ApiError | None) -> None:
        self.finished = time.time()
        self._failed_at = self.progress if error is not None else 0.0
        self.result, self.error = result, error
        self.status = "failed" if error is not None else "ready"
        self.stage = self.status
        self.stage_fraction = 1.0
        self.queue_position = None
        self.request = None
        self._done.set()
        self._notify()

    def snapshot(self) -> dict:
        """The status resource (``GET /v1/avatars/{id}/status``)."""
        now = self.finished or time.time()
        out = {
            "avatar_id": self.id,
            "status": self.status,
            "stage": self.stage,
            "stage_progress": round(self.stage_fraction, 4),
            "progress": self.progress,
            "queue_position": self.queue_position,
            "elapsed_ms": round(1e3 * (now - self.created), 1),
        }
        if self.error is not None:
            out["error"] = {"status": self.error.status, "code": self.error.code, "message": self.error.message}
        if self.result is not None:
            out["avatar"] = dict(self.result)
        return out


@dataclass
class Ticket:
    """A place in the queue reserved before the request body is read; ``release`` if unused."""

    queue: "JobQueue"
    client: str
    nbytes: int
    used: bool = False

    def release(self) -> None:
        if not self.used:
            self.used = True
            self.queue._release(self.client, self.nbytes, waiting=True)


def _lower_priority(nice: int, sched_idle: bool) -> None:
    """Thread initializer: put this thread below the render threads for the CPU.

    With ``sched_idle`` it takes Linux's ``SCHED_IDLE`` policy (sched(7): "for running very low
    priority background jobs"; a thread of the normal policy that wakes preempts it at once);
    without it, or where that fails, it raises its nice value to ``nice``. Both are per thread on
    Linux and inherited by the threads it starts (torch's OpenMP team: tested in
    ``tests/test_jobs.py``; any other thread created from it alike, by Linux's clone rules).
    Lowering one's own priority is always permitted; a platform without either keeps the default.

    Why SCHED_IDLE by default (``bench/creation_load.py fps``, docs/benchmarks.md "Creation under
    load"): with nice 10 a 256² stream kept 0.62-0.68 of its idle frame rate during creations,
    with SCHED_IDLE 0.86-0.91; nice only shrinks a thread's share of the CPU, while a render's
    many short waits (OpenMP barriers, the event loop) each gave the core away to a creation
    thread until its time slice ended.
    """
    if sched_idle:
        try:
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))  # pid 0: the calling thread
            return
        except (AttributeError, OSError) as e:  # not Linux
            log.debug("SCHED_IDLE unavailable for the creation thread (%s); using nice %d", e, nice)
    try:
        tid = threading.get_native_id()
        cur = os.getpriority(os.PRIO_PROCESS, tid)
        if nice > cur:
            os.setpriority(os.PRIO_PROCESS, tid, nice)
    except (AttributeError, OSError) as e:  # not Linux, or not allowed: run at normal priority
        log.debug("could not lower the creation thread's priority: %s", e)


class JobQueue:
    """The app's creation queue (one per app; docstring of the module).

    Args:
        ctx: the ``ServerContext`` (model, store, metrics, settings).
        tracker: the app's ``PhotoTracker`` (photos without cameras).
        extra_stages: run after reconstruction, before saving (``extra_stages_for``).
    """

    def __init__(self, ctx, tracker, extra_stages: Sequence[ExtraStage] = ()) -> None:
        s = ctx.settings
        self.ctx = ctx
        self.tracker = tracker
        self.extra_stages = list(extra_stages)
        self.max_running = s.max_concurrent_reconstructions
        self.max_waiting = s.max_queued_jobs
        self.max_per_client = s.max_jobs_per_client
        self.max_bytes = s.max_queued_upload_bytes
        self.ttl = s.job_ttl_seconds
        self.jobs: dict[str, Job] = {}
        self._order: collections.deque[Job] = collections.deque()  # queued, oldest first
        self._per_client: collections.Counter[str] = collections.Counter()
        self._waiting = 0  # tickets and queued jobs (not yet running)
        self._running = 0
        self._bytes = 0
        self._mean_s = 5.0  # running mean of job durations, for Retry-After
        self._queue: asyncio.Queue | None = None
        self._workers: list[asyncio.Task] = []
        self._pool: ThreadPoolExecutor | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        from prometheus_client import Gauge

        g = Gauge("fastgha_creation_jobs", "avatar creations: running, or waiting (queued or uploading)", ["state"], registry=ctx.metrics.registry)
        g.labels(state="running").set_function(lambda: self._running)
        g.labels(state="waiting").set_function(lambda: self._waiting)

    # ------------------------------------------------------------ life
    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._queue = asyncio.Queue()
        nice = self.ctx.settings.creation_nice
        self._pool = ThreadPoolExecutor(
            max_workers=self.max_running, thread_name_prefix="fastgha-create", initializer=_lower_priority,
            initargs=(nice, self.ctx.settings.creation_sched_idle),
        )
        self._workers = [asyncio.create_task(self._worker(), name=f"fastgha-create-{i}") for i in range(self.max_running)]

    async def stop(self) -> None:
        for t in self._workers:
            t.cancel()
        await asyncio.gather(*self._workers, return_exceptions=True)
        for job in list(self._order):
            job.finish(None, ApiError(503, "server_shutting_down", "the server stopped before this avatar was created; create it again"))
        self._order.clear()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)

    # ------------------------------------------------------------ admission
    def retry_after(self) -> int:
        ahead = self._running + self._waiting
        return int(min(120, max(1, math.ceil(self._mean_s * max(1, ahead) / self.max_running))))

    def reserve(self, client: str, nbytes: int) -> Ticket:
        """Reserve a place before the body is read; ``ApiError`` 429 / 503 (with ``retry_after``) when full."""
        self._sweep()
        if self._per_client[client] >= self.max_per_client:
            raise _busy(429, "too_many_jobs", f"this client already has {self._per_client[client]} avatar creation(s) queued or running "
                        f"(limit {self.max_per_client}); wait for one to finish", self.retry_after())  # fmt: skip
        if self._running + self._waiting >= self.max_running + self.max_waiting:
            raise _busy(503, "queue_full", f"the creation queue is full ({self._waiting} waiting, {self._running} running); try again later",
                        self.retry_after())  # fmt: skip
        if self._bytes > 0 and self._bytes + nbytes > self.max_bytes:
            raise _busy(503, "queue_full", f"the uploads held by queued creations would exceed {self.max_bytes} bytes; try again later",
                        self.retry_after())  # fmt: skip
        self._per_client[client] += 1
        self._waiting += 1
        self._bytes += nbytes
        return Ticket(self, client, nbytes)

    def _release(self, client: str, nbytes: int, waiting: bool) -> None:
        self._per_client[client] -= 1
        if self._per_client[client] <= 0:
            del self._per_client[client]
        if waiting:
            self._waiting -= 1
        else:
            self._running -= 1
        self._bytes -= nbytes

    def submit(self, ticket: Ticket, request: CreationRequest) -> tuple[Job, str]:
        """Queue the request under the ticket; returns the job and the avatar's token (shown once)."""
        if ticket.used:
            raise RuntimeError("ticket already used")
        ticket.used = True
        nb = request.nbytes
        self._bytes += nb - ticket.nbytes  # the real size replaces the declared one
        stages = ["queued", "decoding"] + (["tracking"] if request.cameras is None else []) + ["reconstructing"]
        stages += [name for name, _ in self.extra_stages] + ["saving"]
        token = auth.new_token()
        job = Job(auth.new_avatar_id(), auth.hash_token(token), ticket.client, nb, request, stages)
        self.jobs[job.id] = job
        self._order.append(job)
        self._renumber()
        self._queue.put_nowait(job)
        return job, token

    def _renumber(self) -> None:
        for i, j in enumerate(self._order):
            if j.queue_position != i + 1:
                j.queue_position = i + 1
                j._notify()

    def get(self, avatar_id: str) -> Job | None:
        self._sweep()
        return self.jobs.get(avatar_id)

    def cancel(self, job: Job) -> None:
        """Stop a job: a queued one never runs, a running one is not saved (checked between stages)."""
        job.cancel_requested = True
        if job.status == "queued" and job in self._order:
            self._order.remove(job)
            self._release(job.client, job.nbytes, waiting=True)
            job.finish(None, ApiError(404, "avatar_deleted", "the avatar was deleted before it was created"))
            self._renumber()

    def _sweep(self) -> None:
        now = time.time()
        for jid in [j.id for j in self.jobs.values() if j.finished is not None and now - j.finished > self.ttl]:
            del self.jobs[jid]

    @property
    def stats(self) -> dict:
        return {"running": self._running, "waiting": self._waiting, "bytes": self._bytes}

    # ------------------------------------------------------------ waiting
    async def wait(self, job: Job) -> None:
        await job._done.wait()

    async def watch(self, job: Job, heartbeat_s: float = 15.0) -> AsyncIterator[dict | None]:
        """Snapshots of ``job``: the current one, then one per change, until it is done;
        ``None`` every ``heartbeat_s`` without a change (keep-alive)."""
        while True:
            ev = job._changed
            yield job.snapshot()
            if job.done:
                return
            try:
                await asyncio.wait_for(ev.wait(), heartbeat_s)
            except asyncio.TimeoutError:
                yield None

    async def wait_on_socket(self, websocket, avatar_id: str, token: str) -> tuple[int, str] | None:
        """A stream opened before its avatar is ready: send ``{"type": "progress", ...}`` text
        messages (the status resource's fields) until the job is done. Returns None when the
        avatar is ready (or there is no such job), else ``(close code, reason)`` to refuse the socket."""
        from .errors import CloseCode

        job = self.get(avatar_id)
        if job is None:
            return None
        if not auth.token_matches(token, job.token_sha256):
            return CloseCode.UNAUTHORIZED, "invalid_token"
        async for snap in self.watch(job, heartbeat_s=10.0):
            if snap is None:
                snap = job.snapshot()  # a keep-alive that also finds a client gone
            if snap["status"] == "ready":
                return None
            await websocket.send_text(json.dumps({"type": "progress", **snap}))
            if snap["status"] == "failed":
                return CloseCode.NOT_FOUND, f"creation_failed: {job.error.code}" if job.error else "creation_failed"
        return None

    # ------------------------------------------------------------ running
    async def _worker(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            job: Job = await self._queue.get()
            if job.done:  # cancelled while queued
                continue
            self._order.remove(job)
            self._waiting -= 1
            self._running += 1
            self._renumber()
            job.started = time.time()
            job.update("decoding", 0.0)

            def progress(stage: str, fraction: float, job=job) -> None:  # called from the job thread
                if job.cancel_requested:
                    raise JobCancelled()
                loop.call_soon_threadsafe(job.update, stage, fraction)

            result, error = None, None
            try:
                result = await loop.run_in_executor(self._pool, self._run, job, progress)
            except ApiError as e:
                error = e
            except JobCancelled:
                error = ApiError(404, "avatar_deleted", "the avatar was deleted before it was created")
            except asyncio.CancelledError:
                raise
            except Exception as e:
                error = _known_error(e)
                if error is None:
                    log.exception("creating avatar %s failed", job.id)
                    error = ApiError(500, "internal_error", "creating the avatar failed (internal error)")
            finally:
                self._release(job.client, job.nbytes, waiting=False)
            dt = time.time() - job.started
            self._mean_s = 0.7 * self._mean_s + 0.3 * dt
            if result is not None:
                self.ctx.metrics.reconstruct_seconds.observe(result["reconstruction_ms"] / 1e3)
                self.ctx.metrics.avatars_created.inc()
            job.finish(result, error)

    def _run(self, job: Job, progress: Progress) -> dict:
        """The job's work, in a creation thread: decode, track, reconstruct, extra stages, save."""
        ctx, s = self.ctx, self.ctx.settings
        req = job.request
        model = ctx.model
        size = int(model.config.input_size)
        max_side = max(int(s.decode_max_side), size)
        names = [p.name for p in req.images]
        t0 = time.perf_counter()
        # ---- decoding: one file at a time, downscaled while decoding
        n_files = len(req.images) + len(req.masks or [])
        images, masks, cams = [], [], []
        identity = getattr(ctx, "identity", None)  # server/identity.py: one person in all photos?
        check_id = identity is not None and identity.enabled and len(req.images) > 1 and identity.available
        descriptors: list = []
        id_ms = 0.0
        for i, p in enumerate(req.images):
            rgb, alpha = decode_photo(p, max_pixels=s.max_image_pixels, max_side=max_side)
            h, w = rgb.shape[:2]
            if check_id:
                t_id = time.perf_counter()
                descriptors.append(identity.descriptor(rgb))
                id_ms += 1e3 * (time.perf_counter() - t_id)
            images.append(_to_float(rgb))
            m = None
            if req.masks is not None:
                marr, _ = decode_photo(req.masks[i], max_pixels=s.max_image_pixels, max_side=max_side, mask=True)
                if marr.shape[:2] != (h, w):  # same stored size (probed), so the same target size
                    raise ApiError(400, "mask_size_mismatch", f"mask {req.masks[i].name} does not match {p.name} after decoding")
                m = _to_float(marr)
            elif alpha is not None and int(alpha.min()) < 255:
                m = _to_float(alpha)  # an RGBA photo carries its own matte; opaque everywhere it carries none
            masks.append(m)
            if req.cameras is not None:
                cam = req.cameras[i]
                cams.append(cam if (cam.width, cam.height) == (w, h) else cam.resize(w, h))
            del rgb, alpha
            progress("decoding", (i + 1) / len(req.images))
        job.request = None  # the uploaded bytes are no longer needed
        if identity is None:
            same_person = {"checked": False, "reason": "no checker configured"}
        elif len(names) == 1 and identity.enabled:
            same_person = {"checked": False, "reason": "one photo"}
        else:  # raises 422 different_people when the photos split into several people
            same_person = identity.check(names, descriptors, id_ms).as_dict()
        given = None if all(m is None for m in masks) else masks  # per photo; None where it brings no matte (the tracker makes one)
        mlist = None if given is None else [m if m is not None else torch.ones(1, *im.shape[-2:]) for m, im in zip(masks, images)]
        t1 = time.perf_counter()
        timings = {"decoding_ms": 1e3 * (t1 - t0)}
        log.debug("decoded %d file(s) for %s in %.0f ms", n_files, job.id, timings["decoding_ms"])
        # ---- tracking (photos without cameras)
        tracking_ms = None
        expressions = None  # the photos' own expressions, when tracked: undone for a neutral canonical head
        surface = None  # the tracked head: every pixel's Gaussian goes on it (fastgha_core/model/surface.py)
        if req.cameras is None:
            progress("tracking", 0.0)
            crops, cam_batch, crop_masks, expressions, surface = self.tracker.track(images, given, size, names=names)
            tracking_ms = 1e3 * (time.perf_counter() - t1)
            images, mlist = crops, crop_masks
            cams = cam_batch
            progress("tracking", 1.0)
        # ---- reconstructing
        progress("reconstructing", 0.0)
        t2 = time.perf_counter()
        known_surface = False
        if req.head is not None:
            # the client's tracked head (fastgha track's head.json + expressions.json): reconstructed on it as
            # `fastgha reconstruct` does (every pixel on the head, the photos' expressions undone; FASTGHA_SURFACE_DEPTH=0: depth off)
            from fastgha_core.headfile import head_expressions

            surface, expressions = req.head, head_expressions(req.head, model)
        elif req.cameras is not None and s.surface_depth_cameras != "off":
            # photos with cameras: the head fitted through them (None without the faces extra or a face)
            surface = self.tracker.fit_known_cameras(images, cams, names=names, masks=given)
            known_surface = surface is not None
            if known_surface and model.config.expression_dim == 53:
                expressions = torch.from_numpy(surface.expressions)  # the photos' fitted expressions: undone, and refined with
        try:
            x, c = model.prepare(images, cams, mlist)
        except ValueError as e:
            raise ApiError(400, "invalid_input", str(e)) from None
        fit_expressions = None
        if expressions is None and req.cameras is not None and s.surface_depth_cameras == "off" and self.tracker is not None:
            fit_expressions = _expression_fitter(self.tracker, images, cams, names, given)
        del images
        expressions = _in_model_space(expressions, x.shape[0], model)
        if not s.surface_depth and not known_surface:
            surface = None
        mode = s.surface_depth_cameras if known_surface else "replace"
        with torch.inference_mode():
            # with the expression prior, the tracked expressions make the canonical head neutral
            avatar = model.reconstruct(x.to(ctx.device), c.to(ctx.device), expressions=expressions, surface=surface, surface_mode=mode)
        recon_ms = 1e3 * (time.perf_counter() - t2)
        progress("reconstructing", 1.0)
        state = CreationState(model=model, device=ctx.device, names=names, images=x, cameras=c, avatar=avatar, expressions=expressions,
                              fit_expressions=fit_expressions)  # fmt: skip
        if self.extra_stages and mlist is not None:
            mm = [m.expand(3, -1, -1) for m in (mlist if isinstance(mlist, list) else list(mlist.unbind(0)))]
            state.masks = model.prepare(mm, cams)[0][:, :1]  # the same crop and resize as the images
        for name, fn in self.extra_stages:
            progress(name, 0.0)
            t = time.perf_counter()
            fn(state, lambda f, name=name: progress(name, f))
            state.timings_ms[f"{name}_ms"] = 1e3 * (time.perf_counter() - t)
            progress(name, 1.0)
        avatar = state.avatar
        _check_head(avatar.num_reconstructed, s)  # the head model's mouth interior and lids are not a head
        # ---- saving (the avatar is durable before the job reports ready)
        progress("saving", 0.0)
        n = len(avatar.gaussians)
        meta = {
            "avatar_id": job.id,
            "token_sha256": job.token_sha256,
            "model": model.config.name,
            "expression_space": model.expression_space.name,
            "num_gaussians": n,
            "num_images": len(names),
            "reconstruction_ms": round(recon_ms, 1),
            "created_at": time.time(),
        }
        if tracking_ms is not None:
            meta["tracking_ms"] = round(tracking_ms, 1)
        from .avatar_info import avatar_facts

        meta["same_person"] = same_person  # what the same-person check compared (server/identity.py)
        meta.update(avatar_facts(avatar))  # view blending and prior facts (GET /v1/avatars/{id}, server/avatar_info.py)
        for k, v in state.timings_ms.items():
            meta[k] = round(v, 1)
        if job.cancel_requested:
            raise JobCancelled()
        ctx.store.put(job.id, avatar, meta)
        if job.cancel_requested:  # deleted while saving: undo
            ctx.store.delete(job.id)
            raise JobCancelled()
        log.info("created avatar %s: %d Gaussians from %d images in %.0f ms (job %.0f ms)", job.id, n, len(names), recon_ms,
                 1e3 * (time.perf_counter() - t0))  # fmt: skip
        from .avatar_info import avatar_options

        out = created_fields(meta)
        out.update(avatar_options(model, meta))  # view_blend, expression_prior
        return out


CREATED_KEYS = ("avatar_id", "num_gaussians", "reconstruction_ms", "expression_space")


def created_fields(meta: dict) -> dict:
    """The ``201`` body's fields that an avatar's stored metadata holds (docs/protocol.md): the
    ``CREATED_KEYS``, every stage's time (``tracking_ms``, ``refining_ms``, ...: the metadata's other
    ``*_ms`` keys) and ``same_person``. The creation job returns them (with ``avatar_options``), and
    the ready status rebuilds them from the stored metadata once the job has left memory, so the two
    never differ."""
    out = {k: meta[k] for k in CREATED_KEYS if k in meta}
    out.update({k: v for k, v in meta.items() if k.endswith("_ms") and k not in out})
    if "same_person" in meta:
        out["same_person"] = meta["same_person"]
    return out


def _check_head(n: int, settings) -> None:
    """Refuse a reconstruction that holds no head (422 ``no_head_reconstructed``, the hardened
    protocol's ``check_reconstruction``)."""
    from .protocol import ProtocolError, check_reconstruction

    try:
        check_reconstruction(n, settings.min_avatar_gaussians)
    except ProtocolError as e:
        raise ApiError(422, e.code, e.message) from None


def _known_error(e: Exception) -> ApiError | None:
    """The typed answer of an error the app's handlers know (a full disk: 507), raised inside a job."""
    from .store import StorageFullError  # disk full while saving

    if isinstance(e, StorageFullError):
        log.error("saving an avatar failed: %s", e.strerror or e)
        return ApiError(507, "insufficient_storage", "the server has no disk space left to store this avatar; nothing was stored")
    return None


def _busy(status: int, code: str, message: str, retry_after: int) -> ApiError:
    e = ApiError(status, code, f"{message} (retry after {retry_after} s)")
    e.headers = {"Retry-After": str(retry_after)}
    return e
