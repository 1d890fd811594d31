"""Real-dataset readers on tiny fixtures written here in each dataset's exact format.

Expected cameras are computed by hand in the comments (not by the code under test).
"""

from __future__ import annotations

import io
import json
import math
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from fastgha_core.cameras import Cameras
from fastgha_core.constants import BACKGROUND_RGB
from fastgha_core.data.datasets import MissingViewError, open_ava256, open_nersemble, open_vhap
from fastgha_core.data.sample import View
from fastgha_core.data.sampling import TrainingDataset
from fastgha_core.expressions import flame120_from_axis_angle

W, H = 40, 60  # fixture image size (portrait, like the real rigs)


def _png(arr: np.ndarray) -> bytes:
    b = io.BytesIO()
    Image.fromarray(arr).save(b, format="PNG")
    return b.getvalue()


def _avif(arr: np.ndarray) -> bytes:
    b = io.BytesIO()
    Image.fromarray(arr).save(b, format="AVIF", quality=100)
    return b.getvalue()


def _color(t: int, c: int) -> np.ndarray:
    """A constant image that says which (timestep, camera) it is."""
    return np.broadcast_to(np.array([20 + 40 * t, 30 + 50 * c, 90], np.uint8), (H, W, 3)).copy()


def _check_types(seq, t: int = 0, c: int = 0) -> View:
    """All readers produce the same in-memory types."""
    cams = seq.cameras(t)
    assert isinstance(cams, Cameras) and cams.K.shape == (seq.num_cameras, 3, 3) and cams.w2c.shape == (seq.num_cameras, 4, 4)
    assert (cams.width, cams.height) == (W, H)
    v = seq.view(t, c)
    assert isinstance(v, View)
    assert v.image.shape == (3, H, W) and v.image.dtype == torch.float32
    assert v.mask.shape == (1, H, W) and v.mask.dtype == torch.float32
    assert float(v.image.min()) >= 0 and float(v.image.max()) <= 1
    assert v.depth is None or v.depth.shape == (1, H, W)
    return v


def _bg() -> torch.Tensor:
    return torch.tensor(BACKGROUND_RGB).view(3, 1, 1)


