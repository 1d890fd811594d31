"""The FastAPI application: ``create_app(settings)``.

Run it with ``fastgha serve`` or ``uvicorn --factory server.app:create_app`` (settings from
``FASTGHA_*``). The model loads and warms up in ``lifespan``; the HTTP and WebSocket
contracts are in ``docs/protocol.md``.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import torch
from fastapi import FastAPI, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, StreamingResponse
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from fastgha_core import __version__
from fastgha_core.cameras import Cameras, orbit_cameras

from . import auth
from .avatar_info import FACT_KEYS, avatar_facts, avatar_options, server_options
from .context import ServerContext, StreamRegistry
from .errors import ApiError, CloseCode, error_body
from .frames import FrameRenderer
from .identity import IdentityChecker
from .jobs import CreationRequest, JobQueue, Photo, created_fields, extra_stages_for, probe_request, safe_filename
from .logs import install_token_redaction
from .metrics import CONTENT_TYPE_LATEST
from .protocol import ProtocolError, parse_cameras_json, parse_head_json
from .samples import make_samples_router
from .security import install as install_security
from .settings import Settings, get_settings
from .store import AvatarStore
from .streaming import stream_endpoint
from .tracking import PhotoTracker

__all__ = ["create_app"]

log = logging.getLogger(__name__)

# the parts of POST /v1/avatars (docs/protocol.md); a file under any other name is named in the count error
_CREATION_PARTS = frozenset({"images", "cameras", "masks", "head"})

_STATUS_CODES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    406: "not_acceptable",
    411: "length_required",
    413: "payload_too_large",
    415: "unsupported_media_type",
    422: "invalid_request",
    429: "too_many_requests",
    503: "service_unavailable",
}


def apply_model_overrides(model, s: Settings) -> None:
    """The settings that override the loaded model's own options, set on ``model.config``:
    ``view_blend_tau_deg`` (``FASTGHA_VIEW_BLEND_TAU_DEG`` / ``--view-blend-tau-deg``, 0 = off) and
    ``mirror_views`` (``FASTGHA_MIRROR_VIEWS``); ``None`` keeps the model's own."""
    if s.view_blend_tau_deg is not None:
        model.config.gaussians.view_blend_tau_deg = float(s.view_blend_tau_deg)
    if s.mirror_views is not None:  # model/mirror.py
        model.config.gaussians.mirror_views = bool(s.mirror_views)


