"""Transport-level hardening: connection deadlines and limits, JSON errors below the app, and
security headers.

Three parts, registered by ``fastgha serve`` (``uvicorn_options``) and ``create_app`` (``install``):

* ``GuardedH11Protocol`` (uvicorn's h11 protocol plus deadlines): a connection must send a
  complete request head within ``header_timeout_seconds`` of opening or of its last response,
  and the body within ``body_timeout_seconds`` of the head (408 when something partial came,
  a silent close when nothing did); a request target over ``max_url_bytes`` gets 414 and a head
  over ``max_request_head_bytes`` 431, before any parsing. Requests h11 refuses (a malformed
  ``Content-Length``, say) get the same JSON error body as the app's (``invalid_http``), not
  uvicorn's plain text. Uvicorn itself has no header-read timeout: its keep-alive timer stops
  at the first byte.
* ``GuardedWebSocketProtocol`` (uvicorn's websockets protocol plus a bounded send queue and a
  send deadline): the kernel send buffer of a stream is capped at ``ws_send_buffer_bytes``
  (Linux would otherwise let a client that reads nothing park ~4 MB there before a send ever
  waits); a send that cannot proceed for ``ws_send_timeout_seconds`` queues a 4408 close frame
  and aborts the connection, so neither the socket nor its buffers are held; any connection
  still open ``ws_send_timeout_seconds`` after the app is done is aborted too.
* ``install(app, settings)``: HTTP 507 for a full disk, 410 for an unreadable avatar file, a
  quiet end for clients that disconnect mid-upload, and security headers on every HTTP response
  (CSP, anti-framing, nosniff, no referrer).

Used with plain uvicorn (``uvicorn --factory server.app:create_app``), pass
``--http server.security:GuardedH11Protocol --ws server.security:GuardedWebSocketProtocol``;
the limits then come from the ``FASTGHA_*`` environment. docs/deploy.md lists every setting.
"""

from __future__ import annotations

import asyncio
import json
import logging
import socket
from http import HTTPStatus
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol
from uvicorn.protocols.utils import ClientDisconnected
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

from .errors import error_body
from .settings import Settings, get_settings

__all__ = [
    "GuardedH11Protocol",
    "GuardedWebSocketProtocol",
    "configure_protocols",
    "uvicorn_options",
    "install",
    "SECURITY_HEADERS",
    "CONTENT_SECURITY_POLICY",
]

log = logging.getLogger(__name__)

# The browser demo loads its own app.js and style.css, shows frames from blob: URLs and talks to
# this server over fetch and ws:/wss:. Nothing inline, nothing from elsewhere, never in a frame.
CONTENT_SECURITY_POLICY = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; "
    "connect-src 'self' ws: wss:; object-src 'none'; base-uri 'self'; form-action 'self'; frame-ancestors 'none'"
)
SECURITY_HEADERS = [
    (b"x-content-type-options", b"nosniff"),
    (b"x-frame-options", b"DENY"),
    (b"referrer-policy", b"no-referrer"),
]
# FastAPI's interactive docs load their JS from a CDN and run inline scripts: no CSP there.
_NO_CSP_PATHS = ("/docs", "/redoc")


# ---------------------------------------------------------------- limits
class _Limits:
    header_timeout = 10.0
    body_timeout = 120.0
    max_url_bytes = 8192
    max_head_bytes = 16384
    ws_send_timeout = 10.0
    ws_send_buffer = 512 * 1024
    configured = False


def configure_protocols(settings: Settings) -> None:
    """Take the connection limits from ``settings`` (``fastgha serve`` calls this before uvicorn starts)."""
    _Limits.header_timeout = float(settings.header_timeout_seconds)
    _Limits.body_timeout = float(settings.body_timeout_seconds)
    _Limits.max_url_bytes = int(settings.max_url_bytes)
    _Limits.max_head_bytes = int(settings.max_request_head_bytes)
    _Limits.ws_send_timeout = float(settings.ws_send_timeout_seconds)
    _Limits.ws_send_buffer = int(settings.ws_send_buffer_bytes)
    _Limits.configured = True


def _limits() -> type[_Limits]:
    if not _Limits.configured:  # plain uvicorn --http server.security:...: from the environment
        configure_protocols(get_settings())
    return _Limits


def uvicorn_options(settings: Settings) -> dict[str, Any]:
    """Keyword arguments for ``uvicorn.run`` that put the connection limits into the server."""
    configure_protocols(settings)
    return {
        "http": GuardedH11Protocol,
        "ws": GuardedWebSocketProtocol,
        "timeout_keep_alive": settings.keep_alive_seconds,
        "limit_concurrency": settings.limit_concurrency,
        # h11's own cap on a buffered head; ours (431) fires first, this is the backstop
        "h11_max_incomplete_event_size": settings.max_request_head_bytes + 1024,
        "ws_max_size": 2 * settings.ws_max_message_bytes,  # larger messages are refused by the protocol layer (1009)
    }


