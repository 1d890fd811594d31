"""Cameras: geometry on hand-computed numbers, validation, Plücker rays, converters, sampling."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
import torch
from torch.testing import assert_close

from fastgha_core.cameras import (
    Cameras,
    cameras_from_flame_pose,
    cameras_from_json,
    cameras_to_json,
    farthest_viewpoint_sampling,
    fold_head_pose,
    head_pose_matrix,
    load_request_folder,
    look_at_w2c,
    parse_ava256_krt,
    plucker_rays,
    read_ava256_calibration_json,
    read_ava256_krt,
    read_nersemble_camera_params,
    read_transforms_json,
)


def t64(x):
    return torch.tensor(x, dtype=torch.float64)


def front_camera(width=100, height=100):
    # Camera at z = 2 looking at the origin, 90° vertical FoV: f = 50 / tan(45°) = 50.
    return Cameras.look_at(torch.tensor([0.0, 0.0, 2.0]), fov_deg=90.0, width=width, height=height)


# ---------------------------------------------------------------- geometry by hand
def test_look_at_matrix_by_hand():
    cam = front_camera()
    # Right = world +x (subject's left on image right), down = world -y, forward = world -z.
    expected = t64([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 2], [0, 0, 0, 1]]).float()
    assert_close(cam.w2c, expected)
    assert_close(cam.K, torch.tensor([[50.0, 0, 50], [0, 50, 50], [0, 0, 1]]))
    assert_close(cam.centers, torch.tensor([0.0, 0.0, 2.0]))
    expected_c2w = torch.tensor([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 2], [0, 0, 0, 1]])
    assert_close(cam.c2w, expected_c2w)  # this c2w is its own inverse


def test_c2w_is_inverse_of_w2c_for_general_pose():
    w2c = look_at_w2c(torch.tensor([[0.3, -0.4, 1.2], [-1.0, 0.2, 0.5]]), target=(0.05, 0.1, 0.0))
    cams = Cameras(torch.eye(3).expand(2, 3, 3).clone() + torch.diag(torch.tensor([9.0, 9.0, 0.0])), w2c, 10, 10)
    assert_close(cams.c2w @ cams.w2c, torch.eye(4).expand(2, 4, 4), atol=1e-6, rtol=0)
    # Centre is where the camera sits: it maps to the camera origin.
    pc = cams.world_to_camera(cams.centers[:, None, :])
    assert_close(pc, torch.zeros(2, 1, 3), atol=1e-6, rtol=0)


def test_project_resize_crop_by_hand():
    cam = front_camera()
    p = torch.tensor([[0.1, 0.2, 0.0]])
    # camera coords (0.1, -0.2, 2): u = 50 + 50*0.1/2 = 52.5, v = 50 - 50*0.2/2 = 45
    uv, z = cam.project(p)
    assert_close(uv, torch.tensor([[[52.5, 45.0]]]).squeeze(0))
    assert_close(z, torch.tensor([2.0]))
    # resize 100x100 -> 200x50: fx=100 cx=100, fy=25 cy=25 -> (105, 22.5)
    r = cam.resize(200, 50)
    assert (r.width, r.height) == (200, 50)
    assert_close(r.K, torch.tensor([[100.0, 0, 100], [0, 25, 25], [0, 0, 1]]))
    assert_close(r.project(p)[0], torch.tensor([[105.0, 22.5]]))
    # crop at left=10, top=20: principal point shifts to (40, 30) -> (42.5, 25)
    c = cam.crop(10, 20, 60, 40)
    assert (c.width, c.height) == (60, 40)
    assert_close(c.project(p)[0], torch.tensor([[42.5, 25.0]]))


def test_stack_index_flatten():
    a, b = front_camera(), Cameras.look_at(torch.tensor([[1.0, 0.0, 1.0], [0.0, 1.0, 2.0]]), width=100, height=100)
    s = Cameras.stack([a, b])
    assert s.batch_shape == (3,)
    assert_close(s[2].w2c, b.w2c[1])
    assert s.flatten().batch_shape == (3,)
    with pytest.raises(ValueError, match="one image size"):
        Cameras.stack([a, front_camera(64, 64)])


# ---------------------------------------------------------------- validation
def _ok():
    return torch.tensor([[50.0, 0, 50], [0, 50, 50], [0, 0, 1]]), torch.eye(4)


def test_validation_non_finite():
    K, w2c = _ok()
    w2c[0, 3] = float("nan")
    with pytest.raises(ValueError, match=r"w2c must be finite.*non-finite"):
        Cameras(K, w2c, 100, 100)
    K, w2c = _ok()
    K[0, 2] = float("inf")
    with pytest.raises(ValueError, match="K must be finite"):
        Cameras(K, w2c, 100, 100)


def test_validation_non_orthonormal_rotation():
    K, w2c = _ok()
    w2c[0, 0] = 1.5
    with pytest.raises(ValueError, match=r"orthonormal.*got max deviation 1\.2"):
        Cameras(K, w2c, 100, 100)
    K, w2c = _ok()
    w2c[0, 0] = -1.0  # reflection
    with pytest.raises(ValueError, match="reflection"):
        Cameras(K, w2c, 100, 100)


def test_validation_focal_and_shapes():
    K, w2c = _ok()
    K[1, 1] = -5.0
    with pytest.raises(ValueError, match=r"focal lengths must be positive, got .*fy=\[-5\.0\]"):
        Cameras(K, w2c, 100, 100)
    K, w2c = _ok()
    with pytest.raises(ValueError, match=r"K must have shape \[\.\.\., 3, 3\], got \(4, 4\)"):
        Cameras(torch.eye(4), w2c, 100, 100)
    with pytest.raises(ValueError, match=r"w2c must have shape \[\.\.\., 4, 4\], got \(3, 3\)"):
        Cameras(K, torch.eye(3), 100, 100)
    with pytest.raises(ValueError, match="width and height must be positive, got 0x100"):
        Cameras(K, w2c, 0, 100)


# ---------------------------------------------------------------- Plücker rays
def _brute_force_plucker(K, w2c, W, H, h, w):
    """Per-pixel loop in float64 numpy: pixel centres of an h x w grid over the W x H image."""
    K, w2c = np.asarray(K, np.float64), np.asarray(w2c, np.float64)
    sx, sy = w / W, h / H
    fx, fy, cx, cy = K[0, 0] * sx, K[1, 1] * sy, K[0, 2] * sx, K[1, 2] * sy
    R, t = w2c[:3, :3], w2c[:3, 3]
    o = -R.T @ t
    out = np.zeros((6, h, w))
    for i in range(h):
        for j in range(w):
            d_cam = np.array([(j + 0.5 - cx) / fx, (i + 0.5 - cy) / fy, 1.0])
            d = R.T @ d_cam
            d /= np.linalg.norm(d)
            out[:3, i, j] = d
            out[3:, i, j] = np.cross(o, d)
    return out


def test_plucker_rays_match_brute_force():
    eyes = torch.tensor([[0.3, 0.2, 1.5], [-0.8, -0.1, 0.9]], dtype=torch.float64)
    w2c = look_at_w2c(eyes, target=torch.tensor([0.02, 0.05, 0.0], dtype=torch.float64))
    K = torch.tensor([[[120.0, 0, 61], [0, 110, 47], [0, 0, 1]], [[90.0, 0, 50], [0, 95, 52], [0, 0, 1]]], dtype=torch.float64)
    cams = Cameras(K, w2c, 120, 96)
    rays = plucker_rays(cams, 6, 5)
    assert rays.shape == (2, 6, 6, 5)
    for c in range(2):
        ref = _brute_force_plucker(K[c], w2c[c], 120, 96, 6, 5)
        assert_close(rays[c], torch.from_numpy(ref), atol=1e-10, rtol=0)
    # moment is orthogonal to direction
    assert_close((rays[:, :3] * rays[:, 3:]).sum(1), torch.zeros(2, 6, 5, dtype=torch.float64), atol=1e-12, rtol=0)


def test_centre_pixel_ray_points_at_target():
    cam = front_camera(4, 4)  # principal point (2, 2) = corner between the 4 centre pixels
    rays = plucker_rays(cam, 4, 4)
    d = rays[:3, 1:3, 1:3].mean(dim=(1, 2))
    assert_close(d / d.norm(), torch.tensor([0.0, 0.0, -1.0]), atol=1e-6, rtol=0)


# ---------------------------------------------------------------- JSON + request folder
def test_json_round_trip_and_errors(tmp_path):
    cam = front_camera()
    objs = cameras_to_json(cam)
    back = cameras_from_json(json.dumps(objs))
    assert len(back) == 1 and back[0].batch_shape == (1,)
    assert_close(back[0].w2c[0], cam.w2c)
    with pytest.raises(ValueError, match=r"camera 0: K must be 3x3, got shape \(2, 2\)"):
        cameras_from_json({"K": [[1, 0], [0, 1]], "w2c": objs[0]["w2c"], "width": 4, "height": 4})
    (tmp_path / "b.png").write_bytes(b"")
    (tmp_path / "a.png").write_bytes(b"")
    (tmp_path / "a_mask.png").write_bytes(b"")
    (tmp_path / "cameras.json").write_text(json.dumps(objs * 2))
    images, cams = load_request_folder(tmp_path)
    assert [p.name for p in images] == ["a.png", "b.png"] and len(cams) == 2
    (tmp_path / "c.png").write_bytes(b"")  # a file that is not a view: the message names the images
    with pytest.raises(ValueError, match=r"3 images \(a\.png, b\.png, c\.png\) but 2 cameras in cameras\.json"):
        load_request_folder(tmp_path)
    (tmp_path / "c.png").unlink()
    with pytest.raises(ValueError, match=r"a\.png is a file; expected a folder of photos"):
        load_request_folder(tmp_path / "a.png")  # a photo given where its folder is meant
    with pytest.raises(ValueError, match=r"nowhere does not exist"):
        load_request_folder(tmp_path / "nowhere")
    (tmp_path / "cameras.json").unlink()  # photos alone: the message says how to get cameras
    # the suggested command takes the folder's own photo globs and a NEW folder (track refuses to write
    # into a folder of other photos), which --input then names
    tracked = re.escape(f"out/{tmp_path.name}-tracked")
    with pytest.raises(ValueError, match=rf"has no cameras\.json; .*`fastgha track --images {re.escape(str(tmp_path))}/\*\.png --out {tracked}`.* --input {tracked}$"):
        load_request_folder(tmp_path)


# ---------------------------------------------------------------- converters (hand-computed answers)
KRT_TEXT = """400004
1000 0 300
0 1100 500
0 0 1
0 0 0 0 0
0 0 -1 100
0 1 0 -200
1 0 0 1000

