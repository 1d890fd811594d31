"""Keep MediaPipe's start-up chatter off a command's terminal.

MediaPipe (the ``faces`` extra) writes lines like these to file descriptor 2 from C++ when it builds
a Face Mesh or selfie-segmentation graph, whatever ``GLOG_minloglevel`` / ``TF_CPP_MIN_LOG_LEVEL``
say (its absl logging is not initialised, so no setting reaches it)::

    INFO: Created TensorFlow Lite XNNPACK delegate for CPU.
    WARNING: All log messages before absl::InitializeLog() is called are written to STDERR
    W0000 00:00:1796068287.472275    4094 inference_feedback_manager.cc:114] Feedback manager requires ...
    W0000 00:00:1796068287.487334    4093 landmark_projection_calculator.cc:186] Using NORM_RECT without ...

They are harmless and say nothing a user can act on, but read as warnings in the output of
``fastgha track``. :func:`native_stderr_filtered` sends fd 2 through a pipe for the duration of a
command and drops exactly those lines (the patterns below); everything else, Python's own log lines
and tqdm's ``\\r`` progress updates included, is passed on as it arrives.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import threading

__all__ = ["NOISE", "is_noise", "native_stderr_filtered"]

#: Whole lines (without their newline) that are dropped: MediaPipe's known start-up messages only.
NOISE = (
    re.compile(rb"INFO: Created TensorFlow Lite XNNPACK delegate for CPU\.\r?"),
    re.compile(rb"WARNING: All log messages before absl::InitializeLog\(\) is called are written to STDERR\r?"),
    re.compile(rb"W\d{4} [\d:.]+\s+\d+ (inference_feedback_manager\.cc|landmark_projection_calculator\.cc):\d+\] .*"),
)
# how such a line can begin: a partial line that may still become one is held until its newline
_STARTS = (b"INFO: Created TensorFlow Lite", b"WARNING: All log messages before absl", b"W")


def is_noise(line: bytes) -> bool:
    """Whether ``line`` (one line, without ``\\n``) is one of :data:`NOISE`."""
    return any(p.fullmatch(line) for p in NOISE)


def _may_become_noise(partial: bytes) -> bool:
    return any(s.startswith(partial) or partial.startswith(s) for s in _STARTS)


def _forward(src: int, dst: int) -> None:
    """Copy ``src`` to ``dst`` without the noise lines until ``src`` ends. Never stops reading early
    (a writer to a full pipe would block): when ``dst`` fails (a closed terminal, ``| head``) the rest
    is read and discarded, and an unexpected error passes the rest through unfiltered."""

    def write(data: bytes) -> None:
        nonlocal dst
        if dst is not None and data:
            try:
                os.write(dst, data)
            except OSError:
                dst = None

    buf = b""
    while True:
        try:
            chunk = os.read(src, 65536)
        except OSError:
            return
        if not chunk:
            break
        try:
            buf += chunk
            *lines, buf = buf.split(b"\n")
            out = b"".join(line + b"\n" for line in lines if not is_noise(line))
            if buf and not _may_become_noise(buf.rsplit(b"\r", 1)[-1]):  # e.g. tqdm's "\rrefining: 40%": show it now
                out, buf = out + buf, b""
        except Exception:  # pragma: no cover - never seen; filtering is not worth losing output for
            out, buf = buf, b""
        write(out)
    if not is_noise(buf):
        write(buf)


@contextlib.contextmanager
def native_stderr_filtered(enabled: bool = True):
    """Within the block, lines of :data:`NOISE` written to fd 2 (by C++ or Python) are dropped and
    the rest reach the real stderr unchanged. Not re-entrant; a no-op when ``enabled`` is false or
    fd 2 cannot be redirected (no such descriptor)."""
    if not enabled:
        yield
        return
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        yield
        return
    r, w = os.pipe()
    os.dup2(w, 2)
    os.close(w)
    reader = threading.Thread(target=_forward, args=(r, saved), name="fastgha-stderr-filter", daemon=True)
    reader.start()
    try:
        yield
    finally:
        with contextlib.suppress(Exception):
            sys.stderr.flush()
        os.dup2(saved, 2)  # closes the pipe's last write end: the reader drains it and ends
        reader.join(timeout=5)
        os.close(r)
        os.close(saved)
