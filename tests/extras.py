"""Skip markers for tests that need an optional extra (imported by the test modules)."""

from __future__ import annotations

import functools

import pytest


@functools.lru_cache(maxsize=1)
def faces_installed() -> bool:
    """Whether the ``faces`` extra loads (MediaPipe Face Mesh or dlib, and their models)."""
    try:
        from fastgha_core.tracking.faces import load_face_detector

        load_face_detector()
        return True
    except ImportError:
        return False


needs_faces = pytest.mark.skipif(not faces_installed(), reason="needs the 'faces' extra (mediapipe, dlib-bin, face-recognition-models)")