400007
800 0 0
0 810 0
333 512 1
0 0 0 0 0
1 0 0 0
0 1 0 0
0 0 1 2000

"""


def test_ava256_krt_text(tmp_path):
    # Producer check (facebookresearch/ava-256 data/ava_dataset.py): focal = diag(intrin[:2, :2]),
    # princpt = intrin[:2, 2] with the KRT rows read as rows, and pixel coordinates np.arange(W) (integer
    # pixel centres, OpenCV): hence +0.5 to our corner origin; extrinsic rows = world -> camera [R | t].
    path = tmp_path / "KRT"
    path.write_text(KRT_TEXT)
    cams = read_ava256_krt(path, width=600, height=1000)
    assert list(cams) == ["400004", "400007"]
    a = cams["400004"]
    # translation mm -> m: (0.1, -0.2, 1.0)
    expected = torch.tensor([[0.0, 0, -1, 0.1], [0, 1, 0, -0.2], [1, 0, 0, 1.0], [0, 0, 0, 1]])
    assert_close(a.w2c[0], expected)
    # OpenCV principal point (300, 500) -> +0.5 for our pixel-corner origin
    assert_close(a.K[0], torch.tensor([[1000.0, 0, 300.5], [0, 1100, 500.5], [0, 0, 1]]))
    # centre = -R^T t = -(1.0, -0.2, -0.1)
    assert_close(a.centers[0], torch.tensor([-1.0, 0.2, 0.1]))
    # world origin -> camera (0.1, -0.2, 1.0) -> u = 1000*0.1 + 300.5 = 400.5, v = 1100*(-0.2) + 500.5 = 280.5
    assert_close(a.project(torch.zeros(1, 3))[0][0], torch.tensor([[400.5, 280.5]]))
    # second camera has K stored transposed: fx=800, fy=810, cx=333, cy=512 (+0.5 each)
    b = cams["400007"]
    assert_close(b.K[0], torch.tensor([[800.0, 0, 333.5], [0, 810, 512.5], [0, 0, 1]]))
    assert_close(b.centers[0], torch.tensor([0.0, 0.0, -2.0]))
    assert (b.width, b.height) == (600, 1000)
    # a K already in our convention is kept with principal_point_shift=0
    raw = read_ava256_krt(path, width=600, height=1000, principal_point_shift=0.0)
    assert_close(raw["400004"].K[0, 0, 2], torch.tensor(300.0))


def test_ava256_krt_bad_block():
    with pytest.raises(ValueError, match="expected 7 lines"):
        parse_ava256_krt("cam\n1 0 0\n0 1 0\n")


def test_ava256_calibration_json():
    data = {
        "KRT": [
            {
                "cameraId": "401",
                "width": 667,
                "height": 1024,
                # K = [[800, 0, 333], [0, 810, 512], [0, 0, 1]] stored transposed
                "K": [[800, 0, 0], [0, 810, 0], [333, 512, 1]],
                # w2c = [[1,0,0,10],[0,-1,0,20],[0,0,-1,3000],[0,0,0,1]] (mm) stored transposed
                "T": [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 0], [10, 20, 3000, 1]],
                "distortion": [0, 0, 0, 0, 0],
            },
            {   # 3x4 extrinsic stored transposed as 4x3, no size in the file
                "cameraId": "402",
                "K": [[500, 0, 0], [0, 500, 0], [100, 200, 1]],
                "T": [[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 500]],
            },
        ]
    }
    with pytest.raises(ValueError, match="pass width= and height="):
        read_ava256_calibration_json(data)
    cams = read_ava256_calibration_json(data, width=200, height=400)
    a = cams["401"]
    assert (a.width, a.height) == (667, 1024)
    assert_close(a.K[0], torch.tensor([[800.0, 0, 333.5], [0, 810, 512.5], [0, 0, 1]]))
    assert_close(a.w2c[0], torch.tensor([[1.0, 0, 0, 0.01], [0, -1, 0, 0.02], [0, 0, -1, 3.0], [0, 0, 0, 1]]))
    assert_close(a.centers[0], torch.tensor([-0.01, 0.02, 3.0]))
    # origin -> camera (0.01, 0.02, 3) -> u = 800*0.01/3 + 333.5, v = 810*0.02/3 + 512.5 = 517.9
    assert_close(a.project(torch.zeros(1, 3))[0][0], torch.tensor([[333.5 + 8.0 / 3.0, 517.9]]))
    b = cams["402"]
    assert (b.width, b.height) == (200, 400)
    assert_close(b.centers[0], torch.tensor([0.0, 0.0, -0.5]))


def test_nersemble_camera_params(tmp_path):
    # Producer check (tobias-kirschstein/nersemble-benchmark README, "Load cameras"): world_2_cam is a 4x4
    # world -> camera matrix "in OpenCV camera coordinate convention", intrinsics a 3x3 K (OpenCV pixel
    # centres at integers: +0.5 to our corner origin).
    data = {
        "world_2_cam": {"222200037": [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1], [0, 0, 0, 1]]},
        "intrinsics": [[2000, 0, 1100], [0, 2000, 1604], [0, 0, 1]],
    }
    path = tmp_path / "camera_params.json"
    path.write_text(json.dumps(data))
    cams = read_nersemble_camera_params(path, width=2200, height=3208)
    c = cams["222200037"]
    assert_close(c.centers[0], torch.tensor([0.0, 0.0, 1.0]))
    # principal point (1100, 1604) + 0.5 (OpenCV integer pixel centres -> ours)
    # (0.05, 0.1, 0) -> camera (0.05, -0.1, 1) -> u = 100 + 1100.5 = 1200.5, v = -200 + 1604.5 = 1404.5
    assert_close(c.project(torch.tensor([[0.05, 0.1, 0.0]]))[0][0], torch.tensor([[1200.5, 1404.5]]))
    with pytest.raises(ValueError, match="expected keys 'world_2_cam' and 'intrinsics'"):
        read_nersemble_camera_params({"intrinsics": data["intrinsics"]}, width=1, height=1)


def test_transforms_json_opengl_c2w():
    data = {
        "fl_x": 500, "fl_y": 500, "cx": 256, "cy": 256, "w": 512, "h": 512,
        "frames": [
            # OpenGL camera at (0, 0, 2), looking down -z, y up
            {"transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2], [0, 0, 0, 1]]},
            # camera at (2, 0, 0) looking at the origin: right = (0,0,-1), up = y, back = +x; own intrinsics
            {"transform_matrix": [[0, 0, 1, 2], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]],
             "fl_x": 300, "fl_y": 320, "cx": 128, "cy": 64, "w": 256, "h": 128},
        ],
    }  # fmt: skip
    a, b = read_transforms_json(data)
    assert_close(a.w2c[0], torch.tensor([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 2], [0, 0, 0, 1]]))
    # (0.1, 0.2, 0) -> cv camera (0.1, -0.2, 2) -> (256 + 25, 256 - 50)
    assert_close(a.project(torch.tensor([[0.1, 0.2, 0.0]]))[0][0], torch.tensor([[281.0, 206.0]]))
    assert (b.width, b.height) == (256, 128)
    assert_close(b.w2c[0], torch.tensor([[0.0, 0, -1, 0], [0, -1, 0, 0], [-1, 0, 0, 2], [0, 0, 0, 1]]))
    # (0, 0.1, -0.3) -> cv camera (0.3, -0.1, 2) -> (128 + 300*0.15, 64 - 320*0.05) = (173, 48)
    assert_close(b.project(torch.tensor([[0.0, 0.1, -0.3]]))[0][0], torch.tensor([[173.0, 48.0]]))


def test_transforms_json_camera_angle_x():
    # fl_x = 0.5 * 100 / tan(atan(0.5)) = 100, centre (50, 40)
    data = {"camera_angle_x": 2 * math.atan(0.5), "w": 100, "h": 80,
            "frames": [{"transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2], [0, 0, 0, 1]]}]}  # fmt: skip
    (c,) = read_transforms_json(data)
    assert_close(c.K[0], torch.tensor([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]]))
    with pytest.raises(ValueError, match="no focal length"):
        read_transforms_json({"w": 1, "h": 1, "frames": data["frames"]})


def test_transforms_json_vhap_cy_from_bottom_hand_worked():
    """VHAP's export of a NeRSemble camera (ShenhanQian/VHAP vhap/util/camera.py, convert_camera_convention
    "opencv->opengl": R[:, :3, [1, 2]] *= -1 and K[1, 2] = H - K[1, 2]).

    Source camera (OpenCV): fx = fy = 1000, cx = 550, cy = 700 on 1100 x 1604 images, at (0, 0, 1)
    looking down -z. VHAP writes cy = 1604 - 700 = 904 and the OpenGL c2w = translate(0, 0, 1).
    The world point (0.02, -0.1, 0) is at OpenCV camera (0.02, 0.1, 1): u = 20 + 550 = 570,
    v = 100 + 700 = 800. Reading cy as stored puts it at v = 1004 (204 px off; 2 cy - H in general).
    """
    frame = {"timestep_index": 0, "camera_index": 0, "fl_x": 1000.0, "fl_y": 1000.0, "cx": 550.0, "cy": 904.0, "w": 1100, "h": 1604,
             "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1]]}  # fmt: skip
    p = torch.tensor([[0.02, -0.1, 0.0]])
    (c,) = read_transforms_json({"frames": [frame]})  # auto: a VHAP export (timestep/camera indices)
    assert_close(c.K[0, 1, 2], torch.tensor(700.0))
    assert_close(c.project(p)[0][0], torch.tensor([[570.0, 800.0]]))
    (same,) = read_transforms_json({"frames": [frame]}, principal_point_origin="bottom")
    assert_close(same.K, c.K)
    (top,) = read_transforms_json({"frames": [frame]}, principal_point_origin="top")  # nerfstudio reading
    assert_close(top.project(p)[0][0], torch.tensor([[570.0, 1004.0]]))
    plain = {k: v for k, v in frame.items() if k not in ("timestep_index", "camera_index")}
    (ns,) = read_transforms_json({"frames": [plain]})  # a nerfstudio file: cy from the top, kept
    assert_close(ns.K[0, 1, 2], torch.tensor(904.0))
    with pytest.raises(ValueError, match="principal_point_origin"):
        read_transforms_json({"frames": [frame]}, principal_point_origin="middle")


def test_flame_pose_opengl_camera():
    # Head rotated 90° about y, 0.5 m in front of an OpenGL camera (at z = -0.5).
    # R_y(90°) = [[0,0,1],[0,1,0],[-1,0,0]]; nose tip (0, 0, 0.1) -> R x = (0.1, 0, 0) -> + t = (0.11, 0.02, -0.5)
    # OpenCV camera: (0.11, -0.02, 0.5) -> u = 256 + 1000*0.11/0.5 = 476, v = 256 - 1000*0.02/0.5 = 216
    K = torch.tensor([[1000.0, 0, 256], [0, 1000, 256], [0, 0, 1]])
    cam = cameras_from_flame_pose(torch.tensor([0.0, math.pi / 2, 0.0]), torch.tensor([0.01, 0.02, -0.5]), K, 512, 512)
    expected = torch.tensor([[0.0, 0, 1, 0.01], [0, -1, 0, -0.02], [1, 0, 0, 0.5], [0, 0, 0, 1]])
    assert_close(cam.w2c, expected, atol=1e-6, rtol=0)
    uv, z = cam.project(torch.tensor([[0.0, 0.0, 0.1]]))
    assert_close(uv, torch.tensor([[476.0, 216.0]]), atol=1e-3, rtol=0)
    assert_close(z, torch.tensor([0.5]))
    # With a pivot p = (0, 0, -0.05): x_cam = R (x - p) + p + t; for x = (0, 0, 0.05): x - p = (0, 0, 0.1)
    # -> R: (0.1, 0, 0) -> + p + t = (0.11, 0.02, -0.55) -> OpenCV (0.11, -0.02, 0.55)
    cam_p = cameras_from_flame_pose(
        torch.tensor([0.0, math.pi / 2, 0.0]), torch.tensor([0.01, 0.02, -0.5]), K, 512, 512, pivot=torch.tensor([0.0, 0.0, -0.05])
    )
    assert_close(cam_p.world_to_camera(torch.tensor([[0.0, 0.0, 0.05]])), torch.tensor([[0.11, -0.02, 0.55]]), atol=1e-6, rtol=0)
    # opencv convention: no axis flip
    cam_cv = cameras_from_flame_pose(torch.zeros(3), torch.tensor([0.0, 0.0, 0.5]), K, 512, 512, camera_convention="opencv")
    assert_close(cam_cv.world_to_camera(torch.tensor([[0.0, 0.1, 0.0]])), torch.tensor([[0.0, 0.1, 0.5]]))


def test_fold_head_pose_and_small_angle_pose():
    # Camera w2c = identity; head placed 1 m ahead, turned 180° about y: x_world = diag(-1,1,-1) x_head + (0,0,1)
    cam = Cameras(torch.tensor([[[100.0, 0, 50], [0, 100, 50], [0, 0, 1]]]), torch.eye(4)[None], 100, 100)
    T = head_pose_matrix(torch.tensor([0.0, math.pi, 0.0]), torch.tensor([0.0, 0.0, 1.0]))
    folded = fold_head_pose(cam, T)
    # head point (0.08, 0, 0.1) -> world (-0.08, 0, 0.9)
    assert_close(folded.world_to_camera(torch.tensor([[0.08, 0.0, 0.1]])), torch.tensor([[[-0.08, 0.0, 0.9]]]), atol=1e-6, rtol=0)
    # a tiny rotation is still a rotation (series branch of Rodrigues)
    Ts = head_pose_matrix(torch.tensor([1e-9, 0.0, 0.0]), torch.zeros(3))
    assert_close(Ts, torch.eye(4, dtype=torch.float64), atol=1e-8, rtol=0)
    with pytest.raises(ValueError, match="rigid"):
        fold_head_pose(cam, torch.diag(torch.tensor([2.0, 2.0, 2.0, 1.0])))


# ---------------------------------------------------------------- farthest viewpoint sampling
def test_farthest_viewpoint_sampling_hand_made_set():
    centers = torch.tensor(
        [
            [0.0, 0.0, 1.0],  # 0 front
            [0.1, 0.0, 0.995],  # 1 near-duplicate of front
            [1.0, 0.0, 0.0],  # 2 left
            [-0.7, 0.0, -0.7],  # 3 back-right
            [0.0, 1.0, 0.2],  # 4 top
        ]
    )
    # Radii differ on purpose: the sampling works on directions.
    centers = centers * torch.tensor([[1.0], [3.0], [0.5], [2.0], [1.0]])
    # From 0: distances 0.10 / 1.414 / 1.838 / 1.267 -> 3; then min-dist 1.414 (left) vs 1.267 (top) -> 2; then 4.
    assert farthest_viewpoint_sampling(centers, 4, start=0) == [0, 3, 2, 4]
    assert farthest_viewpoint_sampling(centers, 5, start=0)[-1] == 1
    g = torch.Generator().manual_seed(3)
    picks = farthest_viewpoint_sampling(centers, 3, generator=g)
    assert len(set(picks)) == 3
    with pytest.raises(ValueError, match=r"k must be in \[1, 5\] for 5 cameras, got 6"):
        farthest_viewpoint_sampling(centers, 6)
    with pytest.raises(ValueError, match="start must be a camera index"):
        farthest_viewpoint_sampling(centers, 2, start=9)


@pytest.mark.parametrize("yaw, pitch", [(0.0, 0.0), (40.0, 0.0), (-65.0, 0.0), (0.0, 25.0), (30.0, -20.0)])
def test_facing_head_places_the_camera_by_the_real_sets_convention(yaw, pitch):
    """+yaw: the nose turns towards the image's right edge, so the camera sits on the head's -x side
    (azimuth -yaw); +pitch: nose up, the camera below. The head's origin projects to the image centre."""
    cam = Cameras.facing_head(yaw, pitch, distance=0.8, fov_deg=25.0, size=200)
    centre = cam.c2w[0, :3, 3]
    assert_close(centre.norm(), torch.tensor(0.8), atol=1e-6, rtol=0)
    assert math.degrees(math.atan2(-centre[0].item(), centre[2].item())) == pytest.approx(yaw, abs=1e-4)
    assert math.degrees(math.asin(-centre[1].item() / 0.8)) == pytest.approx(pitch, abs=1e-4)
    uv, _ = cam.project(torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.1]]))  # the head's origin, and 10 cm along its face's axis (the nose)
    uv = uv.reshape(2, 2)
    assert_close(uv[0], torch.tensor([100.0, 100.0]), atol=1e-3, rtol=0)
    if yaw:
        assert (uv[1, 0].item() - 100.0) * yaw > 0  # the nose towards the right edge for +yaw
    if pitch:
        assert (100.0 - uv[1, 1].item()) * pitch > 0  # and up for +pitch