# ---------------------------------------------------------------- start-up
def _load(ctx: ServerContext) -> None:
    """Load the model, choose the MLP precision, compile, open the store and warm up (blocking; runs
    in a worker thread). Each step logs what it is doing before it starts and how long it took, so
    that the ~30 s before the server listens are not silent."""
    from fastgha_core import load_model
    from fastgha_core.model.avatar import CanonicalAvatar

    s = ctx.settings
    t_start = time.perf_counter()
    ctx.device = s.resolved_device()
    compile_on = s.resolved_compile(ctx.device)
    steps = ["load"] + (["precision"] if s.mlp_precision == "auto" else []) + (["compile"] if compile_on else []) + (["warmup"] if s.warmup else [])

    def step(name: str, what: str) -> None:
        log.info("start-up %d/%d: %s ...", steps.index(name) + 1, len(steps), what)

    step("load", f"loading model {s.model!r} on {ctx.device}")
    t0 = time.perf_counter()
    ctx.model = load_model(s.model, device=ctx.device)
    log.info("loaded model %r on %s in %.1f s", ctx.model.config.name, ctx.device, time.perf_counter() - t0)
    apply_model_overrides(ctx.model, s)
    tau = ctx.model.config.gaussians.view_blend_tau_deg
    log.info("view blending of avatars with per-view data: %s (%s)", f"tau {tau:g} deg" if tau > 0 else "off",
             "FASTGHA_VIEW_BLEND_TAU_DEG / --view-blend-tau-deg" if s.view_blend_tau_deg is not None else "the model's own")  # fmt: skip
    log.info("mirrored views of turned photos (avatars on a tracked head): %s (%s)", "on" if ctx.model.config.gaussians.mirror_views else "off",
             "FASTGHA_MIRROR_VIEWS" if s.mirror_views is not None else "the model's own")  # fmt: skip
    ctx.mlp_choice = _choose_precision(ctx, lambda: step("precision", "timing the deformation MLP in fp32 and bf16 (FASTGHA_MLP_PRECISION=auto)"))
    bf16 = ctx.mlp_choice.bf16
    ctx.renderer = FrameRenderer(ctx.model, ctx.device, s.default_camera_distance, s.default_camera_fov_deg, bf16=bf16)
    if compile_on:
        step("compile", f"compiling the deformation MLP with torch.compile ({'bf16' if bf16 else 'fp32'}; tens of seconds on a CPU)")
        _compile_deformation(ctx)
    else:
        log.info("deformation MLP: %s, eager (FASTGHA_COMPILE=%s)", "bf16" if bf16 else "fp32", s.compile)
    if ctx.identity is not None and ctx.identity.enabled:  # dlib's face models now, not on the first creation (server/identity.py)
        log.info("same-person check of each avatar's photos: %s", "on (dlib face descriptors)" if ctx.identity.available
                 else f"off, nothing is checked: {ctx.identity.reason}")  # fmt: skip
    # the budget counts what an avatar holds once it streams: Gaussians, prior binding, the MLP's cached
    # first layer and the prior's per-frame basis (FastGHA.serving_nbytes)
    ctx.store = AvatarStore(s.data_dir, s.cache_max_bytes, s.avatar_ttl_seconds, load_fn=CanonicalAvatar.load, nbytes_fn=ctx.model.serving_nbytes)
    ctx.metrics.bind_cache(lambda: ctx.store.cached_count, lambda: ctx.store.cached_bytes)
    if s.warmup:
        step("warmup", f"warming up: one reconstruction and {s.warmup_frames} frames")
        _warmup(ctx)
    log.info("start-up done in %.1f s", time.perf_counter() - t_start)


def _choose_precision(ctx: ServerContext, announce=lambda: None):
    """The deformation MLP's precision: as configured, or (``auto``) measured on this machine by
    ``fastgha_core.perf.measure_mlp_precision`` (fp32 vs bf16 on the served chunk shape)."""
    from fastgha_core.perf import PrecisionChoice, measure_mlp_precision

    s = ctx.settings
    if s.mlp_precision != "auto":
        return PrecisionChoice(s.mlp_precision, "configured")
    announce()
    choice = measure_mlp_precision(ctx.model)
    if choice.reason == "measured":
        log.info("deformation MLP precision: %s (fp32 %.2f ms, bf16 %.2f ms per %d-row chunk, median of %d)",
                 choice.precision, choice.fp32_ms, choice.bf16_ms, 8192, choice.reps)
    else:
        log.info("deformation MLP precision: %s (%s)", choice.precision, choice.reason)
    return choice


def _compile_deformation(ctx: ServerContext) -> None:
    """torch.compile the per-frame MLP now, so that no client waits for it; eager when it fails."""
    bf16 = ctx.renderer.bf16
    graphs = ctx.settings.cuda_graphs
    if graphs and not str(ctx.device).startswith("cuda"):
        log.warning("FASTGHA_CUDA_GRAPHS is set but the device is %s: ignored", ctx.device)
        graphs = False
    try:
        secs = ctx.model.compile_deformation(bf16=bf16, cuda_graphs=graphs)
    except Exception as e:  # inductor needs a working C++ toolchain; the eager MLP gives the same frames
        log.warning("torch.compile of the deformation MLP failed, running it eagerly: %s: %s", type(e).__name__, str(e).splitlines()[0][:300] if str(e) else "")
        return
    log.info("deformation MLP: %s, compiled%s in %.1f s", "bf16" if bf16 else "fp32", " (CUDA graphs)" if graphs else "", secs)


