"""Prometheus metrics with a per-app ``CollectorRegistry`` (no process-global collectors)."""

from __future__ import annotations

from typing import Callable

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_LATEST

__all__ = ["Metrics", "CONTENT_TYPE_LATEST"]

_MS_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.02, 0.035, 0.05, 0.075, 0.1, 0.15, 0.25, 0.5, 1.0, 2.5)


class Metrics:
    """The server's metrics; ``render()`` gives the Prometheus text exposition."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        r = self.registry
        self.frames_rendered = Counter("fastgha_frames_rendered", "frames rendered and sent", registry=r)
        self.frames_dropped = Counter(
            "fastgha_frames_dropped", "frame requests replaced by a newer one before rendering (latest wins)", registry=r
        )
        self.frame_errors = Counter("fastgha_frame_errors", "frames that failed to render", registry=r)
        self.protocol_errors = Counter("fastgha_protocol_errors", "bad client messages answered with an error", ["code"], registry=r)
        self.render_seconds = Histogram(
            "fastgha_render_seconds", "deformation + rasterization time per frame", buckets=_MS_BUCKETS, registry=r
        )
        self.encode_seconds = Histogram("fastgha_encode_seconds", "JPEG encoding time per frame", buckets=_MS_BUCKETS, registry=r)
        self.reconstruct_seconds = Histogram(
            "fastgha_reconstruct_seconds",
            "avatar reconstruction time",
            buckets=(0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0),
            registry=r,
        )
        self.avatars_created = Counter("fastgha_avatars_created", "avatars reconstructed", registry=r)
        self.active_streams = Gauge("fastgha_active_streams", "open WebSocket streams", registry=r)
        self.cached_avatars = Gauge("fastgha_cached_avatars", "avatars held in memory", registry=r)
        self.cached_avatar_bytes = Gauge("fastgha_cached_avatar_bytes", "bytes of avatars held in memory", registry=r)

    def bind_cache(self, count: Callable[[], float], nbytes: Callable[[], float]) -> None:
        """Read the cache gauges from the store at scrape time."""
        self.cached_avatars.set_function(count)
        self.cached_avatar_bytes.set_function(nbytes)

    def render(self) -> bytes:
        return generate_latest(self.registry)
