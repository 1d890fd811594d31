"""The FastAPI application: ``create_app(settings)``.

Run it with ``fastgha serve`` or ``uvicorn --factory server.app:create_app`` (settings from
``FASTGHA_*``). The model loads and warms up in ``lifespan``; the HTTP and WebSocket
contracts are in ``docs/protocol.md``.
"""

from __future__ import annotations

import asyncio
import logging
import math
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import torch
from fastapi import FastAPI, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException

from fastgha_core import __version__
from fastgha_core.cameras import Cameras, cameras_from_json, orbit_cameras

from . import auth
from .context import ServerContext, StreamRegistry
from .errors import ApiError, CloseCode, error_body
from .frames import FrameRenderer
from .imaging import decode_image, decode_mask
from .logs import install_token_redaction
from .metrics import CONTENT_TYPE_LATEST
from .protocol import ProtocolError, loads_strict
from .samples import make_samples_router
from .settings import Settings, get_settings
from .store import AvatarStore
from .streaming import _safe_close, stream_endpoint
from .tracking import PhotoTracker

__all__ = ["create_app"]

log = logging.getLogger(__name__)

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
}


# ---------------------------------------------------------------- start-up
def _load(ctx: ServerContext) -> None:
    """Load the model, open the store and warm up (blocking; runs in a worker thread)."""
    from fastgha_core import load_model
    from fastgha_core.model.avatar import CanonicalAvatar

    s = ctx.settings
    ctx.device = s.resolved_device()
    t0 = time.perf_counter()
    ctx.model = load_model(s.model, device=ctx.device)
    log.info("loaded model %r on %s in %.1f s", ctx.model.config.name, ctx.device, time.perf_counter() - t0)
    bf16 = s.resolved_bf16(ctx.device)
    ctx.renderer = FrameRenderer(ctx.model, ctx.device, s.default_camera_distance, s.default_camera_fov_deg, bf16=bf16)
    if s.resolved_compile(ctx.device):
        _compile_deformation(ctx)
    else:
        log.info("deformation MLP: %s, eager (FASTGHA_COMPILE=%s)", "bf16" if bf16 else "fp32", s.compile)
    # animate() caches an [N, hidden] first-layer term on each avatar: count it in the budget
    hidden = int(getattr(getattr(ctx.model.config, "deform", None), "hidden_size", 0))

    def nbytes(avatar) -> int:
        return int(avatar.nbytes) + len(avatar.gaussians) * hidden * 4

    ctx.store = AvatarStore(s.data_dir, s.cache_max_bytes, s.avatar_ttl_seconds, load_fn=CanonicalAvatar.load, nbytes_fn=nbytes)
    ctx.metrics.bind_cache(lambda: ctx.store.cached_count, lambda: ctx.store.cached_bytes)
    if s.warmup:
        _warmup(ctx)


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
    ctx.reconstruct_slots = asyncio.Semaphore(s.max_concurrent_reconstructions)
    ctx.streams = StreamRegistry(s.max_streams_per_avatar, s.max_streams_total)
    if not s.api_key_list:
        log.warning("FASTGHA_API_KEYS is not set: anyone who can reach this server can create avatars")
    await ctx.run_work(_load, ctx)
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
            raise ApiError(413, "upload_too_large", f"upload of {n} bytes exceeds the limit of {limit}")
    chunks, total = [], 0
    async for chunk in request.stream():
        total += len(chunk)
        if total > limit:
            raise ApiError(413, "upload_too_large", f"upload exceeds the limit of {limit} bytes")
        chunks.append(chunk)
    return b"".join(chunks)


def _boundary(ctype: str) -> bytes | None:
    from multipart.multipart import parse_options_header

    _, params = parse_options_header(ctype)
    b = params.get(b"boundary")
    return b or None


async def _parse_form(request: Request, s: Settings):
    ctype = request.headers.get("content-type", "")
    if not ctype.lower().startswith("multipart/form-data"):
        raise ApiError(415, "invalid_multipart", f"expected multipart/form-data, got {ctype[:80]!r}")
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