def _warmup(ctx: ServerContext) -> None:
    """One reconstruction and a few frames, so that the first client sees steady-state latency."""
    s, model = ctx.settings, ctx.model
    size = int(model.config.input_size)
    t0 = time.perf_counter()
    g = torch.Generator().manual_seed(0)
    views = min(4, int(getattr(model.config, "max_views", 4)))
    cams = orbit_cameras(views, radius=s.default_camera_distance, fov_deg=s.default_camera_fov_deg, width=size, height=size)
    images = torch.rand(views, 3, size, size, generator=g)  # [V, 3, S, S]
    with torch.inference_mode():
        avatar = model.reconstruct(images.to(ctx.device), cams.to(ctx.device))
    t1 = time.perf_counter()
    space = model.expression_space
    for i in range(s.warmup_frames):
        expr = space.neutral() + 0.1 * i * torch.rand(space.dim, generator=g)
        ctx.renderer.render(avatar, expr, ctx.renderer.default_camera, s.default_jpeg_quality)
    log.info(
        "warm-up: reconstruction %.0f ms, %d frames %.0f ms",
        1e3 * (t1 - t0),
        s.warmup_frames,
        1e3 * (time.perf_counter() - t1),
    )


async def _expiry_loop(ctx: ServerContext) -> None:
    while True:
        await asyncio.sleep(ctx.settings.expiry_interval_seconds)
        try:
            await ctx.run_work(ctx.store.sweep_expired, ctx.streams.active_ids())
        except Exception:  # keep sweeping; an error here must not take the server down
            log.exception("sweeping expired avatars failed")


@asynccontextmanager
async def _lifespan(app: FastAPI):
    ctx: ServerContext = app.state.ctx
    s = ctx.settings
    ctx.work_pool = ThreadPoolExecutor(max_workers=max(2, s.max_concurrent_reconstructions + 1), thread_name_prefix="fastgha-work")
    ctx.render_pool = ThreadPoolExecutor(max_workers=s.render_workers, thread_name_prefix="fastgha-render")
    ctx.streams = StreamRegistry(s.max_streams_per_avatar, s.max_streams_total)
    if not s.api_key_list:
        log.warning("FASTGHA_API_KEYS is not set: anyone who can reach this server can create avatars")
    await ctx.run_work(_load, ctx)
    await ctx.jobs.start()
    ctx.ready = True
    sweeper = asyncio.create_task(_expiry_loop(ctx), name="fastgha-expiry")
    try:
        yield
    finally:
        ctx.ready = False
        sweeper.cancel()
        await asyncio.gather(sweeper, return_exceptions=True)
        for session in ctx.streams.sessions():
            await session.close(CloseCode.GOING_AWAY, "server shutting down")
        await ctx.jobs.stop()
        ctx.render_pool.shutdown(wait=True, cancel_futures=True)
        ctx.work_pool.shutdown(wait=True, cancel_futures=True)
        log.info("shut down")


# ---------------------------------------------------------------- helpers
def _ctx(request: Request) -> ServerContext:
    return request.app.state.ctx


async def _authorize(request: Request, avatar_id: str) -> dict:
    """Metadata of the avatar if the request carries its token; ApiError otherwise."""
    ctx = _ctx(request)
    auth.check_avatar_id(avatar_id)
    token = auth.bearer_from(request.headers, request.query_params)
    if not token:
        raise ApiError(401, "token_required", "this avatar's token is required (Authorization: Bearer or ?token=)")
    meta = await ctx.run_work(ctx.store.get_meta, avatar_id)
    if meta is None:
        raise ApiError(404, "avatar_not_found", "no avatar with this id")
    if not auth.token_matches(token, meta.get("token_sha256", "")):
        raise ApiError(403, "invalid_token", "the token does not belong to this avatar")
    return meta


def _public_meta(meta: dict) -> dict:
    return {k: v for k, v in meta.items() if k != "token_sha256"}


