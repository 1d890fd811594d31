"""Video driving: ``fastgha client --from-video`` and the head pose -> render camera fold
(``fastgha_core.tracking.drive``).

The end-to-end test writes a short MP4 of matplotlib's Grace Hopper portrait drifting and
rolling over a grey background and streams it to a real server process (``server_process.py``).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from client_demo.client import look_at_camera
from fastgha_core.cameras import Cameras
from fastgha_core.cli import main as cli_main
from fastgha_core.tracking.drive import FRONTAL_R, DriveConfig, HeadPoseCamera, video_frames, webcam_frames
from server_process import API_KEY, ServerProcess, make_model_dir, make_sample_dir

pytestmark = pytest.mark.timeout(300)

NUM_FRAMES = 10
ROLL_DEG = np.linspace(-6.0, 6.0, NUM_FRAMES)  # counter-clockwise on screen (PIL's rotate)
SHIFT_PX = np.linspace(-30.0, 30.0, NUM_FRAMES)


def _rot(axis: str, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]  # fmt: skip


def _angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip((np.trace(A @ B.T) - 1) / 2, -1.0, 1.0)))


def _project(K, w2c, p) -> np.ndarray:
    x = np.asarray(w2c)[:3, :3] @ p + np.asarray(w2c)[:3, 3]
    uv = np.asarray(K) @ x
    return uv[:2] / uv[2]


# ---------------------------------------------------------------- the fold, without video
def test_reference_pose_gives_the_servers_frontal_camera():
    cam = HeadPoseCamera(DriveConfig(width=96, height=64))
    R0 = _rot("y", 12.0) @ _rot("x", -7.0) @ FRONTAL_R  # the user sits a bit sideways to the webcam
    K, w2c = cam(R0, np.array([0.03, -0.02, 0.6]))
    ref = look_at_camera((0.0, 0.0, 1.0), fov_deg=20.0, width=96, height=64)  # the server's default camera
    np.testing.assert_allclose(w2c, ref["w2c"], atol=1e-9)
    np.testing.assert_allclose(K, ref["K"], atol=1e-9)
    Cameras(torch.tensor(K, dtype=torch.float32), torch.tensor(w2c, dtype=torch.float32), 96, 64)  # a valid camera


@pytest.mark.parametrize("reference", ["first", "camera"])
@pytest.mark.parametrize("axis,deg", [("y", 25.0), ("y", -25.0), ("x", 15.0), ("x", -15.0)])
def test_turning_the_head_turns_the_avatar_the_same_way(reference, axis, deg):
    """The nose tip moves to the same side of the head centre in the video and in the render."""
    K_video = np.array([[900.0, 0, 320], [0, 900.0, 240], [0, 0, 1]])
    R0, t0 = _rot("y", -8.0) @ FRONTAL_R, np.array([0.02, 0.01, 0.7])
    cam = HeadPoseCamera(DriveConfig(width=128, height=128, reference=reference))
    cam(R0, t0)
    R = R0 @ _rot(axis, deg)  # the head turns about its own axis
    nose, centre = np.array([0.0, 0.0, 0.11]), np.zeros(3)
    w2c_video = np.eye(4)
    w2c_video[:3, :3], w2c_video[:3, 3] = R, t0
    move_video = _project(K_video, w2c_video, nose) - _project(K_video, w2c_video, centre)
    K, w2c = cam(R, t0)
    move_render = _project(K, w2c, nose) - _project(K, w2c, centre)
    i = 0 if axis == "y" else 1  # yaw moves the nose sideways, pitch up/down
    assert np.sign(move_render[i]) == np.sign(move_video[i]) != 0
    # relative to the reference view the render turned by exactly the head's turn
    _, w2c_ref = cam(R0, t0)
    assert _angle_deg(w2c[:3, :3], w2c_ref[:3, :3]) == pytest.approx(abs(deg), abs=1e-6)


def test_head_movement_moves_and_scales_the_avatar_within_bounds():
    cam = HeadPoseCamera(DriveConfig(distance=1.0))
    t0 = np.array([0.0, 0.0, 0.5])
    cam(FRONTAL_R, t0)
    _, w = cam(FRONTAL_R, t0 + np.array([0.02, 0.0, -0.05]))  # 2 cm right, 10 % closer
    np.testing.assert_allclose(w[:3, 3], [0.04, 0.0, 0.9], atol=1e-12)
    _, w = cam(FRONTAL_R, t0 + np.array([1.0, -1.0, 5.0]))  # far out: clamped into the frame
    np.testing.assert_allclose(w[:3, 3], [0.12, -0.12, 1.5], atol=1e-12)
    still = HeadPoseCamera(DriveConfig(follow_translation=False))
    still(FRONTAL_R, t0)
    np.testing.assert_allclose(still(FRONTAL_R, t0 + 0.1)[1][:3, 3], [0.0, 0.0, 1.0])


def test_bad_inputs_are_refused(tmp_path):
    with pytest.raises(ValueError, match="reference"):
        DriveConfig(reference="mirror")
    with pytest.raises(ValueError, match="in front of the camera"):
        HeadPoseCamera()(FRONTAL_R, np.array([0.0, 0.0, -1.0]))
    with pytest.raises(ValueError, match="no such video file"):
        video_frames(tmp_path / "missing.mp4")
    (tmp_path / "junk.mp4").write_bytes(b"not a video")
    with pytest.raises(ValueError, match="cannot read video"):
        video_frames(tmp_path / "junk.mp4")
    with pytest.raises(ValueError, match="no webcam at"):
        webcam_frames(str(tmp_path / "video9"))


# ---------------------------------------------------------------- end to end
def _make_clip(path: Path) -> None:
    import imageio_ffmpeg
    import matplotlib.cbook as cbook
    from PIL import Image

    src = Image.open(cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)).convert("RGB")
    src = src.resize((int(src.width * 360 / src.height), 360), Image.BILINEAR)
    w = imageio_ffmpeg.write_frames(str(path), (640, 480), fps=10, codec="libx264", quality=8, macro_block_size=16)
    w.send(None)
    for roll, dx in zip(ROLL_DEG, SHIFT_PX):
        canvas = Image.new("RGB", (640, 480), (96, 96, 96))
        face = src.rotate(float(roll), resample=Image.BILINEAR, expand=True, fillcolor=(96, 96, 96))
        canvas.paste(face, (int(320 + dx - face.width / 2), int(240 - face.height / 2)))
        w.send(np.ascontiguousarray(np.asarray(canvas)))
    w.close()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    model = make_model_dir(tmp_path_factory.mktemp("model"))
    srv = ServerProcess(model, tmp_path_factory.mktemp("data"), None, tmp_path_factory.mktemp("logs") / "server.log")
    yield srv
    srv.stop()


def test_client_drives_the_avatar_from_a_video(server, tmp_path, capsys):
    pytest.importorskip("dlib", reason="video driving needs the 'faces' extra (dlib-bin, face-recognition-models)")
    clip = tmp_path / "clip.mp4"
    _make_clip(clip)
    request_dir = make_sample_dir(tmp_path / "samples") / "request"
    out, fdir, npz = tmp_path / "avatar.mp4", tmp_path / "frames", tmp_path / "track.npz"
    n = NUM_FRAMES - 1  # bounded by --frames
    rc = cli_main(["client", "--url", server.base, "--input", str(request_dir), "--api-key", API_KEY, "--from-video", str(clip),
                   "--frames", str(n), "--size", "48", "--out", str(out), "--frames-dir", str(fdir), "--save-track", str(npz)])  # fmt: skip
    text = capsys.readouterr().out
    assert rc == 0, text
    assert f"{n} frames of {n} requested" in text and "tracking + streaming end to end" in text
    assert len(list(fdir.glob("frame_*.jpg"))) == n
    assert out.read_bytes()[4:8] == b"ftyp"

    tr = np.load(npz)
    assert list(tr["frame"]) == list(range(n))  # every frame had its face tracked
    expr, R, t, w2c = tr["expression"], tr["R"], tr["t"], tr["w2c"]
    assert expr.shape == (n, 53) and np.isfinite(expr).all() and expr.min() >= 0 and expr.max() <= 1
    assert np.isfinite(R).all() and np.isfinite(t).all() and np.isfinite(w2c).all()
    # a frontal portrait: every tracked pose within 15 degrees of facing the camera (docs/tracking.md,
    # "Real photo": the photo fit gives 2.9 degrees; the clip adds up to 6 degrees of roll)
    assert max(_angle_deg(r, FRONTAL_R) for r in R) < 15.0
    assert (t[:, 2] > 0.3).all() and (t[:, 2] < 3.0).all()
    # the render cameras are near the frontal one at the server's default distance
    assert max(_angle_deg(w[:3, :3], FRONTAL_R) for w in w2c) < 15.0
    assert np.abs(w2c[:, 2, 3] - 1.0).max() < 0.3
    # the clip rolls the face counter-clockwise by 12 degrees in all: the render camera rolls along
    # (a CCW turn on screen is a negative rotation about the camera's z axis, y pointing down)
    roll = np.degrees(np.arctan2(w2c[:, 1, 0], w2c[:, 0, 0]))
    expected = -(ROLL_DEG[n - 1] - ROLL_DEG[0])
    assert np.sign(roll[-1] - roll[0]) == np.sign(expected) and abs(roll[-1] - roll[0]) > 0.3 * abs(expected)
    # ...and the face moves right in the video, so the head centre moves towards camera +x
    assert t[-1, 0] > t[0, 0] and w2c[-1, 0, 3] > w2c[0, 0, 3]
