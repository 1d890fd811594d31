"""Machine-readable errors: one exception type for HTTP, one JSON shape, one list of codes.

HTTP errors are ``{"error": {"code": "...", "message": "..."}}`` with a 4xx status;
WebSocket errors are ``{"type": "error", "code": "...", "message": "..."}``. The codes and
the WebSocket close codes are documented in ``docs/protocol.md``.
"""

from __future__ import annotations

__all__ = ["ApiError", "error_body", "CloseCode"]


class ApiError(Exception):
    """A client error with an HTTP status, a stable ``code`` and a human message."""

    def __init__(self, status: int, code: str, message: str) -> None:
        super().__init__(message)
        self.status = int(status)
        self.code = code
        self.message = message

    def body(self) -> dict:
        return error_body(self.code, self.message)


def error_body(code: str, message: str) -> dict:
    return {"error": {"code": code, "message": message}}


class CloseCode:
    """WebSocket close codes used by the stream endpoint."""

    NORMAL = 1000
    GOING_AWAY = 1001  # the server is shutting down (uvicorn itself uses 1012 on restart)
    MESSAGE_TOO_BIG = 1009  # a client message exceeded ws_max_message_bytes
    INTERNAL_ERROR = 1011
    SERVICE_RESTART = 1012  # sent by uvicorn on graceful shutdown
    BAD_REQUEST = 4400  # invalid avatar id
    UNAUTHORIZED = 4401  # missing or wrong token
    FORBIDDEN_ORIGIN = 4403  # browser Origin not among the configured origins (FASTGHA_CORS_ORIGINS)
    NOT_FOUND = 4404  # unknown avatar
    SLOW_CONSUMER = 4408  # the client read nothing for ws_send_timeout_seconds
    GONE = 4410  # the avatar's file is unreadable (set aside in quarantine/)
    CONFLICT = 4409  # avatar made by another model
    RATE_ABUSE = 4429  # message rate far above the limit
    AT_CAPACITY = 4503  # too many concurrent streams (per avatar or in total)
