"""Load test of a FastGHA server: N concurrent WebSocket streams at a target request rate.

Each client opens one stream and sends frame requests on a fixed clock (``rate_hz``, open
loop, compact binary form; with ``closed_loop`` a stream sends its next request only when the
frame of the previous one is back, as the browser demo does, still at most ``rate_hz``), each with a different expression and a camera orbiting the head,
at ``size`` x ``size`` pixels. The server renders latest-wins, so requests sent faster than it
renders are dropped; the tool measures what is delivered. It stops by itself: clients,
duration, rate and the total number of messages are bounded, and it refuses hosts other
than loopback unless ``allow_remote`` is set.

Report (``run_loadtest`` returns it; ``fastgha loadtest --json`` writes it)::

    config      the LoadTestConfig fields
    server      url, model, device, expression_space, expression_dim
    avatars     count, reconstruction_ms [per avatar]
    aggregate   clients, duration_s, requests_sent, frames_received, dropped_requests,
                unanswered_requests, delivered_fps (all clients), delivered_fps_per_client,
                latency_ms {p50, p95, p99, mean, max}, server_total_ms {p50, p95, p99, mean, max},
                server_render_ms {...}, outside_server_ms {...}, ping_rtt_ms {...},
                client_loop_lag_ms {...}, latency_note, bytes_per_s, errors, error_messages
    clients     one entry per client: client, avatar_id, requests_sent, frames_received,
                dropped_requests, unanswered_requests, delivered_fps, latency_ms {...},
                server_total_ms {...}, bytes_per_s, errors, error_messages
    timeline    bucket_s, t_s, fps, latency_p50_ms, latency_p95_ms, server_total_p50_ms,
                bytes_per_s (aggregate, per bucket)

``dropped_requests`` are requests the server dropped (the ``dropped`` counter of the last
frame header); ``unanswered_requests`` are those neither answered nor reported dropped when
the stream ended (normally 0).

Latency (``latency_ms``) is measured per answered request on the client's clock: from the
moment its message is written to the socket to the moment the frame that answers it (same
``seq``) is read; requests the server dropped have no latency. Beside it, from the frame headers,
the server's own figures for the same frames: ``server_total_ms`` (from taking the request to
sending the frame: waiting for a render worker, deformation, rasterisation, JPEG) and
``server_render_ms`` (deformation + rasterisation only). ``outside_server_ms`` = latency -
server total, per frame: the time a request waited before the server took it (in socket buffers,
the server's input queue and the latest-wins slot) plus transit. About once a second each stream
also sends a ``ping``, which queues behind the requests on the same socket; its round trip
(``ping_rtt_ms``) shows how long the server takes to read what was sent. Request messages are built before streaming starts, so
the load generator's own work per request is one socket write; ``client_loop_lag_ms`` is how late
its event loop woke up (a 10 ms tick), i.e. how much of the latency may be the load generator's
own delay (``latency_note`` says so when it is large: run it on another machine, or give the
server a lower priority, e.g. ``nice``).
"""

from __future__ import annotations

import asyncio
import ipaddress
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Sequence
from urllib.parse import urlsplit

import numpy as np

from .client import Avatar, FastGHAClient, orbit_camera, pack_request, unpack_frame

__all__ = [
    "LoadTestConfig",
    "run_loadtest",
    "check_target",
    "plot_report",
    "MAX_CLIENTS",
    "MAX_DURATION_S",
    "MAX_RATE_HZ",
    "MAX_MESSAGES",
]

log = logging.getLogger(__name__)

MAX_CLIENTS = 256
MAX_DURATION_S = 3600.0
MAX_RATE_HZ = 240.0  # the server's default per-socket message limit
MAX_MESSAGES = 2_000_000  # requests over all clients in one run
MAX_SIZE = 4096
DRAIN_S = 10.0  # after the last request, wait this long at most for its frame
_MAX_ERROR_MESSAGES = 20


