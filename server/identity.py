"""The same-person check of a creation job's photos, as the HTTP API answers it.

The check itself (dlib face descriptors, linking by dlib's 0.6 threshold, photos without a frontal
face left out, nothing checked without dlib) is :mod:`fastgha_core.tracking.identity`, shared with
``fastgha track``; here a split into several people becomes ``422 different_people``.
"""

from __future__ import annotations

import numpy as np

from fastgha_core.tracking.identity import (  # noqa: F401  (re-exported for the server's modules)
    CHECK_SIDE,
    DLIB_SAME_PERSON_DISTANCE,
    DifferentPeopleError,
    SamePersonResult,
    same_person_groups,
)
from fastgha_core.tracking.identity import IdentityChecker as _CoreChecker

from .errors import ApiError

__all__ = ["CHECK_SIDE", "DLIB_SAME_PERSON_DISTANCE", "IdentityChecker", "SamePersonResult", "same_person_groups"]


class IdentityChecker(_CoreChecker):
    """:class:`fastgha_core.tracking.identity.IdentityChecker` whose ``check`` raises ``ApiError``
    422 ``different_people`` (the message names the photos of each group)."""

    def check(self, names: list[str], descriptors: list[np.ndarray | None], ms: float = 0.0) -> SamePersonResult:
        try:
            return super().check(names, descriptors, ms)
        except DifferentPeopleError as e:
            raise ApiError(422, "different_people", str(e)) from None
