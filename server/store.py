"""Avatar store: an in-memory LRU with a byte budget over atomic on-disk persistence.

Layout under ``<data_dir>/avatars/``::

    <id>.safetensors   the canonical avatar (``CanonicalAvatar.save``)
    <id>.json          metadata; written last, so its presence commits the avatar

Every file is written to a temporary name in the same folder and moved into place with
``os.replace``, so a crash never leaves a half-written avatar: at start-up, temporary files
and avatar files without metadata are removed. The metadata file's mtime is the avatar's
last access (touched at most once a minute); avatars idle longer than the TTL are swept.
Ids reaching this class have been validated (``auth.check_avatar_id``); paths are built
from them only after a second check here.

A full disk (``ENOSPC``/``EDQUOT``) while writing raises ``StorageFullError`` (HTTP 507) and
leaves nothing behind. An avatar whose files cannot be read back (truncated, corrupt) is moved
to ``<data_dir>/quarantine/``, logged once, and reported as ``AvatarUnreadableError`` (HTTP 410,
WebSocket 4410); afterwards the id is unknown (404).

The store is synchronous and thread-safe; the app calls the methods that touch the disk
from worker threads.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import secrets
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from .auth import is_valid_avatar_id

__all__ = ["AvatarStore", "StoredAvatar", "StorageFullError", "AvatarUnreadableError"]

log = logging.getLogger(__name__)

_TMP_PREFIX = ".tmp-"
_TOUCH_INTERVAL_S = 60.0


class StorageFullError(OSError):
    """The data folder is out of space (or quota) while saving an avatar; nothing was kept."""


class AvatarUnreadableError(Exception):
    """A stored avatar's files could not be read; they were moved to the quarantine folder."""

    def __init__(self, avatar_id: str, detail: str) -> None:
        super().__init__(f"avatar {avatar_id} could not be read from disk ({detail}); it was set aside")
        self.avatar_id = avatar_id


_FULL_ERRNOS = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC), errno.EFBIG}


@dataclass
class StoredAvatar:
    avatar: Any  # CanonicalAvatar
    meta: dict
    nbytes: int