@dataclass
class LoadTestConfig:
    """One load-test run."""

    url: str  # server base URL, http://host:port
    clients: int = 4  # concurrent WebSocket streams
    duration_s: float = 10.0  # sending time per client
    rate_hz: float = 30.0  # requests per second per client
    size: int = 256  # frame width and height
    shared_avatar: bool = False  # all clients stream one avatar (else one avatar per client)
    api_key: str | None = None  # for creating avatars
    allow_remote: bool = False  # permit a non-loopback host
    bucket_s: float = 1.0  # timeline resolution
    jpeg_quality: int | None = None  # per-socket option; None = the server's default
    closed_loop: bool = False  # one request in flight per stream (as the browser demo), at most rate_hz

    def validate(self) -> None:
        if not 1 <= self.clients <= MAX_CLIENTS:
            raise ValueError(f"clients must be in 1..{MAX_CLIENTS}, got {self.clients}")
        if not 0 < self.duration_s <= MAX_DURATION_S:
            raise ValueError(f"duration must be in (0, {MAX_DURATION_S:g}] seconds, got {self.duration_s}")
        if not 0 < self.rate_hz <= MAX_RATE_HZ:
            raise ValueError(f"rate must be in (0, {MAX_RATE_HZ:g}] Hz per client (the server's per-socket limit), got {self.rate_hz}")
        if not 16 <= self.size <= MAX_SIZE:
            raise ValueError(f"size must be in 16..{MAX_SIZE}, got {self.size}")
        total = self.clients * math.ceil(self.duration_s * self.rate_hz)
        if total > MAX_MESSAGES:
            raise ValueError(f"clients x duration x rate = {total} requests exceeds the bound of {MAX_MESSAGES}; lower one of them")
        if not 0 < self.bucket_s <= self.duration_s:
            raise ValueError(f"bucket_s must be in (0, duration], got {self.bucket_s}")
        check_target(self.url, self.allow_remote)


def check_target(url: str, allow_remote: bool) -> str:
    """The host of ``url``; ``ValueError`` unless it is loopback or ``allow_remote`` is set."""
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"--url must look like http://host:port, got {url!r}")
    host = parts.hostname
    loopback = host == "localhost"
    try:
        loopback = loopback or ipaddress.ip_address(host).is_loopback
    except ValueError:
        pass
    if not loopback and not allow_remote:
        raise ValueError(
            f"refusing to load-test {host!r}: only loopback hosts (127.0.0.1, ::1, localhost) are targeted by default; "
            "pass --allow-remote if you own that server"
        )
    return host


def _stats(values: Sequence[float]) -> dict:
    if not len(values):
        return {"p50": None, "p95": None, "p99": None, "mean": None, "max": None}
    a = np.asarray(values, np.float64)
    return {
        "p50": round(float(np.percentile(a, 50)), 3),
        "p95": round(float(np.percentile(a, 95)), 3),
        "p99": round(float(np.percentile(a, 99)), 3),
        "mean": round(float(a.mean()), 3),
        "max": round(float(a.max()), 3),
    }


@dataclass
class _ClientResult:
    index: int
    avatar_id: str
    sent: int = 0
    received: int = 0
    dropped: int = 0
    unanswered: int = 0
    bytes: int = 0
    errors: int = 0
    error_messages: list[str] = field(default_factory=list)
    t_recv: list[float] = field(default_factory=list)  # seconds since the global start
    latency_ms: list[float] = field(default_factory=list)
    server_total_ms: list[float] = field(default_factory=list)
    server_render_ms: list[float] = field(default_factory=list)
    ping_ms: list[float] = field(default_factory=list)  # ping -> pong round trips on the stream socket
    frame_bytes: list[int] = field(default_factory=list)

    def error(self, msg: str) -> None:
        self.errors += 1
        if len(self.error_messages) < _MAX_ERROR_MESSAGES:
            self.error_messages.append(msg)


def _expression(space: str, dim: int, t: float, phase: float) -> np.ndarray:
    """A smoothly varying expression ``[E]``: weights in [0, 0.8] for ict53, small values otherwise."""
    j = np.arange(dim)
    wave = np.sin(2 * np.pi * 0.5 * t + phase + 0.7 * j)  # [E]
    if space == "ict53":
        return (0.4 + 0.4 * wave).astype(np.float32)
    return (0.1 * wave).astype(np.float32)


def _requests(cfg: LoadTestConfig, space: str, dim: int, index: int) -> list[bytes]:
    """Client ``index``'s request messages, packed ahead of time (binary form, seq = position): a
    changing expression and a camera orbiting the head, evaluated at each request's scheduled time."""
    period = 1.0 / cfg.rate_hz
    phase = 2 * np.pi * index / max(1, cfg.clients)
    out = []
    for seq in range(math.ceil(cfg.duration_s * cfg.rate_hz)):
        t = seq * period
        yaw = 25.0 * math.sin(2 * math.pi * 0.2 * t + phase)
        pitch = 8.0 * math.sin(2 * math.pi * 0.13 * t + phase)
        cam = orbit_camera(yaw, pitch, 1.0 + 0.1 * math.sin(2 * math.pi * 0.07 * t), width=cfg.size, height=cfg.size)
        out.append(pack_request(seq, _expression(space, dim, t, phase), cam))
    return out