def _json_response(status: int, code: str, message: str) -> bytes:
    body = json.dumps(error_body(code, message)).encode("utf-8")
    phrase = HTTPStatus(status).phrase
    head = (
        f"HTTP/1.1 {status} {phrase}\r\ncontent-type: application/json\r\ncontent-length: {len(body)}\r\n"
        "connection: close\r\n\r\n"
    )
    return head.encode("ascii") + body


_STATUS_CODES = {400: "invalid_http", 408: "request_timeout", 413: "payload_too_large", 414: "url_too_long",
                 431: "headers_too_large", 501: "not_implemented"}  # fmt: skip


# ---------------------------------------------------------------- HTTP
class GuardedH11Protocol(H11Protocol):
    """uvicorn's ``H11Protocol`` with request-head and body deadlines, URL/head caps and JSON errors."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._lim = _limits()
        self._timer: asyncio.TimerHandle | None = None
        self._phase = "head"  # "head": waiting for a request head; "body": for its body; "app": neither
        self._head_bytes = 0  # bytes of the current head received so far
        self._first_line = bytearray()
        self._line_done = False
        self._tail = b""  # last bytes of the previous chunk: a head's blank line may straddle two
        self._h11_error: h11.RemoteProtocolError | None = None
        next_event = self.conn.next_event

        def recording_next_event():  # keep h11's reason for a 400, which uvicorn drops
            try:
                return next_event()
            except h11.RemoteProtocolError as e:
                self._h11_error = e
                raise

        self.conn.next_event = recording_next_event  # type: ignore[method-assign]

    # ------------------------------------------------------------ deadlines
    def _arm(self, phase: str) -> None:
        self._disarm()
        self._phase = phase
        if phase == "head":
            self._head_bytes, self._line_done, self._tail = 0, False, b""
            self._first_line.clear()
            self._timer = self.loop.call_later(self._lim.header_timeout, self._on_timeout, "head")
        elif phase == "body":
            self._timer = self.loop.call_later(self._lim.body_timeout, self._on_timeout, "body")

    def _disarm(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _on_timeout(self, phase: str) -> None:
        self._timer = None
        if self.transport.is_closing():
            return
        if phase == "head" and self._head_bytes == 0:
            self.transport.close()  # an idle connection: nothing to answer
            return
        what = "request head" if phase == "head" else "request body"
        limit = self._lim.header_timeout if phase == "head" else self._lim.body_timeout
        self.logger.info("%s:%s - %s not complete after %.0f s: 408", *(self.client or ("?", 0)), what, limit)
        self._refuse(408, f"the {what} did not arrive within {limit:g} s")

    def _refuse(self, status: int, message: str) -> None:
        """Answer a JSON error and close, whatever state h11 is in (the connection ends here)."""
        self._disarm()
        if self.cycle is not None and not self.cycle.response_complete:
            self.cycle.disconnected = True  # the app's response, if any, is dropped
            self.cycle.message_event.set()
            if self.cycle.response_started:  # the app has already started answering: just cut
                self.transport.close()
                return
        if not self.transport.is_closing():
            self.transport.write(_json_response(status, _STATUS_CODES.get(status, "invalid_http"), message))
            self.transport.close()

    def _sync_phase(self) -> None:
        state = self.conn.their_state
        if self._phase == "head" and state is not h11.IDLE:
            self._arm("body" if state is h11.SEND_BODY else "app")
        elif self._phase == "body" and state is not h11.SEND_BODY:
            self._arm("app")

    # ------------------------------------------------------------ uvicorn hooks
    def connection_made(self, transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm("head")

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self._phase == "head" and not self._check_head(data):
            return
        super().data_received(data)
        if not self.transport.is_closing():
            self._sync_phase()

    def _check_head(self, data: bytes) -> bool:
        """Count the bytes of the head being received; refuse an over-long target or head (False)."""
        before = self._head_bytes
        self._head_bytes += len(data)
        if not self._line_done:
            nl = data.find(b"\n")
            self._first_line += data if nl < 0 else data[:nl]
            self._line_done = nl >= 0
            parts = bytes(self._first_line).split(b" ")
            target = len(parts[1]) if len(parts) > 1 else 0
            if target > self._lim.max_url_bytes or len(self._first_line) > self._lim.max_url_bytes + 64:
                self.logger.info("%s:%s - request target over %d bytes: 414", *(self.client or ("?", 0)), self._lim.max_url_bytes)
                self._refuse(414, f"the request target is longer than {self._lim.max_url_bytes} bytes")
                return False
            if self._line_done:
                self._first_line.clear()
        buf = self._tail + data
        end = buf.find(b"\r\n\r\n")  # the head may end in this chunk, a body after it
        head_len = before - len(self._tail) + end + 4 if end >= 0 else self._head_bytes
        self._tail = buf[-3:]
        if head_len > self._lim.max_head_bytes:
            self.logger.info("%s:%s - request head over %d bytes: 431", *(self.client or ("?", 0)), self._lim.max_head_bytes)
            self._refuse(431, f"the request line and headers are longer than {self._lim.max_head_bytes} bytes")
            return False
        return True

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing() and self.conn.their_state is h11.IDLE:
            self._arm("head")  # the next request on this keep-alive connection
            self._sync_phase()  # a pipelined request may already be in

    def handle_websocket_upgrade(self, event: h11.Request) -> None:
        self._disarm()
        self._phase = "app"
        super().handle_websocket_upgrade(event)

    def send_400_response(self, msg: str) -> None:
        e = self._h11_error
        status = e.error_status_hint if e is not None and 400 <= e.error_status_hint < 600 else 400
        detail = str(e) if e is not None and str(e) else msg
        self.logger.info("%s:%s - invalid HTTP request (%s): %d", *(self.client or ("?", 0)), detail[:120], status)
        self._refuse(status, f"invalid HTTP request: {detail}")


# ---------------------------------------------------------------- WebSocket
class GuardedWebSocketProtocol(WebSocketsSansIOProtocol):
    """uvicorn's websockets protocol with a send deadline and no connection outliving its app."""

    SLOW_CONSUMER = 4408

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._lim = _limits()
        self.close_timeout = min(self.close_timeout, self._lim.ws_send_timeout)

    def connection_made(self, transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        sock = transport.get_extra_info("socket")
        if sock is not None and self._lim.ws_send_buffer > 0:
            try:  # a bounded send queue: the kernel's share (it doubles the value) plus the transport's 64 KiB
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self._lim.ws_send_buffer)
            except OSError:
                pass

    def _drop(self, code: int, reason: str) -> None:
        """Queue a close frame behind whatever is unread, then abort the connection shortly."""
        if self.disconnected:
            return
        if not self.close_sent:
            try:
                self.conn.send_close(code, reason)
                self.transport.write(b"".join(self.conn.data_to_send()))
            except Exception:  # the connection's state may not allow a close frame: abort anyway
                pass
            self.close_sent = True
            self.queue.put_nowait({"type": "websocket.disconnect", "code": code, "reason": reason})
        self.loop.call_later(1.0, self._abort)

    def _abort(self) -> None:
        if not self.disconnected:
            self.transport.abort()

    async def send(self, message: Any) -> None:
        if self.handshake_complete and not self.disconnected and not self.writable.is_set():
            if message["type"] == "websocket.close":  # the peer reads nothing: do not wait to say goodbye
                self._drop(int(message.get("code", 1000)), str(message.get("reason", "") or ""))
                return
            try:  # one second past the app's own deadline (streaming.py), which answers first with a log line
                await asyncio.wait_for(self.writable.wait(), self._lim.ws_send_timeout + 1.0)
            except asyncio.TimeoutError:
                self.logger.info("%s:%s - WebSocket client read nothing for %.0f s: closing (4408)", *(self.client or ("?", 0)), self._lim.ws_send_timeout)
                self._drop(self.SLOW_CONSUMER, "slow_consumer")
                raise ClientDisconnected() from None
        await super().send(message)

    def keepalive_timeout(self) -> None:
        super().keepalive_timeout()
        self.loop.call_later(self._lim.ws_send_timeout, self._abort)

    async def run_asgi(self) -> None:
        await super().run_asgi()
        # transport.close() waits for the peer to take the buffered data; a peer that never reads
        # would hold the socket for ever
        self.loop.call_later(self._lim.ws_send_timeout, self._abort)


