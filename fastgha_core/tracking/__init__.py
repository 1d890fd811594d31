"""Tracking: photos and video frames -> head pose cameras, ``ict53`` expressions, crops, masks.

Needs the ``faces`` extra (dlib-bin, face-recognition-models) for detection and landmarks;
fitting, cropping and matting are numpy/scipy. See ``docs/tracking.md``.

- ``faces.py``    dlib detector + 68 landmarks, failure policy (no / several / tiny face)
- ``fit.py``      ICT head model fit to 68 landmarks (bounded Levenberg-Marquardt with priors)
- ``camera.py``   fitted pose -> head-centric OpenCV ``Cameras``
- ``crop.py``     square head crop, K adjusted, background padding
- ``matting.py``  mask from the fitted head silhouette + colour mixture models
- ``pipeline.py`` ``track_photos`` / ``track_request`` (server entry point)
- ``video.py``    per-frame expression + pose tracking with One-Euro smoothing
- ``evaluate.py`` synthetic accuracy figures (``python -m fastgha_core.tracking.evaluate``)
"""

from .pipeline import TrackConfig, TrackedPhotos, track_photos, track_request

__all__ = ["track_request", "track_photos", "TrackConfig", "TrackedPhotos"]
