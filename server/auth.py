"""API keys for creating avatars, per-avatar bearer tokens, and the strict avatar-id format.

* Avatar ids are 22-character URL-safe tokens (128 random bits); anything else is refused
  before it gets near a path (``check_avatar_id``).
* Each avatar gets its own random bearer token (256 bits). Only its SHA-256 is stored, and
  checks compare digests with ``hmac.compare_digest`` (constant time).
* API keys (``FASTGHA_API_KEYS``) gate avatar creation; they are compared in constant time too.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
from typing import Mapping

from .errors import ApiError

__all__ = [
    "AVATAR_ID_RE",
    "new_avatar_id",
    "new_token",
    "hash_token",
    "token_matches",
    "check_avatar_id",
    "is_valid_avatar_id",
    "bearer_from",
    "check_api_key",
]

AVATAR_ID_RE = re.compile(r"[A-Za-z0-9_-]{22}")
_MAX_TOKEN_CHARS = 256


def new_avatar_id() -> str:
    return secrets.token_urlsafe(16)  # 16 bytes -> 22 characters


def new_token() -> str:
    return secrets.token_urlsafe(32)


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def token_matches(token: str | None, stored_hash: str) -> bool:
    """Constant-time check of a presented token against the stored SHA-256 hex digest."""
    if not token or len(token) > _MAX_TOKEN_CHARS or not stored_hash:
        return False
    return hmac.compare_digest(hash_token(token).encode("ascii"), stored_hash.encode("ascii"))


def is_valid_avatar_id(avatar_id: str) -> bool:
    return isinstance(avatar_id, str) and AVATAR_ID_RE.fullmatch(avatar_id) is not None


def check_avatar_id(avatar_id: str) -> str:
    if not is_valid_avatar_id(avatar_id):
        raise ApiError(404, "avatar_not_found", "no avatar with this id (ids are 22 URL-safe characters)")
    return avatar_id


def bearer_from(headers: Mapping[str, str], query: Mapping[str, str]) -> str | None:
    """The token from ``Authorization: Bearer ...`` or else the ``token`` query parameter."""
    auth = headers.get("authorization")
    if auth:
        scheme, _, value = auth.partition(" ")
        if scheme.lower() == "bearer" and value.strip():
            return value.strip()
    tok = query.get("token")
    return tok or None


def check_api_key(headers: Mapping[str, str], api_keys: list[str]) -> None:
    """Raise 401 unless an API key is configured-off or presented (``X-API-Key`` or ``Authorization: Bearer``)."""
    if not api_keys:
        return
    presented = headers.get("x-api-key") or bearer_from(headers, {})
    if not presented:
        raise ApiError(401, "api_key_required", "creating avatars needs an API key (X-API-Key or Authorization: Bearer)")
    p = hashlib.sha256(presented.encode("utf-8")).digest()
    ok = False
    for k in api_keys:  # no early exit: constant time over the key list
        ok |= hmac.compare_digest(p, hashlib.sha256(k.encode("utf-8")).digest())
    if not ok:
        raise ApiError(401, "invalid_api_key", "the API key is not valid")
