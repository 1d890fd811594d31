"""Do all photos of one avatar show the same person? (dlib face descriptors, extra ``faces``.)

``POST /v1/avatars`` takes 1-8 photos of **one** person; photos of two people would be fused into
one head. While a creation job decodes its photos, :class:`IdentityChecker` computes dlib's 128-d
face descriptor (its ResNet face-recognition model, shipped by ``face_recognition_models``) of the
largest frontal face in each photo, and :func:`same_person_groups` splits the photos into groups:
two photos are linked when their descriptors are at most ``max_distance`` apart (0.6 is dlib's
same-person threshold, its documented operating point), and a group is a connected set of links.
More than one group raises :class:`DifferentPeopleError` (the server answers ``422 different_people``), naming the photos of each group and the
closest distance between them.

Only photos with a descriptor are compared. dlib's frontal (HOG) detector finds no face in
profiles and strong side views (beyond ~60-70 degrees of yaw): such a photo is never refused for
that, it is left out of the check (``photos_without_face`` in the avatar's ``same_person``).
Linking through a chain (not every pair) keeps side views of one person, which are further from
the frontal ones than frontal photos are from each other, in one group.

Measured on the real photo sets (three people, 4-6 photos each from 0 to 85 degrees of yaw;
photos downscaled to a 512-pixel longer side, detector without upsampling, as here): photos of one
person are 0.23-0.56 apart (the largest: one person pitched down against pitched up), photos of
two different people 0.62-0.85; dlib finds no frontal face in the two 85-degree profiles.
``docs/protocol.md`` ("Same person") has the figures and the command that reproduces them.

Without dlib (or with ``FASTGHA_SAME_PERSON_CHECK=false``) nothing is checked and the avatar's
``same_person`` says so (``"checked": false``).

Cost: ~15-20 ms of detection and ~75 ms of descriptor per photo on one shared CPU core; a creation
from four real photos without cameras took 2.83 s with the check against 2.53 s without (medians of 5,
busy 2-core machine; ``bench/same_person.py``).
"""

from __future__ import annotations

import logging
import threading
import warnings
from dataclasses import dataclass, field

import numpy as np

__all__ = ["CHECK_SIDE", "DifferentPeopleError", "IdentityChecker", "SamePersonResult", "same_person_groups", "DLIB_SAME_PERSON_DISTANCE"]

log = logging.getLogger(__name__)

DLIB_SAME_PERSON_DISTANCE = 0.6  # dlib's threshold on the Euclidean distance of two face descriptors
CHECK_SIDE = 512  # photos are looked at with this longer side (at most): a face needs >= ~80 px here


class DifferentPeopleError(ValueError):
    """The photos split into several people: the message names the photos of each group and the
    closest distance between groups (the server answers it as ``422 different_people``)."""


def same_person_groups(descriptors: list[np.ndarray | None], max_distance: float) -> tuple[list[list[int]], np.ndarray]:
    """Groups of photo indices linked by descriptor distance ``<= max_distance`` (connected sets),
    and the ``[V, V]`` distance matrix (``nan`` where a photo has no descriptor).

    Args:
        descriptors: per photo, a 128-d descriptor or None (no face found); photos without one are
            in no group.
        max_distance: the link threshold (Euclidean; dlib's same-person threshold is 0.6).
    Returns groups sorted by their first index, each sorted.
    """
    v = len(descriptors)
    dist = np.full((v, v), np.nan)
    have = [i for i, d in enumerate(descriptors) if d is not None]
    for a in have:
        for b in have:
            dist[a, b] = float(np.linalg.norm(np.asarray(descriptors[a], np.float64) - np.asarray(descriptors[b], np.float64)))
    group = {i: i for i in have}  # union-find

    def root(i: int) -> int:
        while group[i] != i:
            group[i] = group[group[i]]
            i = group[i]
        return i

    for a in have:
        for b in have:
            if a < b and dist[a, b] <= max_distance:
                group[root(b)] = root(a)
    out: dict[int, list[int]] = {}
    for i in have:
        out.setdefault(root(i), []).append(i)
    return sorted(out.values(), key=lambda g: g[0]), dist