async def _read_body(request: Request, limit: int) -> bytes:
    cl = request.headers.get("content-length")
    if cl is not None:
        try:
            n = int(cl)
        except ValueError:
            raise ApiError(400, "invalid_multipart", "Content-Length is not a number") from None
        if n > limit:
            raise ApiError(413, "upload_too_large", f"upload of {n} bytes exceeds the server's limit of {limit} bytes "
                                                    "(FASTGHA_MAX_UPLOAD_BYTES): send fewer or smaller photos")  # fmt: skip
    chunks, total = [], 0
    try:
        async for chunk in request.stream():
            total += len(chunk)
            if total > limit:
                raise ApiError(413, "upload_too_large", f"upload exceeds the server's limit of {limit} bytes "
                                                        "(FASTGHA_MAX_UPLOAD_BYTES): send fewer or smaller photos")  # fmt: skip
            chunks.append(chunk)
    except ClientDisconnect:  # nobody is left to answer; its place in the queue is released by the caller
        raise ApiError(400, "client_disconnected", "the client went away before the upload was complete") from None
    return b"".join(chunks)


def _boundary(ctype: str) -> bytes | None:
    from python_multipart.multipart import parse_options_header

    _, params = parse_options_header(ctype)
    b = params.get(b"boundary")
    return b or None


async def _parse_form(request: Request, s: Settings):
    ctype = request.headers.get("content-type", "")
    if not ctype.lower().startswith("multipart/form-data"):
        got = f"Content-Type {ctype[:80]!r}" if ctype else "no Content-Type"
        raise ApiError(415, "invalid_multipart", f"expected multipart/form-data (each photo a file part named 'images', "
                                                 f"as curl -F images=@me.jpg sends), got {got}")  # fmt: skip
    body = await _read_body(request, s.max_upload_bytes)
    boundary = _boundary(ctype)
    if boundary is None:
        raise ApiError(400, "invalid_multipart", "the multipart Content-Type has no boundary")
    if not body.rstrip(b"\r\n").endswith(b"--" + boundary + b"--"):
        raise ApiError(400, "invalid_multipart", "the multipart body is truncated (no closing boundary)")
    sent = False

    async def replay() -> dict:
        nonlocal sent
        if sent:
            return {"type": "http.disconnect"}
        sent = True
        return {"type": "http.request", "body": body, "more_body": False}

    req2 = Request(request.scope, receive=replay)
    try:
        return await req2.form(max_files=2 * s.max_images + 2, max_fields=8, max_part_size=1024 * 1024)
    except StarletteHTTPException as e:
        raise ApiError(400, "invalid_multipart", f"the multipart body could not be parsed: {e.detail}") from None
    except Exception as e:  # python-multipart raises its own errors on malformed bodies
        raise ApiError(400, "invalid_multipart", f"the multipart body could not be parsed ({type(e).__name__}: {e})") from None


async def _photo(part: Any, index: int, what: str) -> Photo:
    """An uploaded file part as a ``Photo`` named by its filename (never by an index or a repr)."""
    if not isinstance(part, UploadFile):
        raise ApiError(400, "invalid_multipart", f"every '{what}s' part must be a file, got a text field (part {index + 1})")
    return Photo(safe_filename(part.filename, index, what), await part.read())


def _prefers_async(request: Request) -> bool:
    """RFC 7240 ``Prefer: respond-async``: answer 202 with a status resource instead of waiting."""
    prefs = ",".join(request.headers.getlist("prefer")).lower()
    return any(p.strip().split(";")[0].strip() == "respond-async" for p in prefs.split(","))


def _client_key(request: Request, api_keys: list[str]) -> str:
    """Who a creation counts against: the API key sent (hashed), else the peer address."""
    if api_keys:
        key = request.headers.get("x-api-key") or auth.bearer_from(request.headers, {}) or ""
        return "key:" + hashlib.sha256(key.encode("utf-8", "replace")).hexdigest()[:16]
    return "addr:" + (request.client.host if request.client else "?")


def _declared_length(request: Request, limit: int) -> int:
    try:
        n = int(request.headers.get("content-length", ""))
    except ValueError:
        return limit
    return n if 0 <= n <= limit else limit


def _ply_bytes(avatar) -> bytes:
    from fastgha_core.io import save_ply

    with tempfile.TemporaryDirectory(prefix="fastgha-ply-") as d:
        p = Path(d) / "avatar.ply"
        save_ply(p, avatar.gaussians)
        return p.read_bytes()


