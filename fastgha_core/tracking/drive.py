"""Video driving: frames of a clip or a webcam -> tracked head pose -> the avatar's render camera.

The avatar is head-centric (head pose lives in the cameras, docs/conventions.md), so driving it from a
video means folding the tracked head pose into the camera that renders it:

- ``VideoTracker`` gives the head's pose in the video camera, ``x_cam = R x_head + t``.
- A **reference** pose ``(R_ref, t_ref)`` counts as "frontal": the first tracked frame
  (``reference="first"``, default: whatever way the user sits relative to the webcam looks straight
  at the viewer) or the head looking straight into the camera (``reference="camera"``,
  ``R_ref = FRONTAL_R``, ``t_ref`` still from the first frame).
- The render camera has rotation ``R_render = (R R_ref^T) FRONTAL_R``: the head's rotation
  relative to the reference, expressed in the camera, applied to the frontal render camera. A
  head that turns by some rotation in the video turns the avatar by the same rotation on screen.
- Translation: the head centre sits at ``(0, 0, distance)`` in the render camera, plus the
  head's movement relative to the reference scaled by ``distance / t_ref_z`` (so moving 10 %
  closer makes the avatar 10 % larger), clamped to ``max_offset_m`` sideways and to
  ``depth_range`` x ``distance`` in depth so the avatar stays in the frame.
- Intrinsics: the server's default frontal camera (``fov_deg`` 20 at ``distance`` 1 m, the
  training framing) for a ``width x height`` output, principal point at the centre.

Frame sources (``video_frames``, ``webcam_frames``) read with imageio-ffmpeg's bundled ffmpeg.
"""

from __future__ import annotations

import logging
import math
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["FRONTAL_R", "DriveConfig", "HeadPoseCamera", "video_frames", "webcam_frames", "VideoInfo"]

logger = logging.getLogger(__name__)

# [3, 3] rotation of the frontal camera (on +z, looking at the origin, +y up): camera x = world +x,
# camera y (down) = world -y, camera z (forward) = world -z. Also the pose of a head that looks
# straight into a camera.
FRONTAL_R = np.diag([1.0, -1.0, -1.0])


@dataclass
class DriveConfig:
    """Options of :class:`HeadPoseCamera`."""

    width: int = 256  # output frame size in pixels
    height: int = 256
    distance: float = 1.0  # metres from the head centre to the render camera (server default)
    fov_deg: float = 20.0  # vertical field of view of the render camera (server default)
    reference: str = "first"  # "first" | "camera" (module doc)
    follow_translation: bool = True  # move the avatar with the head, not only turn it
    max_offset_m: float = 0.12  # clamp of the sideways / vertical offset of the head centre
    depth_range: tuple[float, float] = (0.7, 1.5)  # clamp of the depth, as multiples of ``distance``

    def __post_init__(self) -> None:
        if self.reference not in ("first", "camera"):
            raise ValueError(f"reference must be 'first' or 'camera', got {self.reference!r}")
        if self.width < 1 or self.height < 1:
            raise ValueError(f"width and height must be positive, got {self.width}x{self.height}")
        if not (self.distance > 0 and 0 < self.fov_deg < 180):
            raise ValueError(f"need distance > 0 and 0 < fov_deg < 180, got {self.distance}, {self.fov_deg}")