async def _part_bytes(part: Any, what: str) -> bytes:
    if isinstance(part, UploadFile):
        return await part.read()
    raise ApiError(400, "invalid_multipart", f"{what} must be a file part, got a text field")


def _decode_inputs(blobs: list[bytes], mask_blobs: list[bytes] | None, cams: list[Cameras] | None, max_pixels: int):
    images, masks = [], []
    for i, data in enumerate(blobs):
        img, alpha = decode_image(data, f"image {i}", max_pixels)
        h, w = img.shape[-2:]
        cam = cams[i] if cams is not None else None  # None: the server tracks the photos (server/tracking.py)
        if cam is not None and (cam.width, cam.height) != (w, h):
            raise ApiError(
                400,
                "camera_size_mismatch",
                f"camera {i} describes a {cam.width}x{cam.height} image but image {i} is {w}x{h}",
            )
        mask = None
        if mask_blobs is not None:
            mask = decode_mask(mask_blobs[i], f"mask {i}", max_pixels)
            if tuple(mask.shape[-2:]) != (h, w):
                raise ApiError(400, "mask_size_mismatch", f"mask {i} is {mask.shape[-1]}x{mask.shape[-2]}, image {i} is {w}x{h}")
        elif alpha is not None:
            mask = alpha  # an RGBA photo carries its own matte
        images.append(img)
        masks.append(mask)
    if all(m is None for m in masks):
        return images, None
    return images, [m if m is not None else torch.ones(1, *img.shape[-2:]) for m, img in zip(masks, images)]


def _track_and_reconstruct(ctx: ServerContext, tracker: PhotoTracker, images: list, masks: list | None):
    """Photos without cameras: track them (crops, cameras, masks), then reconstruct; times both."""
    t0 = time.perf_counter()
    crops, cams, crop_masks, exprs = tracker.track(images, masks, int(ctx.model.config.input_size))
    track_ms = 1e3 * (time.perf_counter() - t0)
    avatar, recon_ms = _reconstruct(ctx, crops, cams, crop_masks, exprs)
    return avatar, recon_ms, track_ms


def _reconstruct(ctx: ServerContext, images, cams, masks, expressions=None):
    model = ctx.model
    t0 = time.perf_counter()
    try:
        x, c = model.prepare(images, cams, masks)
    except ValueError as e:
        raise ApiError(400, "invalid_input", str(e)) from None
    if expressions is not None and tuple(expressions.shape) != (x.shape[0], model.config.expression_dim):
        expressions = None  # tracked in another expression space: the photos' expressions are not undone
    with torch.inference_mode():
        # the tracked expressions let a model with the expression prior make a neutral canonical head
        avatar = model.reconstruct(x.to(ctx.device), c.to(ctx.device), expressions=expressions)
    return avatar, 1e3 * (time.perf_counter() - t0)


def _ply_bytes(avatar) -> bytes:
    from fastgha_core.io import save_ply

    with tempfile.TemporaryDirectory(prefix="fastgha-ply-") as d:
        p = Path(d) / "avatar.ply"
        save_ply(p, avatar.gaussians)
        return p.read_bytes()