# ---------------------------------------------------------------- the app
_CREATE_OPENAPI = {
    "parameters": [
        {
            "name": "Prefer",
            "in": "header",
            "required": False,
            "schema": {"type": "string", "example": "respond-async"},
            "description": "respond-async: answer 202 at once with a status resource (a creation job) instead of waiting for 201",
        }
    ],
    "responses": {
        "202": {"description": "accepted (Prefer: respond-async): avatar_id, token, status, status_url, events_url, stream_url"},
        "429": {"description": "too_many_jobs: this client's creations fill its share; see Retry-After"},
        "503": {"description": "queue_full: the creation queue is full; see Retry-After"},
    },
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["images"],
                    "properties": {
                        "images": {"type": "array", "items": {"type": "string", "format": "binary"}, "description": "1-8 JPEG/PNG photos"},
                        "cameras": {
                            "type": "string",
                            "description": "JSON array of camera objects {K, w2c, width, height}, one per image; "
                            "when absent the server tracks the photos (needs the 'faces' extra)",
                        },
                        "masks": {"type": "array", "items": {"type": "string", "format": "binary"}, "description": "optional foreground masks, one per image"},
                        "head": {
                            "type": "string",
                            "description": "optional, with cameras: the tracked head of `fastgha track` "
                            '{"model": "ict_facekit", "identity": [100 numbers], "expressions": [[53 numbers] per image]}; '
                            "every pixel's Gaussian is put on it",
                        },
                    },
                }
            }
        },
    }
}


