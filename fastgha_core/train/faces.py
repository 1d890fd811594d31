"""Face metrics that work offline, from dlib and the face-recognition-models files (extra ``faces``):

- CSIM: cosine similarity of dlib's 128-d face descriptors (ResNet) of the rendered and the
  ground-truth image (the paper uses ArcFace; dlib's descriptor is the offline stand-in, so
  absolute values are not comparable with the paper's table).
- AKD: mean Euclidean distance in pixels between dlib's 68 landmarks on the two images.

The face box is detected once on the ground truth (HOG detector, image upsampled once) and used for
both images, so a blurry render still gets landmarks at the right place; images where no face is
found on the ground truth are skipped (counted). When dlib is not installed, :func:`load_face_metrics`
returns ``None`` and the metrics are reported as unavailable (null).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from torch import Tensor

__all__ = ["FaceMetrics", "load_face_metrics", "to_uint8_hwc"]

log = logging.getLogger(__name__)


def to_uint8_hwc(img: Tensor) -> np.ndarray:
    """``[3, H, W]`` float in [0, 1] -> ``[H, W, 3]`` uint8 RGB."""
    if img.ndim != 3 or img.shape[0] != 3:
        raise ValueError(f"expected an image [3, H, W], got {list(img.shape)}")
    return (img.detach().float().clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)


@dataclass
class FaceMetrics:
    """dlib models; call :meth:`compare` per image pair."""

    detector: object
    shape_predictor: object
    face_rec: object
    dlib: object

    def _box(self, img: np.ndarray):
        dets = self.detector(img, 1)
        if len(dets) == 0:
            return None
        return max(dets, key=lambda r: r.width() * r.height())

    def compare(self, pred: Tensor, target: Tensor) -> tuple[float | None, float | None]:
        """``(csim, akd)`` for one pair of ``[3, H, W]`` images; ``(None, None)`` when no face is
        detected on the ground truth."""
        # dlib's pybind11 bindings accept only C-contiguous uint8 HxWx3 arrays
        p, t = np.ascontiguousarray(to_uint8_hwc(pred)), np.ascontiguousarray(to_uint8_hwc(target))
        box = self._box(t)
        if box is None:
            return None, None
        sp_t = self.shape_predictor(t, box)
        sp_p = self.shape_predictor(p, box)
        lm_t = np.array([[sp_t.part(i).x, sp_t.part(i).y] for i in range(sp_t.num_parts)], dtype=np.float64)
        lm_p = np.array([[sp_p.part(i).x, sp_p.part(i).y] for i in range(sp_p.num_parts)], dtype=np.float64)
        akd = float(np.linalg.norm(lm_t - lm_p, axis=1).mean())
        d_t = np.asarray(self.face_rec.compute_face_descriptor(t, sp_t), dtype=np.float64)
        d_p = np.asarray(self.face_rec.compute_face_descriptor(p, sp_p), dtype=np.float64)
        csim = float(d_t @ d_p / (np.linalg.norm(d_t) * np.linalg.norm(d_p) + 1e-12))
        return csim, akd


def load_face_metrics() -> FaceMetrics | None:
    """The dlib face models, or ``None`` (logged once) when dlib / face_recognition_models are missing."""
    import warnings

    try:
        import dlib  # type: ignore

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # pkg_resources deprecation inside face_recognition_models, on every run
            import face_recognition_models as frm  # type: ignore
    except Exception as e:  # ImportError, or pkg_resources missing with setuptools >= 81
        log.warning("CSIM/AKD unavailable (install the 'faces' extra: dlib-bin, face-recognition-models, setuptools<81): %s", e)
        return None
    return FaceMetrics(
        detector=dlib.get_frontal_face_detector(),
        shape_predictor=dlib.shape_predictor(frm.pose_predictor_model_location()),
        face_rec=dlib.face_recognition_model_v1(frm.face_recognition_model_location()),
        dlib=dlib,
    )
