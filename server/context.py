"""Per-app state: settings, model, renderer, store, metrics, thread pools and open streams.

One ``ServerContext`` lives in ``app.state.ctx``; nothing is module-global, so several apps
(tests) can live in one process.
"""

from __future__ import annotations

import asyncio
import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

from .metrics import Metrics
from .settings import Settings

__all__ = ["ServerContext", "StreamRegistry"]

log = logging.getLogger(__name__)


class StreamRegistry:
    """Open stream sessions, per avatar and in total, with the configured caps (event-loop only)."""

    def __init__(self, max_per_avatar: int, max_total: int) -> None:
        self.max_per_avatar = max_per_avatar
        self.max_total = max_total
        self._by_avatar: dict[str, set[Any]] = {}
        self._total = 0

    @property
    def total(self) -> int:
        return self._total

    def active_ids(self) -> set[str]:
        return set(self._by_avatar)

    def sessions(self, avatar_id: str | None = None) -> list[Any]:
        if avatar_id is not None:
            return list(self._by_avatar.get(avatar_id, ()))
        return [s for group in self._by_avatar.values() for s in group]

    def try_add(self, avatar_id: str, session: Any) -> str | None:
        """Register; returns None, or a reason when a cap is reached."""
        if self._total >= self.max_total:
            return f"the server is at its limit of {self.max_total} streams"
        group = self._by_avatar.setdefault(avatar_id, set())
        if len(group) >= self.max_per_avatar:
            if not group:
                del self._by_avatar[avatar_id]
            return f"this avatar already has {self.max_per_avatar} open streams"
        group.add(session)
        self._total += 1
        return None

    def remove(self, avatar_id: str, session: Any) -> None:
        group = self._by_avatar.get(avatar_id)
        if group is None or session not in group:
            return
        group.discard(session)
        self._total -= 1
        if not group:
            del self._by_avatar[avatar_id]


@dataclass
class ServerContext:
    settings: Settings
    metrics: Metrics = field(default_factory=Metrics)
    model: Any = None  # FastGHA, set in lifespan
    renderer: Any = None  # FrameRenderer
    mlp_choice: Any = None  # fastgha_core.perf.PrecisionChoice, set in lifespan
    store: Any = None  # AvatarStore
    device: str = "cpu"
    render_pool: ThreadPoolExecutor | None = None
    work_pool: ThreadPoolExecutor | None = None  # uploads: decoding, reconstruction, disk
    reconstruct_slots: asyncio.Semaphore | None = None
    streams: StreamRegistry | None = None
    jobs: Any = None  # JobQueue (server/jobs.py): avatar creation
    identity: Any = None  # IdentityChecker (server/identity.py): do the photos show one person; None = not checked
    ready: bool = False
    log_throttle: Any = None  # streaming.LogThrottle: one traceback per kind of repeated error

    async def run_work(self, fn, *args):
        return await asyncio.get_running_loop().run_in_executor(self.work_pool, fn, *args)

    async def run_render(self, fn, *args):
        return await asyncio.get_running_loop().run_in_executor(self.render_pool, fn, *args)
