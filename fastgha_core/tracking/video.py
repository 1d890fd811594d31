"""Per-frame expression + head-pose tracking for video driving (webcam or a clip).

Per frame (``VideoTracker.track``), with MediaPipe (the default detector): its Face Mesh graph
in tracking mode gives the landmarks (its face detector runs only when the face is lost), then
steps 3-4. With dlib (fallback):

1. **Face box**: dlib's HOG detector on the frame downscaled to ``detect_width`` pixels (no
   upsampling), only every ``detect_every`` frames or when tracking was lost; in between the box
   comes from the previous frame's landmarks (their bounding box mapped to a detector-like box by
   the offset measured on the last detection frame).
2. **Landmarks**: dlib's 68-point predictor in that box.
3. **Fit**: ``fit.fit_landmarks`` with the identity fixed (estimated on the first frame, or given),
   warm-started from the previous frame's pose and expression, ``iterations`` LM steps, no
   rigid stage.
4. **Smoothing**: One-Euro filters (Casiez et al., CHI 2012) on the expression vector, the
   translation and the rotation matrix entries (re-orthonormalised by SVD): steady when the face
   is still, little lag when it moves fast.

Speed target: >= 15 frames per second at 640 x 480 on a 2-core CPU (measured with
``python -m fastgha_core.tracking.video --bench``; see docs/tracking.md).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from .faces import FaceBox, load_face_detector
from .fit import FitConfig, FitResult, LandmarkModel, default_intrinsics, fit_landmarks

__all__ = ["VideoConfig", "OneEuroFilter", "FrameTrack", "VideoTracker"]

logger = logging.getLogger(__name__)


@dataclass
class VideoConfig:
    detect_every: int = 15  # run the detector at least every N frames
    detect_width: int = 640  # detector input width (wider frames are downscaled to it; HOG needs faces >= 80 px)
    iterations: int = 4  # LM steps per frame (warm start)
    fov_deg: float = 30.0  # assumed field of view across the longer frame side
    lost_rms: float = 0.08  # re-detect when the landmark RMS exceeds this fraction of the face size
    expr_min_cutoff: float = 1.5  # One-Euro: Hz, smoothing of slow motion (lower = smoother)
    expr_beta: float = 0.5  # One-Euro: speed coefficient (higher = less lag on fast motion)
    pose_min_cutoff: float = 1.0
    pose_beta: float = 0.3
    fit: FitConfig = field(default_factory=FitConfig)


class OneEuroFilter:
    """One-Euro filter of a vector signal (Casiez, Roussel, Vogel 2012)."""

    def __init__(self, min_cutoff: float = 1.0, beta: float = 0.0, d_cutoff: float = 1.0):
        self.min_cutoff, self.beta, self.d_cutoff = min_cutoff, beta, d_cutoff
        self.x_prev: np.ndarray | None = None
        self.dx_prev: np.ndarray | None = None
        self.t_prev: float | None = None

    @staticmethod
    def _alpha(cutoff, dt: float):
        tau = 1.0 / (2.0 * math.pi * cutoff)
        return 1.0 / (1.0 + tau / dt)

    def __call__(self, x: np.ndarray, t: float) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        if self.x_prev is None or self.t_prev is None or t <= self.t_prev:
            self.x_prev, self.dx_prev, self.t_prev = x.copy(), np.zeros_like(x), t
            return x.copy()
        dt = t - self.t_prev
        dx = (x - self.x_prev) / dt
        a_d = self._alpha(self.d_cutoff, dt)
        dx_hat = a_d * dx + (1 - a_d) * self.dx_prev
        cutoff = self.min_cutoff + self.beta * np.abs(dx_hat)
        a = self._alpha(cutoff, dt)
        x_hat = a * x + (1 - a) * self.x_prev
        self.x_prev, self.dx_prev, self.t_prev = x_hat, dx_hat, t
        return x_hat.copy()


@dataclass
class FrameTrack:
    """The tracked state of one frame (smoothed)."""

    expression: np.ndarray  # [53] ict53 in [0, 1]
    R: np.ndarray  # [3, 3] head -> camera
    t: np.ndarray  # [3] metres
    K: np.ndarray  # [3, 3] assumed intrinsics of the frame
    landmarks: np.ndarray  # [68, 2] detected (raw), frame pixels
    detected: bool  # the detector ran on this frame
    rms_px: float  # landmark RMS of the (unsmoothed) fit

    @property
    def w2c(self) -> np.ndarray:  # [4, 4] head-centric camera (camera.py)
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self.R, self.t
        return m

    def cameras(self, width: int, height: int):
        from .camera import pose_to_cameras

        return pose_to_cameras(self.R[None], self.t[None], self.K, width, height)


class VideoTracker:
    """Stateful tracker: call :meth:`track` on consecutive frames (module doc)."""

    def __init__(self, identity: np.ndarray | None = None, config: VideoConfig | None = None, detector=None):
        self.cfg = config or VideoConfig()
        self.det = detector or load_face_detector()
        self.model = LandmarkModel.from_head_model(num_identity=self.cfg.fit.num_identity, layout=getattr(self.det, "layout", "dlib68"))
        self.fast_cfg = FitConfig(**{**self.cfg.fit.__dict__, "iterations": self.cfg.iterations})
        self.identity = None if identity is None else np.asarray(identity, dtype=np.float64)
        self.reset()

    def reset(self) -> None:
        self.prev: FitResult | None = None
        self.prev_lm: np.ndarray | None = None
        self.box_offset = np.array([0.0, 0.0, 0.0, 0.0])  # detector box - landmark bbox, per bbox size
        self.since_detect = 0
        self.frame_index = 0
        c = self.cfg
        self.f_expr = OneEuroFilter(c.expr_min_cutoff, c.expr_beta)
        self.f_t = OneEuroFilter(c.pose_min_cutoff, c.pose_beta)
        self.f_R = OneEuroFilter(c.pose_min_cutoff, c.pose_beta)
        if hasattr(self.det, "reset_video"):
            self.det.reset_video()

    def _landmarks(self, frame: np.ndarray) -> tuple[np.ndarray | None, bool]:
        """Landmarks of this frame and whether a detector ran (MediaPipe: its own tracking mode)."""
        if hasattr(self.det, "track_frame"):
            return self.det.track_frame(frame), self.prev_lm is None
        detected = False
        if self.prev_lm is None or self.since_detect >= self.cfg.detect_every:
            box = self._detect(frame)
            if box is None:
                return None, True
            detected, self.since_detect = True, 0
        else:
            box = self._box_from_landmarks(self.prev_lm)
            self.since_detect += 1
        lm = self.det.landmarks(frame, box)
        if detected:
            b = FaceBox.from_landmarks(lm)
            size = np.array([b.right - b.left, b.bottom - b.top] * 2)
            self.box_offset = (np.array([box.left, box.top, box.right, box.bottom]) - np.array([b.left, b.top, b.right, b.bottom])) / size
        return lm, detected

    def _detect(self, frame: np.ndarray) -> FaceBox | None:
        h, w = frame.shape[:2]
        s = min(1.0, self.cfg.detect_width / w)
        small = frame
        if s < 1.0:
            from PIL import Image

            small = np.asarray(Image.fromarray(frame).resize((int(round(w * s)), int(round(h * s))), Image.BILINEAR))
        boxes = self.det.detect(small, upsample=0)
        return boxes[0].scaled(1.0 / s) if boxes else None

    def _box_from_landmarks(self, lm: np.ndarray) -> FaceBox:
        b = FaceBox.from_landmarks(lm)
        size = np.array([b.right - b.left, b.bottom - b.top] * 2)
        o = self.box_offset * size
        return FaceBox(b.left + o[0], b.top + o[1], b.right + o[2], b.bottom + o[3])

    def track(self, frame: np.ndarray, timestamp: float | None = None) -> FrameTrack | None:
        """Track one ``[H, W, 3]`` uint8 RGB frame; ``None`` when no face is found."""
        t_now = self.frame_index / 30.0 if timestamp is None else float(timestamp)
        self.frame_index += 1
        lm, detected = self._landmarks(frame)
        if lm is None:
            self.prev, self.prev_lm = None, None
            return None
        h, w = frame.shape[:2]
        K = default_intrinsics(w, h, self.cfg.fov_deg)
        if self.identity is None:  # first frame: estimate the identity once, then keep it fixed
            res = fit_landmarks(lm[None], K, self.cfg.fit, self.model)
            self.identity = res.identity
        elif self.prev is None:
            res = fit_landmarks(lm[None], K, self.cfg.fit, self.model, identity=self.identity)
        else:
            res = fit_landmarks(lm[None], K, self.fast_cfg, self.model, identity=self.identity, init=self.prev)
        face = float(np.linalg.norm(lm.max(0) - lm.min(0)))
        lost = res.rms_px[0] > self.cfg.lost_rms * face
        self.prev = None if lost else res
        self.prev_lm = None if lost else lm
        expr = np.clip(self.f_expr(res.expressions[0], t_now), 0.0, 1.0)
        tt = self.f_t(res.translations[0], t_now)
        U, _, Vt = np.linalg.svd(self.f_R(res.rotations[0].reshape(-1), t_now).reshape(3, 3))
        R = U @ Vt
        return FrameTrack(expr, R, tt, K, lm, detected, float(res.rms_px[0]))


def bench_frames(n: int = 150, width: int = 640, height: int = 480, face_height: int = 420) -> list[np.ndarray]:
    """Test frames: matplotlib's Grace Hopper portrait moving over a grey background."""
    import matplotlib.cbook as cbook
    from PIL import Image

    src = Image.open(cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)).convert("RGB")
    s = face_height / src.height
    src = np.asarray(src.resize((int(src.width * s), face_height), Image.BILINEAR))
    frames = []
    for i in range(n):
        f = np.full((height, width, 3), 96, np.uint8)
        x = int((width - src.shape[1]) / 2 + 60 * math.sin(2 * math.pi * i / 90))
        y = int((height - src.shape[0]) / 2 + 20 * math.sin(2 * math.pi * i / 60))
        f[max(y, 0) : y + src.shape[0], max(x, 0) : x + src.shape[1]] = src[max(-y, 0) : height - y, max(-x, 0) : width - x]
        frames.append(f)
    return frames


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m fastgha_core.tracking.video", description="measure video tracking speed")
    p.add_argument("--bench", action="store_true", help="track synthetic 640x480 frames and print the frame rate")
    p.add_argument("--frames", type=int, default=150)
    p.add_argument("--size", default="640x480", help="frame size WxH (the face is 7/8 of the height)")
    a = p.parse_args(argv)
    w, h = (int(x) for x in a.size.lower().split("x"))
    frames = bench_frames(a.frames, w, h, face_height=int(h * 7 / 8))
    tr = VideoTracker()
    tr.track(frames[0])  # identity calibration + warm-up, not timed
    t0 = time.perf_counter()
    n_ok = 0
    for f in frames[1:]:
        n_ok += tr.track(f) is not None
    dt = time.perf_counter() - t0
    print(f"{len(frames) - 1} frames {w}x{h} in {dt:.2f} s: {(len(frames) - 1) / dt:.1f} FPS ({n_ok} tracked, {tr.model.layout} landmarks)")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