def create_app(settings: Settings | None = None) -> FastAPI:
    """The FastGHA server. ``settings`` defaults to ``get_settings()`` (the ``FASTGHA_*`` environment)."""
    s = settings if settings is not None else get_settings()
    install_token_redaction()
    app = FastAPI(
        title="FastGHA",
        version=__version__,
        description="Few-shot 3D Gaussian head avatars: reconstruct once over HTTP, animate in real time over WebSocket.",
        lifespan=_lifespan,
    )
    app.state.ctx = ServerContext(settings=s)
    install_security(app, s)  # 507/410 errors and security headers (server/security.py)
    # do all photos of one avatar show the same person (server/identity.py; loads dlib on first use)
    app.state.ctx.identity = IdentityChecker(s.same_person_check, s.same_person_max_distance)
    tracker = PhotoTracker()  # photos without cameras (server/tracking.py); loads dlib on first use
    app.state.ctx.jobs = JobQueue(app.state.ctx, tracker, extra_stages_for(app.state.ctx))  # started in lifespan

    if s.cors_origin_list:
        from fastapi.middleware.cors import CORSMiddleware

        app.add_middleware(
            CORSMiddleware,
            allow_origins=s.cors_origin_list,
            allow_methods=["GET", "POST", "DELETE"],
            allow_headers=["Authorization", "Content-Type", "X-API-Key", "Prefer"],
            expose_headers=["Location", "Retry-After", "Preference-Applied"],
        )

    # ------------------------------------------------------------ errors
    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError):
        return JSONResponse(exc.body(), status_code=exc.status, headers=getattr(exc, "headers", None))

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, exc: StarletteHTTPException):
        code = _STATUS_CODES.get(exc.status_code, "http_error")
        return JSONResponse(error_body(code, str(exc.detail)), status_code=exc.status_code, headers=getattr(exc, "headers", None))

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, exc: RequestValidationError):
        errs = exc.errors()
        msg = "; ".join(f"{'.'.join(str(x) for x in e.get('loc', ()))}: {e.get('msg')}" for e in errs[:5])
        return JSONResponse(error_body("invalid_request", msg or "invalid request"), status_code=422)

    @app.exception_handler(Exception)
    async def _internal_error(request: Request, exc: Exception):
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return JSONResponse(error_body("internal_error", "internal server error"), status_code=500)

    # ------------------------------------------------------------ routes
    @app.get("/healthz", tags=["service"])
    async def healthz(request: Request):
        ctx = _ctx(request)
        mlp = None
        if ctx.model is not None and ctx.renderer is not None:
            mlp = {"precision": "bf16" if ctx.renderer.bf16 else "fp32", "compiled": ctx.model.deform.compiled}
            if ctx.mlp_choice is not None:  # how the precision was chosen, with the measured times
                mlp["choice"] = ctx.mlp_choice.to_dict()
        return {
            "status": "ok" if ctx.ready else "starting",
            "version": __version__,
            "model": ctx.model.config.name if ctx.model else None,
            "mlp": mlp,
        }

    @app.get("/metrics", tags=["service"], response_class=Response)
    async def metrics(request: Request):
        return Response(_ctx(request).metrics.render(), media_type=CONTENT_TYPE_LATEST)

    @app.get("/v1/model", tags=["model"])
    async def model_info(request: Request):
        ctx = _ctx(request)
        cfg, sp, r = ctx.model.config, ctx.model.expression_space, ctx.renderer
        return {
            "name": cfg.name,
            "expression_space": sp.name,
            "expression_names": list(sp.names),
            "expression_dim": sp.dim,
            "input_size": [int(cfg.input_size), int(cfg.input_size)],
            "output_size": [r.width, r.height],
            "max_output_size": ctx.settings.max_output_size,
            "max_images": min(ctx.settings.max_images, int(getattr(cfg, "max_views", ctx.settings.max_images))),
            "device": ctx.device,
            **server_options(ctx.model),  # view_blend_tau_deg, expression_prior (server/avatar_info.py)
        }

    @app.post("/v1/avatars", status_code=201, tags=["avatars"], openapi_extra=_CREATE_OPENAPI)
    async def create_avatar(request: Request):
        """Create an avatar: ``201`` when it is ready, or ``202`` at once with ``Prefer: respond-async``."""
        ctx = _ctx(request)
        auth.check_api_key(request.headers, s.api_key_list)
        respond_async = _prefers_async(request)
        # a place in the bounded queue before the body is read: 429 / 503 + Retry-After when full
        ticket = ctx.jobs.reserve(_client_key(request, s.api_key_list), _declared_length(request, s.max_upload_bytes))
        try:
            creq = await _read_creation(ctx, request)
            job, token = ctx.jobs.submit(ticket, creq)
        except BaseException:
            ticket.release()
            raise
        if respond_async:
            urls = {
                "status_url": f"/v1/avatars/{job.id}/status",
                "events_url": f"/v1/avatars/{job.id}/events",
                "stream_url": f"/v1/avatars/{job.id}/stream",
            }
            return JSONResponse(
                {**job.snapshot(), "token": token, **urls},
                status_code=202,
                headers={"Location": urls["status_url"], "Retry-After": "1", "Preference-Applied": "respond-async"},
            )
        await ctx.jobs.wait(job)
        if job.error is not None:
            raise job.error
        return JSONResponse({**job.result, "token": token}, status_code=201)

    async def _read_creation(ctx: ServerContext, request: Request) -> CreationRequest:
        """Parse and check the upload (headers only: no pixel is decoded before the job runs)."""
        form = await _parse_form(request, s)
        max_images = min(s.max_images, int(getattr(ctx.model.config, "max_views", s.max_images)))
        parts = form.getlist("images")
        if not 1 <= len(parts) <= max_images:
            msg = f"send 1 to {max_images} 'images' parts, got {len(parts)}"
            if not parts:  # `curl -F image=@me.jpg`: say which parts did come
                other = sorted({k for k, v in form.multi_items() if k not in _CREATION_PARTS and not isinstance(v, str)})[:4]
                if other:
                    msg += f" (file part(s) named {', '.join(repr(k[:40]) for k in other)}: name each photo's part 'images')"
            raise ApiError(400, "invalid_image_count", msg)
        cam_field = form.get("cameras")
        cams: list[Cameras] | None = None
        head_field = form.get("head")
        if head_field is not None and cam_field is None:
            raise ApiError(400, "head_without_cameras", "the 'head' part lies in the world of the cameras it was tracked with: "
                           "send the 'cameras' part too (cameras.json of the same `fastgha track` folder)")  # fmt: skip
        if cam_field is None:  # no cameras: the server tracks the photos, if it can (server/tracking.py)
            await ctx.run_work(tracker.check_available)
        else:
            cam_text = await cam_field.read() if isinstance(cam_field, UploadFile) else cam_field
            try:
                cams = parse_cameras_json(cam_text)  # bounded numbers and renderable cameras (server/protocol.py)
            except ProtocolError as e:
                raise ApiError(400, "non_finite_number" if e.code == "non_finite_number" else "invalid_cameras", e.message) from None
            except ValueError as e:
                raise ApiError(400, "invalid_cameras", str(e)) from None
            if len(cams) != len(parts):
                raise ApiError(400, "camera_count_mismatch", f"{len(parts)} images but {len(cams)} cameras; send one camera per image")
        head = None
        if head_field is not None:  # fastgha track's head: every pixel's Gaussian goes on it, as `fastgha reconstruct` does
            head_text = await head_field.read() if isinstance(head_field, UploadFile) else head_field
            try:
                head = parse_head_json(head_text, len(parts))
            except ProtocolError as e:
                code = e.code if e.code in ("non_finite_number", "head_count_mismatch") else "invalid_head"
                raise ApiError(400, code, e.message) from None
        mask_parts = form.getlist("masks")
        if mask_parts and len(mask_parts) != len(parts):
            raise ApiError(400, "mask_count_mismatch", f"{len(parts)} images but {len(mask_parts)} masks; send none or one per image")
        images = [await _photo(p, i, "image") for i, p in enumerate(parts)]
        masks = [await _photo(p, i, "mask") for i, p in enumerate(mask_parts)] if mask_parts else None
        await form.close()
        await ctx.run_work(
            lambda: probe_request(images, masks, cams, max_pixels=s.max_image_pixels, max_request_pixels=s.max_request_pixels)
        )
        return CreationRequest(images, masks, cams, head)

    async def _job_or_meta(request: Request, avatar_id: str):
        """``(job, None)`` for an avatar being created, ``(None, meta)`` for a stored one; checks the token."""
        ctx = _ctx(request)
        auth.check_avatar_id(avatar_id)
        job = ctx.jobs.get(avatar_id)
        if job is None or job.status == "ready":
            return None, await _authorize(request, avatar_id)
        token = auth.bearer_from(request.headers, request.query_params)
        if not token:
            raise ApiError(401, "token_required", "this avatar's token is required (Authorization: Bearer or ?token=)")
        if not auth.token_matches(token, job.token_sha256):
            raise ApiError(403, "invalid_token", "the token does not belong to this avatar")
        return job, None

    async def _options(ctx: ServerContext, meta: dict) -> dict:
        """The avatar's ``view_blend`` and ``expression_prior`` (server/avatar_info.py); an avatar stored
        before its facts were recorded in its metadata gets them from its file."""
        facts = meta
        if not all(k in meta for k in FACT_KEYS):
            item = await ctx.run_work(ctx.store.get, meta["avatar_id"])
            facts = avatar_facts(item.avatar) if item is not None else {}
        return avatar_options(ctx.model, facts)

    async def _stored_status(ctx: ServerContext, meta: dict) -> dict:
        # the job's own clock is gone with the job: elapsed_ms is null, but the key is there as in every status
        avatar = {**created_fields(meta), **await _options(ctx, meta)}  # the 201 body without the token
        return {"avatar_id": meta["avatar_id"], "status": "ready", "stage": "ready", "stage_progress": 1.0, "progress": 1.0,
                "queue_position": None, "elapsed_ms": None, "avatar": avatar}  # fmt: skip

    async def _ready_status(ctx: ServerContext, avatar_id: str, meta: dict) -> dict:
        """A ready avatar's status: its job's snapshot while the job is still in memory (it keeps its
        elapsed_ms), else the stored one (elapsed_ms null); the same for /status and /events."""
        done = ctx.jobs.get(avatar_id)
        return done.snapshot() if done is not None and done.status == "ready" else await _stored_status(ctx, meta)

    @app.get("/v1/avatars/{avatar_id}/status", tags=["avatars"])
    async def avatar_status(avatar_id: str, request: Request):
        """The creation job's status: ``queued`` / ``running`` (``stage``, ``progress``) / ``ready`` / ``failed``."""
        job, meta = await _job_or_meta(request, avatar_id)
        if job is None:
            return await _ready_status(_ctx(request), avatar_id, meta)
        return JSONResponse(job.snapshot(), headers=None if job.done else {"Retry-After": "1"})

    @app.get("/v1/avatars/{avatar_id}/events", tags=["avatars"], response_class=StreamingResponse)
    async def avatar_events(avatar_id: str, request: Request):
        """Server-sent events: one ``progress`` event per change of the status, then ``ready`` or ``failed``."""
        job, meta = await _job_or_meta(request, avatar_id)

        async def events():
            if job is None:
                yield f"event: ready\ndata: {json.dumps(await _ready_status(_ctx(request), avatar_id, meta))}\n\n"
                return
            async for snap in _ctx(request).jobs.watch(job):
                if snap is None:
                    yield ": keep-alive\n\n"
                    continue
                kind = snap["status"] if snap["status"] in ("ready", "failed") else "progress"
                yield f"event: {kind}\ndata: {json.dumps(snap)}\n\n"

        return StreamingResponse(events(), media_type="text/event-stream", headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})

    @app.get("/v1/avatars/{avatar_id}", tags=["avatars"])
    async def get_avatar(avatar_id: str, request: Request):
        job, meta = await _job_or_meta(request, avatar_id)
        if job is not None and job.status == "failed":
            raise ApiError(404, "avatar_not_found", f"the avatar's creation failed ({job.error.code}): see /v1/avatars/{avatar_id}/status")
        if job is not None:
            raise ApiError(409, "avatar_not_ready", f"the avatar is still being created ({job.status}, stage {job.stage}): see /v1/avatars/{avatar_id}/status")
        ctx = _ctx(request)
        info = {k: v for k, v in _public_meta(meta).items() if k not in FACT_KEYS}
        return {**info, **await _options(ctx, meta), "active_streams": len(ctx.streams.sessions(avatar_id))}

    @app.get("/v1/avatars/{avatar_id}/ply", tags=["avatars"], response_class=Response)
    async def get_ply(avatar_id: str, request: Request):
        await _authorize(request, avatar_id)
        ctx = _ctx(request)
        item = await ctx.run_work(ctx.store.get, avatar_id)
        if item is None:
            raise ApiError(404, "avatar_not_found", "no avatar with this id")
        data = await ctx.run_work(_ply_bytes, item.avatar)
        return Response(
            data,
            media_type="application/octet-stream",
            headers={"Content-Disposition": f'attachment; filename="{avatar_id}.ply"'},
        )

    @app.delete("/v1/avatars/{avatar_id}", status_code=204, tags=["avatars"], response_class=Response)
    async def delete_avatar(avatar_id: str, request: Request):
        job, _ = await _job_or_meta(request, avatar_id)
        ctx = _ctx(request)
        if job is not None:  # still being created: cancel it (a queued job never runs, a running one is not kept)
            ctx.jobs.cancel(job)
            if not job.done:
                await ctx.jobs.wait(job)  # a running job stops at its next stage; if it was saved, it is removed below
        await ctx.run_work(ctx.store.delete, avatar_id)
        for session in ctx.streams.sessions(avatar_id):
            await session.close(CloseCode.NOT_FOUND, "avatar_deleted")
        return Response(status_code=204)

    app.add_api_websocket_route("/v1/avatars/{avatar_id}/stream", stream_endpoint)
    # Shipped sample subjects for the browser demo; before the static mount at "/" so it can't hide them.
    app.include_router(make_samples_router(s.samples_dir))

    static = s.resolved_static_dir()
    if static is not None:
        from fastapi.staticfiles import StaticFiles

        app.mount("/", StaticFiles(directory=static, html=True), name="demo")
    return app
