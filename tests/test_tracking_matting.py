"""The three matting classifiers (matting.py) on a real portrait: the face in, the background out."""

from __future__ import annotations

import numpy as np
import pytest

try:
    from fastgha_core.tracking.faces import MeshDetector

    MESH = MeshDetector()
except ImportError:
    MESH = None


@pytest.mark.skipif(MESH is None, reason="needs the 'faces' extra with mediapipe (make install-test)")
@pytest.mark.parametrize("method", ["segmentation", "mixture", "grabcut"])
def test_matting_methods_keep_the_face_and_drop_the_background(method):
    import skimage.data

    from fastgha_core.tracking import TrackConfig, track_photos
    from fastgha_core.tracking.matting import MattingConfig

    res = track_photos([skimage.data.astronaut()], TrackConfig(size=128, matting=MattingConfig(method=method)), detector=MESH)
    m = res.masks[0]
    assert m[40:90, 40:90].mean() > 0.9  # the face
    assert m[:10, :10].mean() < 0.2 and m[:10, -10:].mean() < 0.2  # flag and background at the top corners


def test_unknown_matting_method_is_refused():
    from fastgha_core.tracking.matting import MattingConfig, matte_from_head

    sil = np.zeros((32, 32), np.float32)
    sil[8:24, 8:24] = 1
    with pytest.raises(ValueError, match="matting method must be"):
        matte_from_head(np.zeros((32, 32, 3), np.uint8), sil, 100.0, 20.0, None, MattingConfig(method="magic"))


@pytest.mark.skipif(MESH is None, reason="needs the 'faces' extra with mediapipe (make install-test)")
def test_a_photo_whose_landmarks_no_head_explains_is_refused_by_name():
    """Landmarks scrambled for one photo (as a detector fooled by a drawing would give): the set is
    refused naming that photo, not tracked with a wrong camera."""
    import skimage.data

    from fastgha_core.tracking import track_photos

    class Scrambled:
        layout = MESH.layout

        def detect_one(self, img, name):
            box, lm = MESH.detect_one(img, name)
            if name == "drawing.png":
                rng = np.random.default_rng(0)
                lm = lm[rng.permutation(len(lm))]
            return box, lm

    img = skimage.data.astronaut()
    with pytest.raises(ValueError, match="cannot place the head in drawing.png"):
        track_photos([img, img], names=["astronaut.png", "drawing.png"], detector=Scrambled())
