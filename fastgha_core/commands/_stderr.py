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

The server tracks photos with the same graphs (``server/tracking.py``) and is not a command that
ends: there, :func:`mediapipe_start_up_quiet` does the same only while a graph is built and until
its first call has run (``tracking/faces.py`` ``QuietGraph``), which is when the lines come; a
server's stderr is not sent through a Python thread for its whole life (a native crash's last words
would be lost with it). Setting ``GLOG_minloglevel`` / ``TF_CPP_MIN_LOG_LEVEL`` before the import
was tried and does not reach them (mediapipe 0.10.21).
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import threading

__all__ = ["NOISE", "is_noise", "native_stderr_filtered", "mediapipe_start_up_quiet"]

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


def _install():
    """Send fd 2 through a pipe to a thread running :func:`_forward`; the state for :func:`_remove`,
    or None when fd 2 cannot be redirected (no such descriptor)."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        return None
    try:
        r, w = os.pipe()
    except OSError:  # out of descriptors: unfiltered rather than failing the command
        os.close(saved)
        return None
    os.dup2(w, 2)
    os.close(w)
    reader = threading.Thread(target=_forward_and_close, args=(r, saved), name="fastgha-stderr-filter", daemon=True)
    reader.start()
    return r, saved, reader


def _forward_and_close(src: int, dst: int) -> None:
    """:func:`_forward`, then close both descriptors. The reader owns them: a child process started
    inside the block inherits fd 2 (the pipe) and may outlive it, so the pipe can end after
    :func:`_remove` has returned; closing them there would let their numbers be reused by files opened
    later, into which the reader would then write the child's late lines (seen with a
    ``sh -c 'sleep 7; echo x >&2'`` child)."""
    try:
        _forward(src, dst)
    finally:
        os.close(src)
        os.close(dst)


#: Seconds :func:`_remove` waits for the pipe to drain (all at once unless a child process still holds it)
DRAIN_TIMEOUT_S = 5.0


def _remove(state) -> None:
    _r, saved, reader = state
    with contextlib.suppress(Exception):
        sys.stderr.flush()
    os.dup2(saved, 2)  # closes the pipe's last write end (unless a child holds it): the reader drains it, closes r and saved, and ends
    reader.join(timeout=DRAIN_TIMEOUT_S)  # a child's later lines still reach the real stderr through the reader


@contextlib.contextmanager
def native_stderr_filtered(enabled: bool = True):
    """Within the block, lines of :data:`NOISE` written to fd 2 (by C++ or Python) are dropped and
    the rest reach the real stderr unchanged. Not re-entrant across threads (use
    :func:`mediapipe_start_up_quiet` there); a no-op when ``enabled`` is false or fd 2 cannot be
    redirected (no such descriptor)."""
    state = _install() if enabled else None
    try:
        yield
    finally:
        if state is not None:
            _remove(state)


_shared_lock = threading.Lock()
_shared_users = 0
_shared_state = None


@contextlib.contextmanager
def mediapipe_start_up_quiet():
    """:func:`native_stderr_filtered` for the library's own MediaPipe calls (``tracking/faces.py``,
    ``tracking/silhouette.py``), which also run inside the server, where other threads write to
    stderr at the same time: process-wide and thread-safe, so concurrent or nested blocks share one
    filter, put in place by the first to enter and taken away by the last to leave. Other threads'
    lines written meanwhile pass through it unchanged. Inside a command's own filter (``fastgha
    track``) it stacks on top and comes off first. Does nothing when the root logger is at DEBUG
    (``fastgha -v ...``: the lines are then shown, as the commands' filter does)."""
    import logging

    global _shared_users, _shared_state
    if logging.getLogger().isEnabledFor(logging.DEBUG):
        yield
        return
    with _shared_lock:
        if _shared_users == 0:
            _shared_state = _install()
        _shared_users += 1
    try:
        yield
    finally:
        with _shared_lock:
            _shared_users -= 1
            if _shared_users == 0 and _shared_state is not None:
                state, _shared_state = _shared_state, None
                _remove(state)