def _atomic_write_bytes(path: Path, data: bytes) -> None:
    tmp = path.with_name(f"{_TMP_PREFIX}{secrets.token_hex(8)}-{path.name}")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class AvatarStore:
    """LRU cache of avatars (byte budget) backed by a folder.

    Args:
        root: the data folder; avatars go in ``root/avatars``.
        max_bytes: in-memory budget; least recently used avatars are dropped from memory
            (never from disk) when the total exceeds it.
        ttl_seconds: idle time after which ``sweep_expired`` deletes an avatar; 0 = never.
        load_fn: ``path -> avatar`` (``CanonicalAvatar.load``).
        nbytes_fn: ``avatar -> int`` bytes held in memory.
    """

    def __init__(
        self,
        root: str | Path,
        max_bytes: int,
        ttl_seconds: float,
        load_fn: Callable[[Path], Any],
        nbytes_fn: Callable[[Any], int] = lambda a: int(a.nbytes() if callable(a.nbytes) else a.nbytes),
    ) -> None:
        self.dir = Path(root) / "avatars"
        self.dir.mkdir(parents=True, exist_ok=True)
        self.quarantine_dir = Path(root) / "quarantine"
        self.max_bytes = int(max_bytes)
        self.ttl_seconds = float(ttl_seconds)
        self._load_fn = load_fn
        self._nbytes_fn = nbytes_fn
        self._lock = threading.Lock()
        self._cache: OrderedDict[str, StoredAvatar] = OrderedDict()
        self._bytes = 0
        self._touched: dict[str, float] = {}
        self._cleanup_partial()

    # ------------------------------------------------------------ paths
    def _paths(self, avatar_id: str) -> tuple[Path, Path]:
        if not is_valid_avatar_id(avatar_id):  # defence in depth: callers validate first
            raise ValueError(f"invalid avatar id {avatar_id[:40]!r}")
        return self.dir / f"{avatar_id}.safetensors", self.dir / f"{avatar_id}.json"

    def _cleanup_partial(self) -> None:
        removed = 0
        for p in self.dir.iterdir():
            if p.name.startswith(_TMP_PREFIX):
                p.unlink(missing_ok=True)
                removed += 1
            elif p.suffix == ".safetensors" and not p.with_suffix(".json").exists():
                p.unlink(missing_ok=True)  # avatar written but never committed
                removed += 1
        if removed:
            log.info("removed %d partial avatar file(s) from %s", removed, self.dir)

    # ------------------------------------------------------------ stats
    @property
    def cached_count(self) -> int:
        return len(self._cache)

    @property
    def cached_bytes(self) -> int:
        return self._bytes

    def disk_ids(self) -> list[str]:
        return sorted(p.stem for p in self.dir.glob("*.json") if is_valid_avatar_id(p.stem))

    # ------------------------------------------------------------ cache
    def _insert(self, avatar_id: str, item: StoredAvatar) -> None:
        with self._lock:
            old = self._cache.pop(avatar_id, None)
            if old is not None:
                self._bytes -= old.nbytes
            self._cache[avatar_id] = item
            self._bytes += item.nbytes
            while self._cache and self._bytes > self.max_bytes:
                evicted_id, ev = self._cache.popitem(last=False)
                self._bytes -= ev.nbytes
                log.debug("evicted avatar %s from memory (%d bytes)", evicted_id, ev.nbytes)

    def _touch(self, avatar_id: str, meta_path: Path) -> None:
        now = time.time()
        if now - self._touched.get(avatar_id, 0.0) < _TOUCH_INTERVAL_S:
            return
        self._touched[avatar_id] = now
        try:
            os.utime(meta_path, (now, now))
        except FileNotFoundError:
            pass

    # ------------------------------------------------------------ public API
    def put(self, avatar_id: str, avatar: Any, meta: dict) -> None:
        """Persist atomically (avatar file, then metadata) and cache.

        Raises ``StorageFullError`` when the disk is full (nothing of this avatar is left on disk),
        other ``OSError`` as they come (nothing left either)."""
        avatar_path, meta_path = self._paths(avatar_id)
        tmp = avatar_path.with_name(f"{_TMP_PREFIX}{secrets.token_hex(8)}-{avatar_path.name}")
        committed = False
        try:
            try:
                avatar.save(tmp)
                with open(tmp, "rb+") as f:
                    os.fsync(f.fileno())
                os.replace(tmp, avatar_path)
            finally:
                tmp.unlink(missing_ok=True)
            _atomic_write_bytes(meta_path, json.dumps(meta, indent=1, sort_keys=True).encode("utf-8"))
            committed = True
        except OSError as e:
            if e.errno in _FULL_ERRNOS:
                raise StorageFullError(e.errno, f"no space left for avatar {avatar_id} in {self.dir}") from e
            raise
        finally:
            if not committed:  # the avatar file without its metadata is not an avatar: remove it now
                avatar_path.unlink(missing_ok=True)
        _fsync_dir(self.dir)
        self._touched[avatar_id] = time.time()
        self._insert(avatar_id, StoredAvatar(avatar, dict(meta), self._nbytes_fn(avatar)))

    def get_meta(self, avatar_id: str) -> dict | None:
        """Metadata of a stored avatar, or None when there is none."""
        with self._lock:
            item = self._cache.get(avatar_id)
            if item is not None:
                return item.meta
        _, meta_path = self._paths(avatar_id)
        try:
            meta = json.loads(meta_path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            return None
        except (ValueError, UnicodeDecodeError) as e:
            self._quarantine(avatar_id, e)
        if not isinstance(meta, dict):
            self._quarantine(avatar_id, ValueError(f"metadata is a {type(meta).__name__}, not an object"))
        return meta

    def _quarantine(self, avatar_id: str, exc: BaseException) -> None:
        """Move an unreadable avatar's files to ``quarantine/``, log once, raise ``AvatarUnreadableError``."""
        detail = f"{type(exc).__name__}: {str(exc).splitlines()[0][:200] if str(exc) else ''}"
        moved = []
        with self._lock:
            item = self._cache.pop(avatar_id, None)
            if item is not None:
                self._bytes -= item.nbytes
            self._touched.pop(avatar_id, None)
            self.quarantine_dir.mkdir(parents=True, exist_ok=True)
            for p in self._paths(avatar_id):
                try:
                    os.replace(p, self.quarantine_dir / p.name)
                    moved.append(p.name)
                except FileNotFoundError:
                    pass
        if moved:  # another thread may have moved them already: only the mover logs
            log.warning("avatar %s is unreadable (%s): moved %s to quarantine %s", avatar_id, detail, ", ".join(moved), self.quarantine_dir)
        raise AvatarUnreadableError(avatar_id, detail)

    def get(self, avatar_id: str) -> StoredAvatar | None:
        """The avatar (loaded from disk when not in memory) or None when there is none."""
        avatar_path, meta_path = self._paths(avatar_id)
        with self._lock:
            item = self._cache.get(avatar_id)
            if item is not None:
                self._cache.move_to_end(avatar_id)
        if item is None:
            meta = self.get_meta(avatar_id)
            if meta is None or not avatar_path.exists():
                return None
            t0 = time.perf_counter()
            try:
                avatar = self._load_fn(avatar_path)
            except FileNotFoundError:
                return None  # deleted meanwhile
            except Exception as e:  # truncated or corrupt file: set it aside (raises)
                self._quarantine(avatar_id, e)
            item = StoredAvatar(avatar, meta, self._nbytes_fn(avatar))
            self._insert(avatar_id, item)
            log.info("loaded avatar %s from disk in %.1f ms", avatar_id, 1e3 * (time.perf_counter() - t0))
        self._touch(avatar_id, meta_path)
        return item

    def delete(self, avatar_id: str) -> bool:
        """Remove from memory and disk (metadata first, which un-commits it). True when it existed."""
        avatar_path, meta_path = self._paths(avatar_id)
        with self._lock:
            item = self._cache.pop(avatar_id, None)
            if item is not None:
                self._bytes -= item.nbytes
        self._touched.pop(avatar_id, None)
        existed = meta_path.exists() or item is not None
        meta_path.unlink(missing_ok=True)
        avatar_path.unlink(missing_ok=True)
        return existed

    def sweep_expired(self, keep: set[str] | frozenset = frozenset(), now: float | None = None) -> list[str]:
        """Delete avatars idle for longer than the TTL (except ids in ``keep``, e.g. streaming ones)."""
        if self.ttl_seconds <= 0:
            return []
        now = time.time() if now is None else now
        expired = []
        for p in self.dir.glob("*.json"):
            aid = p.stem
            if not is_valid_avatar_id(aid) or aid in keep:
                continue
            try:
                idle = now - p.stat().st_mtime
            except FileNotFoundError:
                continue
            if idle > self.ttl_seconds:
                self.delete(aid)
                expired.append(aid)
        if expired:
            log.info("expired %d idle avatar(s)", len(expired))
        return expired