# ---------------------------------------------------------------- the app
_CREATE_OPENAPI = {
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
    tracker = PhotoTracker()  # photos without cameras (server/tracking.py); loads dlib on first use

    if s.cors_origin_list:
        from fastapi.middleware.cors import CORSMiddleware

        app.add_middleware(
            CORSMiddleware,
            allow_origins=s.cors_origin_list,
            allow_methods=["GET", "POST", "DELETE"],
            allow_headers=["Authorization", "Content-Type", "X-API-Key"],
        )

    # ------------------------------------------------------------ errors
    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError):
        return JSONResponse(exc.body(), status_code=exc.status)

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
        }

    @app.post("/v1/avatars", status_code=201, tags=["avatars"], openapi_extra=_CREATE_OPENAPI)
    async def create_avatar(request: Request):
        ctx = _ctx(request)
        auth.check_api_key(request.headers, s.api_key_list)
        form = await _parse_form(request, s)
        max_images = min(s.max_images, int(getattr(ctx.model.config, "max_views", s.max_images)))
        parts = form.getlist("images")
        if not 1 <= len(parts) <= max_images:
            raise ApiError(400, "invalid_image_count", f"send 1 to {max_images} 'images' parts, got {len(parts)}")
        cam_field = form.get("cameras")
        cams: list[Cameras] | None = None
        if cam_field is None:  # no cameras: the server tracks the photos, if it can (server/tracking.py)
            await ctx.run_work(tracker.check_available)
        else:
            cam_text = await cam_field.read() if isinstance(cam_field, UploadFile) else cam_field
            try:
                cams = cameras_from_json(loads_strict(cam_text))
            except ProtocolError as e:
                raise ApiError(400, "non_finite_number" if e.code == "non_finite_number" else "invalid_cameras", e.message) from None
            except ValueError as e:
                raise ApiError(400, "invalid_cameras", str(e)) from None
            if len(cams) != len(parts):
                raise ApiError(400, "camera_count_mismatch", f"{len(parts)} images but {len(cams)} cameras; send one camera per image")
        mask_parts = form.getlist("masks")
        if mask_parts and len(mask_parts) != len(parts):
            raise ApiError(400, "mask_count_mismatch", f"{len(parts)} images but {len(mask_parts)} masks; send none or one per image")
        blobs = [await _part_bytes(p, f"image {i}") for i, p in enumerate(parts)]
        mask_blobs = [await _part_bytes(p, f"mask {i}") for i, p in enumerate(mask_parts)] if mask_parts else None
        await form.close()
        images, masks = await ctx.run_work(_decode_inputs, blobs, mask_blobs, cams, s.max_image_pixels)
        track_ms = None
        async with ctx.reconstruct_slots:
            if cams is None:
                avatar, recon_ms, track_ms = await ctx.run_work(_track_and_reconstruct, ctx, tracker, images, masks)
            else:
                avatar, recon_ms = await ctx.run_work(_reconstruct, ctx, images, cams, masks)
        ctx.metrics.reconstruct_seconds.observe(recon_ms / 1e3)
        avatar_id, token = auth.new_avatar_id(), auth.new_token()
        n = len(avatar.gaussians)
        meta = {
            "avatar_id": avatar_id,
            "token_sha256": auth.hash_token(token),
            "model": ctx.model.config.name,
            "expression_space": ctx.model.expression_space.name,
            "num_gaussians": n,
            "num_images": len(images),
            "reconstruction_ms": round(recon_ms, 1),
            "created_at": time.time(),
        }
        if track_ms is not None:
            meta["tracking_ms"] = round(track_ms, 1)
        await ctx.run_work(ctx.store.put, avatar_id, avatar, meta)
        ctx.metrics.avatars_created.inc()
        log.info("created avatar %s: %d Gaussians from %d images in %.0f ms", avatar_id, n, len(images), recon_ms)
        return JSONResponse(
            {
                "avatar_id": avatar_id,
                "token": token,
                "num_gaussians": n,
                "reconstruction_ms": round(recon_ms, 1),
                "expression_space": meta["expression_space"],
                **({"tracking_ms": meta["tracking_ms"]} if track_ms is not None else {}),
            },
            status_code=201,
        )

    @app.get("/v1/avatars/{avatar_id}", tags=["avatars"])
    async def get_avatar(avatar_id: str, request: Request):
        meta = await _authorize(request, avatar_id)
        ctx = _ctx(request)
        return {**_public_meta(meta), "active_streams": len(ctx.streams.sessions(avatar_id))}

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
        await _authorize(request, avatar_id)
        ctx = _ctx(request)
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