@dataclass
class SamePersonResult:
    """What the check saw: ``checked`` False when nothing was compared for want of dlib (or the
    setting is off); ``compared`` photos with a descriptor; ``max_distance`` the largest distance
    between two of them (None for fewer than two)."""

    checked: bool
    reason: str = ""
    compared: list[str] = field(default_factory=list)
    without_face: list[str] = field(default_factory=list)
    max_distance: float | None = None
    ms: float = 0.0

    def as_dict(self) -> dict:
        out: dict = {"checked": self.checked}
        if not self.checked:
            out["reason"] = self.reason
            return out
        out.update(photos_compared=len(self.compared), photos_without_face=list(self.without_face),
                   max_distance=None if self.max_distance is None else round(self.max_distance, 3), check_ms=round(self.ms, 1))  # fmt: skip
        return out


class IdentityChecker:
    """dlib's face detector, 5-point landmarks and face-recognition model, loaded on first use (one
    per app; thread-safe: descriptors are computed one at a time). ``available`` is False, with ``reason``, when dlib or
    ``face_recognition_models`` is missing."""

    def __init__(self, enabled: bool = True, max_distance: float = DLIB_SAME_PERSON_DISTANCE) -> None:
        self.enabled = bool(enabled)
        self.max_distance = float(max_distance)
        self._lock = threading.Lock()
        self._models = None
        self.reason = "" if enabled else "disabled by FASTGHA_SAME_PERSON_CHECK=false"

    def _load(self):
        if self._models is None and not self.reason:
            try:
                import dlib  # type: ignore

                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # pkg_resources deprecation inside face_recognition_models
                    import face_recognition_models as frm  # type: ignore
                self._models = (
                    dlib.get_frontal_face_detector(),
                    dlib.shape_predictor(frm.pose_predictor_five_point_model_location()),
                    dlib.face_recognition_model_v1(frm.face_recognition_model_location()),
                )
            except Exception as e:  # ImportError, missing model files, pkg_resources missing
                self.reason = f"dlib face descriptors unavailable (install the 'faces' extra): {type(e).__name__}: {e}"
                log.warning("photos of one avatar are not checked to show the same person: %s", self.reason)
        return self._models

    @property
    def available(self) -> bool:
        with self._lock:
            return self._load() is not None

    def descriptor(self, rgb: np.ndarray) -> np.ndarray | None:
        """The 128-d descriptor of the largest frontal face in ``rgb`` (``[H, W, 3]`` uint8, upright),
        looked at with a longer side of at most :data:`CHECK_SIDE`; None when no face is found or
        dlib is missing."""
        h, w = rgb.shape[:2]
        s = min(1.0, CHECK_SIDE / max(h, w))
        if s < 1.0:
            from PIL import Image

            rgb = np.asarray(Image.fromarray(rgb).resize((max(1, round(w * s)), max(1, round(h * s))), Image.BILINEAR))
        img = np.ascontiguousarray(rgb[..., :3], dtype=np.uint8)
        with self._lock:  # dlib's network keeps per-call state: one photo at a time (jobs may run concurrently)
            models = self._load()
            if models is None:
                return None
            det, shape5, rec = models
            faces = det(img, 0)
            if len(faces) == 0:
                return None
            box = max(faces, key=lambda r: r.area())
            return np.asarray(rec.compute_face_descriptor(img, shape5(img, box)), dtype=np.float64)

    def check(self, names: list[str], descriptors: list[np.ndarray | None], ms: float = 0.0) -> SamePersonResult:
        """``SamePersonResult`` of photos ``names`` with their descriptors; raises
        :class:`DifferentPeopleError` naming the photos of each group when they split into several."""
        if not self.enabled or self._models is None:
            return SamePersonResult(False, reason=self.reason or "dlib face descriptors unavailable")
        groups, dist = same_person_groups(descriptors, self.max_distance)
        compared = [names[i] for g in groups for i in sorted(g)]
        without = [n for n, d in zip(names, descriptors) if d is None]
        if len(groups) > 1:
            parts = ["photos " + ", ".join(names[i] for i in g) if len(g) > 1 else f"photo {names[g[0]]}" for g in groups]
            a, b = groups[0], [i for g in groups[1:] for i in g]
            sub = dist[np.ix_(a, b)]
            i, j = np.unravel_index(int(np.nanargmin(sub)), sub.shape)
            raise DifferentPeopleError(
                f"the photos do not all show the same person: {' / '.join(parts)} look like {len(groups)} different people "
                f"(face descriptor distance {sub[i, j]:.2f} between {names[a[i]]} and {names[b[j]]}, above {self.max_distance:g}, "
                "dlib's same-person threshold); post photos of one person"
            )
        have = [i for g in groups for i in g]
        mx = float(np.nanmax(dist[np.ix_(have, have)])) if len(have) > 1 else None
        return SamePersonResult(True, compared=compared, without_face=without, max_distance=mx, ms=ms)