class HeadPoseCamera:
    """Stateful: tracked head poses -> render cameras ``(K [3, 3], w2c [4, 4])`` (module doc)."""

    def __init__(self, config: DriveConfig | None = None) -> None:
        self.cfg = config or DriveConfig()
        c = self.cfg
        f = 0.5 * c.height / math.tan(math.radians(c.fov_deg) / 2)
        self.K = np.array([[f, 0.0, c.width / 2], [0.0, f, c.height / 2], [0.0, 0.0, 1.0]])  # [3, 3]
        self.reset()

    def reset(self) -> None:
        """Forget the reference: the next pose sets it."""
        self.R_ref: np.ndarray | None = None  # [3, 3]
        self.t_ref: np.ndarray | None = None  # [3]

    def __call__(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Head pose in the video camera (``R [3, 3]`` head -> camera, ``t [3]`` m) -> ``(K, w2c)``."""
        R = np.asarray(R, np.float64).reshape(3, 3)
        t = np.asarray(t, np.float64).reshape(3)
        if not (np.isfinite(R).all() and np.isfinite(t).all()) or t[2] <= 0:
            raise ValueError(f"expected a finite head pose in front of the camera, got R={R.tolist()}, t={t.tolist()}")
        c = self.cfg
        if self.R_ref is None:
            self.R_ref = R.copy() if c.reference == "first" else FRONTAL_R.copy()
            self.t_ref = t.copy()
        rot = R @ self.R_ref.T @ FRONTAL_R  # [3, 3]
        U, _, Vt = np.linalg.svd(rot)  # keep it exactly orthonormal
        rot = U @ Vt
        pos = np.array([0.0, 0.0, c.distance])
        if c.follow_translation:
            pos = pos + (t - self.t_ref) * (c.distance / self.t_ref[2])
            pos[:2] = np.clip(pos[:2], -c.max_offset_m, c.max_offset_m)
            pos[2] = np.clip(pos[2], c.depth_range[0] * c.distance, c.depth_range[1] * c.distance)
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = rot, pos
        return self.K.copy(), w2c

    def camera_object(self, R: np.ndarray, t: np.ndarray) -> dict:
        """The same as a protocol camera object ``{"K", "w2c", "width", "height"}`` (docs/protocol.md)."""
        K, w2c = self(R, t)
        return {"K": K.tolist(), "w2c": w2c.tolist(), "width": int(self.cfg.width), "height": int(self.cfg.height)}


# ---------------------------------------------------------------- frame sources
@dataclass
class VideoInfo:
    width: int
    height: int
    fps: float  # frames per second of the source (0 when unknown)


def _frames_from_reader(gen, what: str) -> tuple[VideoInfo, Iterator[np.ndarray]]:
    try:
        meta = gen.__next__()  # imageio-ffmpeg yields its metadata dict first
    except (RuntimeError, OSError, StopIteration) as e:
        gen.close()
        raise ValueError(f"cannot read {what}: {str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__}") from None
    w, h = (int(v) for v in meta["size"])
    info = VideoInfo(w, h, float(meta.get("fps") or 0.0))

    def frames() -> Iterator[np.ndarray]:
        try:
            for buf in gen:
                yield np.frombuffer(buf, np.uint8).reshape(h, w, 3)  # [H, W, 3]
        finally:
            gen.close()

    return info, frames()


def video_frames(path: str | Path, max_frames: int | None = None) -> tuple[VideoInfo, Iterator[tuple[np.ndarray, float]]]:
    """Frames of a video file: ``(info, iterator of (frame [H, W, 3] uint8 RGB, timestamp s))``.

    Every frame is returned (no dropping); timestamps are ``index / fps`` of the file.
    """
    import imageio_ffmpeg

    p = Path(path)
    if not p.is_file():
        raise ValueError(f"no such video file: {p}")
    info, frames = _frames_from_reader(imageio_ffmpeg.read_frames(str(p), pix_fmt="rgb24"), f"video {p}")
    fps = info.fps if info.fps > 0 else 30.0

    def timed() -> Iterator[tuple[np.ndarray, float]]:
        for i, f in enumerate(frames):
            if max_frames is not None and i >= max_frames:
                frames.close()
                return
            yield f, i / fps

    return info, timed()


def webcam_frames(
    device: str = "/dev/video0", max_frames: int | None = None, stop: threading.Event | None = None
) -> tuple[VideoInfo, Iterator[tuple[np.ndarray, float]]]:
    """Live frames of a V4L2 webcam (Linux): ``(info, iterator of (frame, timestamp s))``.

    A reader thread keeps only the newest frame, so a slow consumer gets the latest picture
    instead of an ever older backlog. Iteration ends after ``max_frames`` or when ``stop`` is set.
    """
    import imageio_ffmpeg

    if not sys.platform.startswith("linux"):
        raise ValueError(f"--webcam reads V4L2 devices (Linux only); on {sys.platform} record a clip and use --from-video")
    if not Path(device).exists():
        raise ValueError(f"no webcam at {device} (no such device; list them with `ls /dev/video*`, or use --from-video clip.mp4)")
    gen = imageio_ffmpeg.read_frames(device, input_params=["-f", "v4l2"], pix_fmt="rgb24")
    info, frames = _frames_from_reader(gen, f"webcam {device}")
    stop = stop or threading.Event()
    cond = threading.Condition()
    state = {"frame": None, "number": 0, "done": False, "error": None}  # shared with the reader thread

    def reader() -> None:
        try:
            for n, f in enumerate(frames, 1):
                with cond:
                    state["frame"], state["number"] = f, n
                    cond.notify_all()
                if stop.is_set():
                    break
        except Exception as e:  # handed to the consumer
            state["error"] = e
        finally:
            frames.close()
            with cond:
                state["done"] = True
                cond.notify_all()

    threading.Thread(target=reader, name="fastgha-webcam", daemon=True).start()

    def latest() -> Iterator[tuple[np.ndarray, float]]:
        seen, count, t0 = 0, 0, time.monotonic()
        try:
            while (max_frames is None or count < max_frames) and not stop.is_set():
                with cond:
                    if not cond.wait_for(lambda: state["number"] != seen or state["done"], timeout=10.0):
                        raise ValueError(f"webcam {device} sent no frame for 10 s")
                    if state["error"] is not None:
                        raise ValueError(f"reading webcam {device} failed: {state['error']}")
                    if state["number"] == seen:  # done, nothing new
                        return
                    frame, seen = state["frame"], state["number"]
                count += 1
                yield frame, time.monotonic() - t0
        finally:
            stop.set()

    return info, latest()
