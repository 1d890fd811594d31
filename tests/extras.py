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


def hide_modules(monkeypatch: pytest.MonkeyPatch, *names: str) -> None:
    """Make ``import NAME`` raise ImportError for each of ``names`` for the rest of the test, as on a
    machine without that extra (the module may be installed here)."""
    import builtins

    real_import = builtins.__import__

    def without(name, *a, **k):
        if name in names:
            raise ImportError(f"No module named {name!r}")
        return real_import(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", without)
