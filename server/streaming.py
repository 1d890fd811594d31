"""The WebSocket stream: one receive task and one render task per socket.

The receive task parses every client message at once (errors are answered immediately,
the socket stays open) and puts frame requests into a one-item ``LatestSlot``: a request
still waiting when a newer one arrives is replaced and counted as dropped ("latest wins").
The render task takes the newest request, renders it in the render thread pool (off the
event loop) and sends one binary frame message. Both tasks are cancelled in ``finally``.
A failure while rendering one frame is reported to that client only, and logged through a
``LogThrottle`` (one traceback per kind, then counts). Every send has a deadline
(``ws_send_timeout_seconds``): a client that stops reading is closed with 4408 and its stream
slot freed. With origins configured (``cors_origins``) a browser ``Origin`` outside them is
refused with 4403.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from typing import Any

from fastapi import WebSocket
from starlette.websockets import WebSocketDisconnect, WebSocketState

from fastgha_core.cameras import Cameras, cameras_to_json

from .auth import bearer_from, is_valid_avatar_id, token_matches
from .avatar_info import avatar_facts, avatar_options
from .context import ServerContext
from .errors import CloseCode
from .frames import fit_camera
from .store import AvatarUnreadableError
from .protocol import (
    FrameRequest,
    OptionsMessage,
    PingMessage,
    ProtocolError,
    error_message,
    pack_frame,
    parse_binary_message,
    parse_text_message,
)

__all__ = ["LatestSlot", "LogThrottle", "RateLimiter", "StreamSession", "stream_endpoint", "origin_allowed"]

log = logging.getLogger(__name__)

PROTOCOL_VERSION = 1


class LatestSlot:
    """A one-item mailbox: ``put`` replaces a waiting item (counted in ``dropped``), ``take`` waits."""

    def __init__(self) -> None:
        self._item: Any = None
        self._event = asyncio.Event()
        self.dropped = 0

    def put(self, item: Any) -> None:
        if self._item is not None:
            self.dropped += 1
        self._item = item
        self._event.set()

    async def take(self) -> Any:
        await self._event.wait()
        item, self._item = self._item, None
        self._event.clear()
        return item


class RateLimiter:
    """Token bucket (``rate`` per second, burst ``rate``) plus an abuse check over 1 s windows.

    ``hit()`` returns ``"ok"``, ``"limited"`` (over the rate: drop the message) or ``"abuse"``
    (more than ``rate * abuse_factor`` messages within one second: close the socket).
    """

    def __init__(self, rate: float, abuse_factor: float, clock=time.monotonic) -> None:
        self.rate = float(rate)
        self.capacity = max(1.0, self.rate)
        self.abuse_limit = self.rate * float(abuse_factor)
        self._clock = clock
        self._tokens = self.capacity
        self._last = clock()
        self._window_start = self._last
        self._window_count = 0

    def hit(self) -> str:
        now = self._clock()
        self._tokens = min(self.capacity, self._tokens + (now - self._last) * self.rate)
        self._last = now
        if now - self._window_start >= 1.0:
            self._window_start, self._window_count = now, 0
        self._window_count += 1
        if self._window_count > self.abuse_limit:
            return "abuse"
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return "ok"
        return "limited"


class LogThrottle:
    """Log an error with its traceback once per ``key``, then only counts, at most once per ``interval`` s.

    One misbehaving avatar or client can fail every frame (hundreds per second); the log gets
    the first traceback and then one line per interval saying how many more there were.
    Thread-safe enough for the event loop (no awaits inside).
    """

    def __init__(self, interval: float = 60.0, clock=time.monotonic) -> None:
        self.interval = float(interval)
        self._clock = clock
        self._state: dict[str, list] = {}  # key -> [time of the last line, suppressed since]

    def exception(self, logger: logging.Logger, key: str, msg: str, *args: Any) -> None:
        """Call from an ``except`` block: ``logger.error(msg % args)`` with the traceback the first time."""
        now = self._clock()
        st = self._state.get(key)
        if st is None:
            self._state[key] = [now, 0]
            logger.error(msg, *args, exc_info=True)
        elif now - st[0] >= self.interval:
            logger.error(msg + " (and %d more like it in the last %.0f s; traceback logged once)", *args, st[1], now - st[0])
            st[0], st[1] = now, 0
        else:
            st[1] += 1


def origin_allowed(headers: Any, allowed: list[str]) -> bool:
    """True when a WebSocket handshake's ``Origin`` may connect.

    No origins configured (``cors_origins`` empty) or ``*``: any. Otherwise the ``Origin`` must be
    one of them or the server's own (same scheme-less host as the ``Host`` header, i.e. the page
    this server serves). Clients that send no ``Origin`` (not browsers) are allowed: browsers
    always send one, and tokens, not origins, authenticate.
    """
    if not allowed or "*" in allowed:
        return True
    origin = headers.get("origin")
    if origin is None:
        return True
    origin = origin.strip().rstrip("/")
    if origin in {a.rstrip("/") for a in allowed}:
        return True
    host = (headers.get("host") or "").strip().lower()
    _, sep, rest = origin.lower().partition("://")
    return bool(sep) and bool(host) and rest == host


class _Close(Exception):
    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code, self.reason = code, reason


class StreamSession:
    """State and tasks of one open stream."""

    def __init__(self, ctx: ServerContext, websocket: WebSocket, avatar_id: str, avatar: Any) -> None:
        s = ctx.settings
        self.ctx = ctx
        self.ws = websocket
        self.avatar_id = avatar_id
        self.avatar = avatar
        self.space = ctx.model.expression_space
        self.camera: Cameras = ctx.renderer.default_camera
        self.jpeg_quality = s.default_jpeg_quality
        self.max_size = s.max_output_size
        self.slot = LatestSlot()
        self.limiter = RateLimiter(s.ws_max_messages_per_second, s.ws_abuse_factor)
        self._send_lock = asyncio.Lock()
        self._last_rate_error = 0.0
        self._tasks: list[asyncio.Task] = []
        self.frames_sent = 0

    # ------------------------------------------------------------ sending
    async def _send(self, coro_fn, payload) -> None:
        """One send with a deadline: a client that does not read closes with 4408 (SLOW_CONSUMER)."""
        timeout = self.ctx.settings.ws_send_timeout_seconds
        async with self._send_lock:
            try:
                async with asyncio.timeout(timeout):  # no extra task per frame, unlike wait_for
                    await coro_fn(payload)
            except TimeoutError:
                self.ctx.metrics.protocol_errors.labels(code="slow_consumer").inc()
                log.warning("stream of avatar %s: the client read nothing for %.0f s; closing (4408)", self.avatar_id, timeout)
                raise _Close(CloseCode.SLOW_CONSUMER, "slow_consumer: the client does not read its frames") from None

    async def _send_text(self, text: str) -> None:
        await self._send(self.ws.send_text, text)

    async def _send_bytes(self, data: bytes) -> None:
        await self._send(self.ws.send_bytes, data)

    async def send_error(self, code: str, message: str) -> None:
        self.ctx.metrics.protocol_errors.labels(code=code).inc()
        await self._send_text(error_message(code, message))

    def ready_message(self) -> str:
        sp = self.space
        cam = self.camera
        return json.dumps(
            {
                "type": "ready",
                "protocol": PROTOCOL_VERSION,
                "avatar_id": self.avatar_id,
                "model": self.ctx.model.config.name,
                "expression_space": sp.name,
                "expression_names": list(sp.names),
                "expression_dim": sp.dim,
                "width": cam.width,
                "height": cam.height,
                "camera": cameras_to_json(cam)[0],
                "jpeg_quality": self.jpeg_quality,
                "max_size": self.max_size,
                "max_message_bytes": self.ctx.settings.ws_max_message_bytes,
                "max_messages_per_second": self.ctx.settings.ws_max_messages_per_second,
                # what this avatar's frames are made with (server/avatar_info.py; as GET /v1/avatars/{id})
                **avatar_options(self.ctx.model, avatar_facts(self.avatar)),
            }
        )

    # ------------------------------------------------------------ tasks
    async def run(self) -> None:
        await self._send_text(self.ready_message())
        recv = asyncio.create_task(self._receive_loop(), name=f"ws-recv-{self.avatar_id}")
        rend = asyncio.create_task(self._render_loop(), name=f"ws-render-{self.avatar_id}")
        self._tasks = [recv, rend]
        try:
            done, _ = await asyncio.wait(self._tasks, return_when=asyncio.FIRST_COMPLETED)
            for t in done:
                exc = t.exception()
                if exc is not None:
                    raise exc
        finally:
            for t in self._tasks:
                t.cancel()
            await asyncio.gather(*self._tasks, return_exceptions=True)

    async def _receive_loop(self) -> None:
        s = self.ctx.settings
        while True:
            msg = await self.ws.receive()
            if msg["type"] == "websocket.disconnect":
                return
            text, data = msg.get("text"), msg.get("bytes")
            size = len(text.encode("utf-8")) if text is not None else len(data or b"")
            if size > s.ws_max_message_bytes:
                raise _Close(CloseCode.MESSAGE_TOO_BIG, f"message of {size} bytes exceeds {s.ws_max_message_bytes}")
            verdict = self.limiter.hit()
            if verdict == "abuse":
                raise _Close(CloseCode.RATE_ABUSE, "message rate far above the limit")
            if verdict == "limited":
                self.slot.dropped += 1
                self.ctx.metrics.frames_dropped.inc()
                now = time.monotonic()
                if now - self._last_rate_error >= 1.0:
                    self._last_rate_error = now
                    await self.send_error(
                        "rate_limited", f"more than {s.ws_max_messages_per_second:g} messages per second; message dropped"
                    )
                continue
            try:
                req = parse_text_message(text, self.space) if text is not None else parse_binary_message(data, self.space)
            except ProtocolError as e:
                await self.send_error(e.code, e.message)
                continue
            except Exception as e:  # a parser bug must not end the stream (1011): answer it like a bad message
                _throttle(self.ctx).exception(log, f"parse:{type(e).__name__}", "parsing a message on a stream of avatar %s failed", self.avatar_id)
                await self.send_error("invalid_message", f"the message could not be parsed ({type(e).__name__})")
                continue
            if isinstance(req, FrameRequest):
                if req.camera is not None:
                    self.camera = req.camera  # sticky, even when this request is dropped later
                before = self.slot.dropped
                self.slot.put(req)
                if self.slot.dropped != before:
                    self.ctx.metrics.frames_dropped.inc()
            elif isinstance(req, PingMessage):
                pong = {"type": "pong"}
                if "t" in req.payload:
                    pong["t"] = req.payload["t"]
                await self._send_text(json.dumps(pong))
            elif isinstance(req, OptionsMessage):
                if req.jpeg_quality is not None:
                    self.jpeg_quality = req.jpeg_quality
                if req.max_size is not None:
                    self.max_size = min(req.max_size, s.max_output_size)
                await self._send_text(
                    json.dumps({"type": "options", "jpeg_quality": self.jpeg_quality, "max_size": self.max_size})
                )

    async def _render_loop(self) -> None:
        ctx = self.ctx
        while True:
            req: FrameRequest = await self.slot.take()
            t0 = time.perf_counter()
            try:
                cam = fit_camera(self.camera, self.max_size)
                fr = await ctx.run_render(ctx.renderer.render, self.avatar, req.expression, cam, self.jpeg_quality)
            except Exception as e:  # one bad frame must not end the stream or touch other sessions
                _throttle(ctx).exception(log, f"render:{type(e).__name__}", "rendering a frame of avatar %s failed", self.avatar_id)
                ctx.metrics.frame_errors.inc()
                await self.send_error("render_failed", f"the frame could not be rendered ({type(e).__name__})")
                continue
            ctx.metrics.render_seconds.observe(fr.render_ms / 1e3)
            ctx.metrics.encode_seconds.observe(fr.encode_ms / 1e3)
            header = {
                "seq": req.seq,
                "render_ms": round(fr.render_ms, 3),
                "deform_ms": round(fr.deform_ms, 3),
                "raster_ms": round(fr.raster_ms, 3),
                "encode_ms": round(fr.encode_ms, 3),
                "total_ms": round(1e3 * (time.perf_counter() - t0), 3),
                "width": fr.width,
                "height": fr.height,
                "dropped": self.slot.dropped,
            }
            await self._send_bytes(pack_frame(header, fr.jpeg))
            ctx.metrics.frames_rendered.inc()
            self.frames_sent += 1

    async def close(self, code: int, reason: str) -> None:
        for t in self._tasks:
            t.cancel()
        await _safe_close(self.ws, code, reason)


def _throttle(ctx: ServerContext) -> LogThrottle:
    if ctx.log_throttle is None:
        ctx.log_throttle = LogThrottle()
    return ctx.log_throttle


_CLOSE_TIMEOUT_S = 5.0  # a close frame queued behind unread data must not hold the handler


async def _safe_close(ws: WebSocket, code: int, reason: str) -> None:
    try:
        if ws.application_state == WebSocketState.CONNECTED and ws.client_state == WebSocketState.CONNECTED:
            await asyncio.wait_for(ws.close(code=code, reason=reason[:120]), _CLOSE_TIMEOUT_S)
    except (RuntimeError, WebSocketDisconnect, OSError, asyncio.TimeoutError):
        pass


async def stream_endpoint(websocket: WebSocket, avatar_id: str) -> None:
    """``/v1/avatars/{avatar_id}/stream``: authenticate, then run a ``StreamSession``.

    The socket is accepted before any check so that refusals reach browsers as close codes
    (4401 auth, 4403 origin not allowed, 4404 unknown avatar, 4409 other model, 4410 unreadable
    avatar file, 4503 at capacity).
    """
    ctx: ServerContext = websocket.app.state.ctx
    await websocket.accept()
    session: StreamSession | None = None
    registered = False
    try:
        if not origin_allowed(websocket.headers, ctx.settings.cors_origin_list):
            raise _Close(CloseCode.FORBIDDEN_ORIGIN, "origin_not_allowed")
        if not is_valid_avatar_id(avatar_id):
            raise _Close(CloseCode.NOT_FOUND, "avatar_not_found")
        token = bearer_from(websocket.headers, websocket.query_params)
        if not token:
            raise _Close(CloseCode.UNAUTHORIZED, "token_required")
        meta = await ctx.run_work(ctx.store.get_meta, avatar_id)
        if meta is None and ctx.jobs is not None:  # still being created: progress messages until ready (server/jobs.py)
            refusal = await ctx.jobs.wait_on_socket(websocket, avatar_id, token)
            if refusal is not None:
                raise _Close(*refusal)
            meta = await ctx.run_work(ctx.store.get_meta, avatar_id)
        if meta is None:
            raise _Close(CloseCode.NOT_FOUND, "avatar_not_found")
        if not token_matches(token, meta.get("token_sha256", "")):
            raise _Close(CloseCode.UNAUTHORIZED, "invalid_token")
        if meta.get("model") != ctx.model.config.name:
            raise _Close(CloseCode.CONFLICT, "avatar_model_mismatch")
        item = await ctx.run_work(ctx.store.get, avatar_id)
        if item is None:
            raise _Close(CloseCode.NOT_FOUND, "avatar_not_found")
        session = StreamSession(ctx, websocket, avatar_id, item.avatar)
        refusal = ctx.streams.try_add(avatar_id, session)
        if refusal is not None:
            raise _Close(CloseCode.AT_CAPACITY, f"at_capacity: {refusal}")
        registered = True
        ctx.metrics.active_streams.inc()
        await session.run()
        await _safe_close(websocket, CloseCode.NORMAL, "bye")
    except _Close as c:
        await _safe_close(websocket, c.code, c.reason)
    except AvatarUnreadableError:  # set aside by the store (logged there, once)
        await _safe_close(websocket, CloseCode.GONE, "avatar_unreadable")
    except WebSocketDisconnect:
        pass
    except Exception:
        log.exception("stream of avatar %s failed", avatar_id)
        await _safe_close(websocket, CloseCode.INTERNAL_ERROR, "internal_error")
    finally:
        if registered:
            ctx.streams.remove(avatar_id, session)
            ctx.metrics.active_streams.dec()