# ---------------------------------------------------------------- app level
class SecurityHeadersMiddleware:
    """Adds ``SECURITY_HEADERS`` to every HTTP response and the CSP to all but the API docs."""

    def __init__(self, app: Any) -> None:
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path = scope.get("path", "")
        csp = not path.startswith(_NO_CSP_PATHS)

        async def send_with_headers(message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                present = {k.lower() for k, _ in headers}
                extra = list(SECURITY_HEADERS)
                if csp:
                    extra.append((b"content-security-policy", CONTENT_SECURITY_POLICY.encode("ascii")))
                headers += [(k, v) for k, v in extra if k not in present]
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_headers)


def install(app: Any, settings: Settings) -> None:
    """Register the error handlers and the security-header middleware on a FastAPI ``app``."""
    from fastapi.responses import JSONResponse, Response
    from starlette.requests import ClientDisconnect

    from .store import AvatarUnreadableError, StorageFullError

    async def storage_full(request, exc: StorageFullError):
        log.error("%s %s: %s", request.method, request.url.path, exc.strerror or exc)
        return JSONResponse(error_body("insufficient_storage", "the server has no disk space left to store this avatar; nothing was stored"), status_code=507)

    async def unreadable(request, exc: AvatarUnreadableError):
        return JSONResponse(error_body("avatar_unreadable", "this avatar's stored file is damaged and was set aside; create it again"), status_code=410)

    async def disconnected(request, exc: ClientDisconnect):
        log.info("%s %s: the client disconnected before sending its whole request", request.method, request.url.path)
        return Response(status_code=400)  # nobody is listening

    app.add_exception_handler(StorageFullError, storage_full)
    app.add_exception_handler(AvatarUnreadableError, unreadable)
    app.add_exception_handler(ClientDisconnect, disconnected)
    app.add_middleware(SecurityHeadersMiddleware)