async def _loop_lag(samples: list[float], stop: asyncio.Event, tick: float = 0.01) -> None:
    """How late this event loop wakes up from a ``tick``-second sleep, in ms, until ``stop`` is set."""
    while not stop.is_set():
        t = time.perf_counter()
        await asyncio.sleep(tick)
        samples.append(max(0.0, 1e3 * (time.perf_counter() - t - tick)))


async def _run_client(
    client: FastGHAClient, avatar: Avatar, res: _ClientResult, cfg: LoadTestConfig, messages: list[bytes], t0: float
) -> None:
    period = 1.0 / cfg.rate_hz
    n_requests = len(messages)
    ping_every = max(1, round(cfg.rate_hz * PING_INTERVAL_S))  # requests between pings
    sent_at: dict[int, float] = {}
    last_seq_answered = -1
    done_sending = asyncio.Event()
    frame_back = asyncio.Event()  # closed loop: set when the request in flight is answered
    frame_back.set()
    try:
        async with client.connect(avatar) as ws:
            ready = json.loads(await asyncio.wait_for(ws.recv(), 30))
            if ready.get("type") != "ready":
                res.error(f"no ready message: {ready}")
                return
            if cfg.jpeg_quality is not None:
                await ws.send(json.dumps({"type": "options", "jpeg_quality": cfg.jpeg_quality}))

            async def sender() -> None:
                start = begin = time.perf_counter()
                for seq in range(n_requests):
                    if cfg.closed_loop:  # one request in flight: the next goes out when its frame is back
                        await frame_back.wait()
                        frame_back.clear()
                        if time.perf_counter() - begin >= cfg.duration_s:
                            break
                    delay = start + seq * period - time.perf_counter()
                    if delay > 0:
                        await asyncio.sleep(delay)
                    elif delay < -period:  # fell behind (e.g. a stall): restart the clock, no burst
                        start = time.perf_counter() - seq * period
                    sent_at[seq] = time.perf_counter()  # the write below hands the message to the socket
                    await ws.send(messages[seq])
                    res.sent += 1
                    if seq % ping_every == ping_every // 2:  # a ping queues behind the requests: its round trip shows the wait
                        await ws.send(json.dumps({"type": "ping", "t": time.perf_counter()}))
                done_sending.set()

            send_task = asyncio.create_task(sender())
            try:
                while True:
                    if done_sending.is_set() and last_seq_answered >= res.sent - 1:
                        break
                    timeout = DRAIN_S if done_sending.is_set() else max(DRAIN_S, cfg.duration_s + DRAIN_S)
                    # wait for a message, or for the sender to finish with everything answered (a closed-loop
                    # sender may stop after the last frame has already come back); cancelling recv() is safe
                    recv = asyncio.ensure_future(ws.recv())
                    waiting = {recv}
                    if not done_sending.is_set():
                        waiting.add(asyncio.ensure_future(done_sending.wait()))
                    try:
                        done, _ = await asyncio.wait(waiting, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
                    finally:
                        for f in waiting - {recv}:
                            f.cancel()
                    if recv not in done:
                        recv.cancel()
                        await asyncio.gather(recv, return_exceptions=True)
                        if done:  # the sender finished: re-check whether everything is answered
                            continue
                        res.error(f"no frame within {timeout:.0f} s")
                        break
                    msg = recv.result()
                    now = time.perf_counter()
                    if isinstance(msg, str):
                        obj = json.loads(msg)
                        if obj.get("type") == "error":
                            res.error(f"{obj.get('code')}: {obj.get('message')}")
                            frame_back.set()  # that request will not be answered
                        elif obj.get("type") == "pong" and isinstance(obj.get("t"), float):
                            res.ping_ms.append(1e3 * (now - obj["t"]))
                        continue
                    header, _ = unpack_frame(msg)
                    seq = int(header["seq"])
                    frame_back.set()
                    last_seq_answered = seq
                    res.received += 1
                    res.bytes += len(msg)
                    res.dropped = int(header.get("dropped", res.dropped))
                    res.t_recv.append(now - t0)
                    res.latency_ms.append(1e3 * (now - sent_at.pop(seq, now)))
                    res.server_total_ms.append(float(header.get("total_ms", float("nan"))))
                    res.server_render_ms.append(float(header.get("render_ms", float("nan"))))
                    res.frame_bytes.append(len(msg))
                    for s in [s for s in sent_at if s < seq]:
                        del sent_at[s]
                    if send_task.done() and send_task.exception() is not None:
                        raise send_task.exception()  # type: ignore[misc]
            finally:
                send_task.cancel()
                await asyncio.gather(send_task, return_exceptions=True)
    except Exception as e:  # connection refused, closed by the server (e.g. 4503), protocol errors
        code = getattr(getattr(e, "rcvd", None), "code", None)
        reason = getattr(getattr(e, "rcvd", None), "reason", "")
        if code:  # the server's close code and reason say it all (docs/protocol.md, Close codes)
            hint = " (retry later; with --shared-avatar, at most the server's FASTGHA_MAX_STREAMS_PER_AVATAR clients)" if code == 4503 else ""
            res.error(f"closed by the server: {code} {reason}{hint}")
        else:
            res.error(f"{type(e).__name__}: {e}")
    res.unanswered = max(0, res.sent - res.received - res.dropped)


def _timeline(results: list[_ClientResult], duration: float, bucket: float) -> dict:
    t_end = max([duration] + [r.t_recv[-1] for r in results if r.t_recv])
    n = max(1, math.ceil(t_end / bucket))
    frames = np.zeros(n, np.int64)
    nbytes = np.zeros(n, np.float64)
    lats: list[list[float]] = [[] for _ in range(n)]
    srvs: list[list[float]] = [[] for _ in range(n)]
    for r in results:
        for t, lat, srv, b in zip(r.t_recv, r.latency_ms, r.server_total_ms, r.frame_bytes):
            k = min(n - 1, int(t / bucket))
            frames[k] += 1
            nbytes[k] += b
            lats[k].append(lat)
            if math.isfinite(srv):
                srvs[k].append(srv)
    return {
        "bucket_s": bucket,
        "t_s": [round((k + 0.5) * bucket, 3) for k in range(n)],
        "fps": [round(float(f) / bucket, 3) for f in frames],
        "latency_p50_ms": [round(float(np.percentile(v, 50)), 3) if v else None for v in lats],
        "latency_p95_ms": [round(float(np.percentile(v, 95)), 3) if v else None for v in lats],
        "server_total_p50_ms": [round(float(np.percentile(v, 50)), 3) if v else None for v in srvs],
        "bytes_per_s": [round(float(b) / bucket, 1) for b in nbytes],
    }


PING_INTERVAL_S = 1.0  # each stream sends a ping about once a second
LAG_NOTE_FRACTION = 0.1  # the load generator's loop lag (p95) above this fraction of the latency p50 is reported


def latency_note(latency: dict, lag: dict) -> str | None:
    """A warning when the load generator's own event-loop lag (p95) is a noticeable part of the
    measured latency (p50): then the client, not the server, adds to the figures. None otherwise."""
    if latency.get("p50") is None or lag.get("p95") is None:
        return None
    if lag["p95"] <= LAG_NOTE_FRACTION * latency["p50"]:
        return None
    return (f"the load generator's event loop ran up to {lag['p95']:.0f} ms late (p95), against a latency p50 of "
            f"{latency['p50']:.0f} ms: part of the latency is the load generator's own delay; run it on another "
            "machine or give the server a lower priority (nice)")


def run_loadtest(
    cfg: LoadTestConfig,
    images: Sequence[Any],
    cameras: Sequence[dict],
    masks: Sequence[Any] | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """Create the avatar(s) from ``images``/``cameras``, run the streams, delete the avatars, return the report."""
    cfg.validate()
    say = progress or (lambda m: log.info("%s", m))
    client = FastGHAClient(cfg.url, api_key=cfg.api_key)
    info = client.model_info()
    space, dim = str(info["expression_space"]), int(info["expression_dim"])
    n_avatars = 1 if cfg.shared_avatar else cfg.clients
    say(f"creating {n_avatars} avatar(s) on {cfg.url} (model {info['name']}, {info['device']})")
    avatars: list[Avatar] = []
    try:
        for _ in range(n_avatars):
            avatars.append(client.create_avatar(images, cameras, masks))
        say(f"streaming: {cfg.clients} client(s) x {cfg.rate_hz:g} Hz for {cfg.duration_s:g} s at {cfg.size}x{cfg.size}")
        results = [_ClientResult(i, avatars[0 if cfg.shared_avatar else i].avatar_id) for i in range(cfg.clients)]

        plans = [_requests(cfg, space, dim, r.index) for r in results]  # no message building while streaming
        lag: list[float] = []

        async def main() -> None:
            stop = asyncio.Event()
            monitor = asyncio.create_task(_loop_lag(lag, stop))
            t0 = time.perf_counter()
            try:
                await asyncio.gather(
                    *(_run_client(client, avatars[0 if cfg.shared_avatar else r.index], r, cfg, plans[r.index], t0) for r in results)
                )
            finally:
                stop.set()
                await monitor

        asyncio.run(main())
    finally:
        for av in avatars:
            try:
                client.delete(av)
            except Exception as e:  # the report still matters more than the clean-up
                log.warning("could not delete avatar %s: %s", av.avatar_id, e)

    dur = cfg.duration_s
    per_client = [
        {
            "client": r.index,
            "avatar_id": r.avatar_id,
            "requests_sent": r.sent,
            "frames_received": r.received,
            "dropped_requests": r.dropped,
            "unanswered_requests": r.unanswered,
            "delivered_fps": round(r.received / dur, 3),
            "latency_ms": _stats(r.latency_ms),
            "server_total_ms": _stats([v for v in r.server_total_ms if math.isfinite(v)]),
            "bytes_per_s": round(r.bytes / dur, 1),
            "errors": r.errors,
            "error_messages": r.error_messages,
        }
        for r in results
    ]
    all_lat = [v for r in results for v in r.latency_ms]
    all_srv = [v for r in results for v in r.server_total_ms if math.isfinite(v)]
    all_render = [v for r in results for v in r.server_render_ms if math.isfinite(v)]
    outside = [lat - srv for r in results for lat, srv in zip(r.latency_ms, r.server_total_ms) if math.isfinite(srv)]
    received = sum(r.received for r in results)
    lag_stats = _stats(lag)
    return {
        "config": {k: v for k, v in asdict(cfg).items() if k != "api_key"},
        "server": {"url": cfg.url, "model": info["name"], "device": info["device"], "expression_space": space, "expression_dim": dim},
        "avatars": {"count": len(avatars), "reconstruction_ms": [a.reconstruction_ms for a in avatars]},
        "aggregate": {
            "clients": cfg.clients,
            "duration_s": dur,
            "requests_sent": sum(r.sent for r in results),
            "frames_received": received,
            "dropped_requests": sum(r.dropped for r in results),
            "unanswered_requests": sum(r.unanswered for r in results),
            "delivered_fps": round(received / dur, 3),
            "delivered_fps_per_client": round(received / dur / cfg.clients, 3),
            "latency_ms": _stats(all_lat),
            "server_total_ms": _stats(all_srv),
            "server_render_ms": _stats(all_render),
            "outside_server_ms": _stats(outside),
            "client_loop_lag_ms": lag_stats,
            "ping_rtt_ms": _stats([v for r in results for v in r.ping_ms]),
            "latency_note": latency_note(_stats(all_lat), lag_stats),
            "bytes_per_s": round(sum(r.bytes for r in results) / dur, 1),
            "errors": sum(r.errors for r in results),
            "error_messages": [m for r in results for m in r.error_messages][:_MAX_ERROR_MESSAGES],
        },
        "clients": per_client,
        "timeline": _timeline(results, dur, cfg.bucket_s),
    }


def plot_report(report: dict, path: str) -> None:
    """A PNG of delivered FPS and latency over time (matplotlib, Agg backend). Legends sit to the
    right of the plots, outside the data; the latency panel shows the server's own time (p50) beside
    the client-measured request -> frame latency."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tl, agg, cfg = report["timeline"], report["aggregate"], report["config"]
    t = np.asarray(tl["t_s"])
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    ax1.plot(t, tl["fps"], label="delivered\n(all clients)")
    ax1.axhline(cfg["clients"] * cfg["rate_hz"], color="grey", ls="--", label="requested")
    ax1.set_ylabel("frames / s")
    ax1.set_ylim(bottom=0)
    ax1.set_title(
        f"{cfg['clients']} client(s) x {cfg['rate_hz']:g} Hz at {cfg['size']}², model {report['server']['model']} "
        f"({report['server']['device']}): {agg['delivered_fps']:.1f} fps, {agg['errors']} errors"
    )
    ax1.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small", frameon=False)
    ax1.grid(alpha=0.3)
    nan = lambda vs: [np.nan if v is None else v for v in vs]  # noqa: E731
    # markers: a bucket between empty ones (no frame arrived) is still drawn
    ax2.plot(t, nan(tl["latency_p50_ms"]), marker="o", ms=3, label="latency p50")
    ax2.plot(t, nan(tl["latency_p95_ms"]), marker="o", ms=3, label="latency p95")
    if "server_total_p50_ms" in tl:
        ax2.plot(t, nan(tl["server_total_p50_ms"]), ls=":", marker=".", color="black", label="server total p50\n(from the headers)")
    ax2.set_ylabel("request → frame (ms)")
    ax2.set_xlabel("time (s)")
    ax2.set_ylim(bottom=0)
    ax2.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small", frameon=False)
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
