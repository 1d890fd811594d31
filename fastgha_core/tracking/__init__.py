"""Tracking: photos and video frames -> head pose cameras, ``ict53`` expressions, crops, masks.

Needs the ``faces`` extra (MediaPipe Face Mesh, installed with ``--no-deps``, and OpenCV
headless; dlib as the fallback) for detection, landmarks and segmentation; fitting and cropping
are numpy/scipy. See ``docs/tracking.md``.

- ``faces.py``    MediaPipe Face Mesh (or dlib's 68 points), failure policy (no / several / tiny face)
- ``meshmap.py``  Face Mesh point -> ICT vertex correspondence (and its yaw-dependent table)
- ``fit.py``      one joint ICT head-model fit per person (bounded Levenberg-Marquardt with priors)
- ``silhouette.py`` person mask outline as an optional residual for side views
- ``camera.py``   fitted pose -> head-centric OpenCV ``Cameras``
- ``crop.py``     square head crop, K adjusted, background padding
- ``matting.py``  mask: trimap from the fitted head (sure foreground: the face), the rest decided by segmentation / mixture / GrabCut
- ``pipeline.py`` ``track_photos`` / ``track_request`` (server entry point) / ``track_known_cameras`` (photos with cameras)
- ``video.py``    per-frame expression + pose tracking with One-Euro smoothing
- ``evaluate.py`` synthetic accuracy figures (``python -m fastgha_core.tracking.evaluate``)
- ``realsets.py`` yaw on the real photo sets (``python -m fastgha_core.tracking.realsets``)
- ``photoalign.py`` photometric registration of the photos' poses to each other on the fitted face; by default of the photos turned >= 55 degrees only (``TrackConfig.photo_align``)
- ``multiview.py`` relative head poses from SIFT features lifted onto the fitted head (a measurement, not in the fit)
- ``matting_eval.py`` masks against known alpha (synthetic heads on walls) and a leak score on the real sets
"""

from .pipeline import TrackConfig, TrackedPhotos, track_known_cameras, track_photos, track_request

__all__ = ["track_request", "track_photos", "track_known_cameras", "TrackConfig", "TrackedPhotos"]