# ================================================================ Ava-256
def _write_ava(root: Path, with_fit: bool) -> Path:
    d = root / "m--20230101--1200--ABC123--GHS" / "decoder"
    d.mkdir(parents=True)
    # Calibration for 80x120 sensors (images are 40x60: scale 0.5). K and T stored transposed.
    K = np.array([[100.0, 0, 39.5], [0, 100.0, 59.5], [0, 0, 1]])
    # camera 400001 at world (0, 0, 1000 mm) looking at -z: R = diag(1,-1,-1), t = -R c = (0, 0, 1000)
    T1 = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1000], [0, 0, 0, 1]])
    # camera 400002 at world (1000 mm, 0, 0) looking at -x: rows x_cam=(0,0,-1), y_cam=(0,-1,0), z_cam=(-1,0,0)
    R2 = np.array([[0.0, 0, -1], [0, -1, 0], [-1, 0, 0]])
    T2 = np.eye(4)
    T2[:3, :3] = R2
    T2[:3, 3] = -R2 @ np.array([1000.0, 0, 0])
    krt = [{"cameraId": cid, "K": K.T.tolist(), "T": T.T.tolist()} for cid, T in (("400001", T1), ("400002", T2))]
    krt.append({"cameraId": "400003", "K": K.T.tolist(), "T": T1.T.tolist()})  # no images: must be skipped
    (d / "camera_calibration.json").write_text(json.dumps({"KRT": krt}))
    (d / "frame_list.csv").write_text("seg_id,frame_id\nEXP_a,0\nEXP_a,1\nEXP_b,2\n")
    (d / "image").mkdir()
    (d / "segmentation_parts").mkdir()
    for ci, cid in enumerate(("400001", "400002")):
        with zipfile.ZipFile(d / "image" / f"cam{cid}.zip", "w") as z:
            for t in range(3):
                enc = _avif if cid == "400002" else _png  # real files are AVIF; also accept PNG
                z.writestr(f"cam{cid}/{t:06d}.{'avif' if cid == '400002' else 'png'}", enc(_color(t, ci)))
        with zipfile.ZipFile(d / "segmentation_parts" / f"cam{cid}.zip", "w") as z:
            seg = np.zeros((H // 2, W // 2), np.uint8)  # lower-resolution segmentation
            seg[:, W // 4 :] = 2  # right half: "body" (foreground); left half 0 = background
            seg[: H // 4, W // 4 :] = 3  # top right: chair (background)
            for t in range(3):
                z.writestr(f"cam{cid}/{t:06d}.png", _png(seg))
    # head poses (3x4, head -> world, mm): frame 0 identity, frame 1 Ry(90 deg) + (10 mm, 0, 0)
    (d / "head_pose").mkdir()
    with zipfile.ZipFile(d / "head_pose" / "head_pose.zip", "w") as z:
        z.writestr("000000.txt", "1 0 0 0\n0 1 0 0\n0 0 1 0\n")
        z.writestr("000001.txt", "0 0 1 10\n0 1 0 0\n-1 0 0 0\n")
        z.writestr("000002.txt", "1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    # a precomputed depth prior for (frame 0, camera 400001), extracted folder form
    (d / "depth" / "cam400001").mkdir(parents=True)
    np.save(d / "depth" / "cam400001" / "000000.npy", np.full((H, W), 0.95, np.float32))
    if with_fit:
        rng = np.random.default_rng(0)
        np.savez(
            root / "fit.npz",
            frame_id=np.array([0, 2]),  # frame 1 has no fit -> dropped
            expr=rng.normal(size=(2, 100)).astype(np.float32),
            jaw_pose=rng.normal(size=(2, 3)).astype(np.float32) * 0.1,
            eyes_pose=rng.normal(size=(2, 6)).astype(np.float32) * 0.1,
        )
    return d.parent


def test_ava256_cameras_match_hand_computed(tmp_path):
    cap = _write_ava(tmp_path, with_fit=False)
    seqs = open_ava256(cap, calibration_size=(80, 120))
    assert [s.sequence for s in seqs] == ["EXP_a", "EXP_b"]
    a = seqs[0]
    assert a.num_cameras == 2 and a.camera_names == ["400001", "400002"] and a.num_timesteps == 2
    assert a.subject == "m--20230101--1200--ABC123--GHS" and a.expression_space == "none"
    cams0 = a.cameras(0)
    # K: cx = (39.5 + 0.5) * 0.5 = 20, cy = (59.5 + 0.5) * 0.5 = 30, f = 100 * 0.5 = 50
    K_expect = torch.tensor([[50.0, 0, 20], [0, 50, 30], [0, 0, 1]])
    torch.testing.assert_close(cams0.K[0], K_expect)
    torch.testing.assert_close(cams0.K[1], K_expect)
    # frame 0, identity head pose: w2c in metres
    torch.testing.assert_close(cams0.w2c[0], torch.tensor([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1], [0, 0, 0, 1]]))
    torch.testing.assert_close(cams0.centers[1], torch.tensor([1.0, 0, 0]), atol=1e-6, rtol=0)
    # frame 1: head -> world = [Ry(90) | (0.01, 0, 0)], w2c_head = w2c @ H:
    # R = diag(1,-1,-1) Ry = [[0,0,1],[0,-1,0],[1,0,0]], t = diag(1,-1,-1)(0.01,0,0) + (0,0,1) = (0.01,0,1)
    w1 = a.cameras(1).w2c[0]
    torch.testing.assert_close(w1, torch.tensor([[0.0, 0, 1, 0.01], [0, -1, 0, 0], [1, 0, 0, 1], [0, 0, 0, 1]]), atol=1e-6, rtol=0)
    # the head origin projects to u = 50 * 0.01 / 1 + 20 = 20.5, v = 30
    uv, z = a.cameras(1)[0:1].project(torch.zeros(1, 3))
    torch.testing.assert_close(uv[0, 0], torch.tensor([20.5, 30.0]))
    torch.testing.assert_close(z[0, 0], torch.tensor(1.0))


def test_ava256_views_masks_depth_and_expressions(tmp_path):
    cap = _write_ava(tmp_path, with_fit=True)
    seqs = open_ava256(cap, calibration_size=(80, 120), flame_fit=tmp_path / "fit.npz")
    a, b = seqs
    assert a.frame_ids == [0] and b.frame_ids == [2]  # frame 1 has no fit
    assert a.expression_space == "flame120"
    with np.load(tmp_path / "fit.npz") as z:
        expect = flame120_from_axis_angle(z["expr"][1], z["jaw_pose"][1], z["eyes_pose"][1])
    torch.testing.assert_close(b.expression(0), expect)
    v = _check_types(a, 0, 0)
    # mask: right half "body" minus the top-right "chair"
    m = torch.zeros(H, W)
    m[H // 2 :, W // 2 :] = 1
    torch.testing.assert_close(v.mask[0], m)
    col = torch.tensor(_color(0, 0)[0, 0], dtype=torch.float32) / 255
    torch.testing.assert_close(v.image[:, -1, -1], col)
    torch.testing.assert_close(v.image[:, 0, 0], _bg()[:, 0, 0])  # background composited
    torch.testing.assert_close(v.depth, torch.full((1, H, W), 0.95))
    v2 = _check_types(a, 0, 1)  # AVIF camera: lossy, so compare loosely
    assert v2.depth is None
    col2 = torch.tensor(_color(0, 1)[0, 0], dtype=torch.float32) / 255
    assert (v2.image[:, -1, -1] - col2).abs().max() < 0.04


def test_ava256_without_fit_is_refused_by_the_sampler(tmp_path):
    seqs = open_ava256(_write_ava(tmp_path, with_fit=False), calibration_size=(80, 120))
    assert seqs[0].expression(0).shape == (0,)
    with pytest.raises(ValueError, match="flame_fit"):
        TrainingDataset(seqs, num_inputs=1, num_targets=2)


def test_ava256_missing_frame_and_bad_calibration(tmp_path):
    cap = _write_ava(tmp_path, with_fit=False)
    d = cap / "decoder"
    (d / "frame_list.csv").write_text("seg_id,frame_id\nEXP_a,0\nEXP_a,7\n")
    with zipfile.ZipFile(d / "head_pose" / "head_pose.zip", "a") as z:
        z.writestr("000007.txt", "1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    seq = open_ava256(cap, calibration_size=(80, 120))[0]
    with pytest.raises(MissingViewError):
        seq.view(1, 0)
    with pytest.raises(ValueError, match="aspect ratio"):
        open_ava256(cap, calibration_size=(80, 80))
    (d / "camera_calibration.json").write_text(json.dumps({"cameras": []}))
    with pytest.raises(ValueError, match="KRT"):
        open_ava256(cap)


# ================================================================ NeRSemble
def _rz(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def _write_nersemble_calib(part: Path) -> None:
    (part / "calibration").mkdir(parents=True)
    w2c_a = np.eye(4)
    w2c_a[2, 3] = 2.0  # camera at world (0, 0, -2) looking along +z
    w2c_b = np.eye(4)
    w2c_b[:3, :3] = np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]])  # looking along +x... from (-2, 0, 0)
    w2c_b[:3, 3] = [0, 0, 2.0]
    params = {
        "world_2_cam": {"222200037": w2c_a.tolist(), "222200046": w2c_b.tolist()},
        "intrinsics": [[60.0, 0, 19.5], [0, 60.0, 29.5], [0, 0, 1]],
    }
    (part / "calibration" / "camera_params.json").write_text(json.dumps(params))


def _write_tracking(path: Path, T: int, frames: list[int]) -> dict:
    rng = np.random.default_rng(1)
    rot = np.zeros((T, 3))
    Rm = np.stack([np.eye(3)] + [_rz(90)] * (T - 1))
    trk = dict(
        shape=np.zeros((1, 300), np.float32),
        expression=rng.normal(size=(T, 100)).astype(np.float32),
        jaw=(rng.normal(size=(T, 3)) * 0.1).astype(np.float32),
        eyes=(rng.normal(size=(T, 6)) * 0.1).astype(np.float32),
        rotation=rot.astype(np.float32),
        rotation_matrices=Rm.astype(np.float32),
        translation=np.array([[0.0, 0, 0]] + [[0.2, 0, 0]] * (T - 1), np.float32),
        scale=np.array([[2.0]], np.float32),
        neck=np.zeros((T, 3), np.float32),
        frames=np.array(frames),
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **trk)
    return trk


def test_nersemble_extracted_frames_cameras_and_head_pose(tmp_path):
    part = tmp_path / "017"
    _write_nersemble_calib(part)
    seq = part / "sequences" / "EMO-1"
    serials = ["222200037", "222200046"]
    for fr in range(2):
        fd = seq / "timesteps" / f"frame_{fr:05d}"
        (fd / "images-2x").mkdir(parents=True)
        (fd / "alpha_map").mkdir()
        for ci, s in enumerate(serials):
            Image.fromarray(_color(fr, ci)).save(fd / "images-2x" / f"cam_{s}.jpg", quality=100)
            a = np.zeros((H, W), np.uint8)
            a[:, : W // 2] = 255
            Image.fromarray(a).save(fd / "alpha_map" / f"cam_{s}.png")
    trk = _write_tracking(seq / "tracking" / "flame2023_tracking.npz", T=2, frames=[1, 0])
    (out,) = open_nersemble(tmp_path, participant=17, calibration_size=(W, H))
    assert out.subject == "017" and out.sequence == "EMO-1" and out.camera_names == serials
    assert out.num_timesteps == 2 and out.frame_ids == [1, 0]
    c0 = out.cameras(0)
    # K: principal point + 0.5, no scaling (calibration_size = image size)
    torch.testing.assert_close(c0.K[0], torch.tensor([[60.0, 0, 20], [0, 60, 30], [0, 0, 1]]))
    # t=0: head pose identity, scale 2 -> translation / 2
    torch.testing.assert_close(c0.w2c[0], torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1]]))
    # t=1: x_w = 2 Rz(90) x + (0.2,0,0); camera a: w2c_head = [Rz(90) | ((0.2,0,0) + (0,0,2)) / 2] = [Rz90 | (0.1,0,1)]
    w = out.cameras(1).w2c[0]
    torch.testing.assert_close(w, torch.tensor([[0.0, -1, 0, 0.1], [1, 0, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1]]), atol=1e-6, rtol=0)
    # projections agree with the original world cameras for a FLAME model point
    x = torch.tensor([[0.03, -0.02, 0.05]], dtype=torch.float64)
    xw = 2.0 * torch.as_tensor(_rz(90)) @ x[0] + torch.tensor([0.2, 0, 0], dtype=torch.float64)
    for c in range(2):
        w2c_world = torch.tensor(json.loads((part / "calibration" / "camera_params.json").read_text())["world_2_cam"][serials[c]], dtype=torch.float64)
        pc = w2c_world[:3, :3] @ xw + w2c_world[:3, 3]
        uv_world = torch.tensor([60 * pc[0] / pc[2] + 20, 60 * pc[1] / pc[2] + 30])
        uv, z = out.cameras(1)[c : c + 1].project(x.float())
        torch.testing.assert_close(uv[0, 0], uv_world.float(), atol=1e-4, rtol=0)
        torch.testing.assert_close(z[0, 0], (pc[2] / 2).float())
    # expression of timestep 1 = tracking row 1 as flame120; its image is frame folder 0
    torch.testing.assert_close(out.expression(1), flame120_from_axis_angle(trk["expression"][1], trk["jaw"][1], trk["eyes"][1]))
    v = _check_types(out, 1, 1)
    col = torch.tensor(_color(0, 1)[0, 0], dtype=torch.float32) / 255
    assert (v.image[:, 5, 2] - col).abs().max() < 0.03  # jpg: loose
    torch.testing.assert_close(v.image[:, 5, -3], _bg()[:, 0, 0])
    assert float(v.mask[0, :, : W // 2].min()) == 1.0 and float(v.mask[0, :, W // 2 :].max()) == 0.0


def test_nersemble_videos(tmp_path):
    imageio = pytest.importorskip("imageio.v2")
    part = tmp_path / "017"
    _write_nersemble_calib(part)
    seq = part / "sequences" / "SEN-01"
    (seq / "images").mkdir(parents=True)
    (seq / "alpha_maps").mkdir()
    for ci, s in enumerate(["222200037", "222200046"]):
        with imageio.get_writer(seq / "images" / f"cam_{s}.mp4", fps=25, codec="libx264", quality=10, macro_block_size=1) as wr:
            for fr in range(3):
                wr.append_data(_color(fr, ci))
        with imageio.get_writer(seq / "alpha_maps" / f"cam_{s}.mp4", fps=25, codec="libx264", quality=10, macro_block_size=1) as wr:
            for fr in range(3):
                wr.append_data(np.full((H, W, 3), 255, np.uint8))
    # without tracking: every frame is a timestep, no expressions
    (plain,) = open_nersemble(part, calibration_size=(W, H))
    assert plain.num_timesteps == 3 and plain.expression_space == "none"
    torch.testing.assert_close(plain.cameras(2).w2c, plain.cameras(0).w2c)
    _write_tracking(seq / "tracking" / "flame2023_tracking.npz", T=2, frames=[2, 0])
    (out,) = open_nersemble(part, calibration_size=(W, H))
    v = _check_types(out, 0, 1)  # video frame 2 of camera 1
    col = torch.tensor(_color(2, 1)[0, 0], dtype=torch.float32) / 255
    assert (v.image[:, H // 2, W // 2] - col).abs().max() < 0.06
    assert float(v.mask.min()) > 0.9


# ================================================================ VHAP
def test_vhap_export_cameras_head_pose_and_views(tmp_path):
    root = tmp_path / "export" / "074_EMO-1"
    (root / "images").mkdir(parents=True)
    (root / "fg_masks").mkdir()
    (root / "flame_param").mkdir()
    (root / "depth").mkdir()
    frames = []
    # camera 0: c2w (OpenGL) = translate (0, 0, 1): at z = 1 looking along -z
    # camera 1: at (1, 0, 0) looking along -x: GL axes x_cam = (0,0,-1), y_cam = (0,1,0), z_cam (backward) = (1,0,0)
    c2ws = [
        [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1]],
        [[0, 0, 1, 1], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]],
    ]
    rng = np.random.default_rng(2)
    for t in range(2):
        for c in range(2):
            stem = f"{t:05d}_{c:02d}"
            Image.fromarray(_color(t, c)).save(root / "images" / f"{stem}.png")
            m = np.zeros((H, W), np.uint8)
            m[H // 2 :] = 255
            Image.fromarray(m).save(root / "fg_masks" / f"{stem}.png")
            frames.append(
                dict(timestep_index=t, timestep_index_original=t, timestep_id=f"frame_{t:05d}", camera_index=c, camera_id=f"cam{c}",
                     cx=19.5, cy=20.0, fl_x=50.0, fl_y=52.0, h=H, w=W, transform_matrix=c2ws[c],
                     file_path=f"images/{stem}.png", fg_mask_path=f"fg_masks/{stem}.png", flame_param_path=f"flame_param/{t:05d}.npz")
            )
        np.savez(
            root / "flame_param" / f"{t:05d}.npz",
            translation=np.array([[0.0, 0.05, 0.0]]) if t else np.zeros((1, 3)),
            rotation=np.array([[0.0, math.pi / 2, 0.0]]) if t else np.zeros((1, 3)),
            neck_pose=np.zeros((1, 3)), jaw_pose=rng.normal(size=(1, 3)) * 0.1, eyes_pose=rng.normal(size=(1, 6)) * 0.1,
            shape=np.zeros(300), expr=rng.normal(size=(1, 50)),
        )
    np.save(root / "depth" / "00001_01.npy", np.full((H, W), 0.8, np.float32))
    (root / "transforms.json").write_text(json.dumps({"frames": frames, "timestep_indices": [0, 1], "camera_indices": [0, 1]}))
    (out,) = open_vhap(root, root_joint=(0.1, 0.0, 0.0))
    assert out.subject == "074_EMO-1" and out.num_timesteps == 2 and out.num_cameras == 2
    K = out.cameras(0).K[0]
    # VHAP writes cy from the bottom row (its opencv->opengl conversion: K[1,2] = H - K[1,2]): 60 - 20 = 40
    torch.testing.assert_close(K, torch.tensor([[50.0, 0, 19.5], [0, 52, 40.0], [0, 0, 1]]))
    # camera 0: OpenCV w2c = [diag(1,-1,-1) | (0, 0, 1)]
    torch.testing.assert_close(out.cameras(0).w2c[0], torch.tensor([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1], [0, 0, 0, 1]]))
    # camera 1: OpenCV rows x=(0,0,-1), y=(0,-1,0), z=(-1,0,0); t = -R (1,0,0) = (0,0,1)
    torch.testing.assert_close(out.cameras(0).w2c[1], torch.tensor([[0.0, 0, -1, 0], [0, -1, 0, 0], [-1, 0, 0, 1], [0, 0, 0, 1]]))
    # t=1: R = Ry(90) about J0 = (0.1,0,0), t = (0,0.05,0): head->world translation
    # = t + J0 - R J0 = (0,0.05,0) + (0.1,0,0) - (0,0,-0.1) = (0.1, 0.05, 0.1)
    # camera 0: R = diag(1,-1,-1) Ry = [[0,0,1],[0,-1,0],[1,0,0]], t = (0.1, -0.05, -0.1) + (0,0,1) = (0.1,-0.05,0.9)
    torch.testing.assert_close(
        out.cameras(1).w2c[0], torch.tensor([[0.0, 0, 1, 0.1], [0, -1, 0, -0.05], [1, 0, 0, 0.9], [0, 0, 0, 1]]), atol=1e-6, rtol=0
    )
    with np.load(root / "flame_param" / "00001.npz") as z:
        expect = flame120_from_axis_angle(z["expr"][0], z["jaw_pose"][0], z["eyes_pose"][0])
    torch.testing.assert_close(out.expression(1), expect)
    v = _check_types(out, 1, 1)
    torch.testing.assert_close(v.depth, torch.full((1, H, W), 0.8))
    col = torch.tensor(_color(1, 1)[0, 0], dtype=torch.float32) / 255
    torch.testing.assert_close(v.image[:, -1, 0], col)
    torch.testing.assert_close(v.image[:, 0, 0], _bg()[:, 0, 0])
    assert _check_types(out, 0, 0).depth is None


def test_readers_feed_the_training_sampler(tmp_path):
    """Any reader's sequences go through the sampler and DataLoader workers (pickled sources)."""
    cap = _write_ava(tmp_path, with_fit=True)
    seqs = open_ava256(cap, calibration_size=(80, 120), flame_fit=tmp_path / "fit.npz")
    ds = TrainingDataset(seqs, num_inputs=1, num_targets=2, seed=3, resolution=24)
    s = ds[0]
    assert s.input_images.shape == (1, 3, 24, 24) and s.target_images.shape == (2, 3, 24, 24)
    assert s.expression.shape == (120,)
    import pickle

    ds2 = pickle.loads(pickle.dumps(ds))
    torch.testing.assert_close(ds2[0].target_images, s.target_images)
