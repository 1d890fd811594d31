"""Keep avatar tokens out of logs: uvicorn logs request paths with their query strings."""

from __future__ import annotations

import logging
import re

__all__ = ["RedactTokens", "install_token_redaction"]

_TOKEN_RE = re.compile(r"(token=)[^&\s\"']+")


class RedactTokens(logging.Filter):
    """Replaces ``token=<value>`` in a record's message and arguments with ``token=***``."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str) and "token=" in record.msg:
            record.msg = _TOKEN_RE.sub(r"\1***", record.msg)
        if record.args:
            args = record.args if isinstance(record.args, tuple) else (record.args,)
            if any(isinstance(a, str) and "token=" in a for a in args):
                record.args = tuple(_TOKEN_RE.sub(r"\1***", a) if isinstance(a, str) else a for a in args)
        return True


def install_token_redaction() -> None:
    """Attach the filter to uvicorn's loggers (idempotent)."""
    for name in ("uvicorn.access", "uvicorn.error"):
        lg = logging.getLogger(name)
        if not any(isinstance(f, RedactTokens) for f in lg.filters):
            lg.addFilter(RedactTokens())
