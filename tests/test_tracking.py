"""Tracking: landmark fitter on synthetic truth, cameras/crops, matting, video smoothing, and the
dlib pipeline on a real photo (matplotlib's Grace Hopper portrait) with its failure cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fastgha_core.cameras import Cameras
from fastgha_core.constants import BACKGROUND_RGB
from fastgha_core.tracking.camera import cameras_to_pose, pose_to_cameras
from fastgha_core.tracking.crop import CropBox, crop_array, crop_cameras, head_crop_box
from fastgha_core.tracking.evaluate import evaluate, random_subject, rotation_error_deg
from fastgha_core.tracking.fit import FRONTAL_R, FitConfig, LandmarkModel, default_intrinsics, fit_landmarks
from fastgha_core.tracking.matting import GaussianMixture
from fastgha_core.tracking.video import OneEuroFilter
from extras import hide_modules

try:
    from fastgha_core.tracking.faces import load_face_detector

    DETECTOR = load_face_detector()
except ImportError:  # FacesUnavailableError
    DETECTOR = None
needs_faces = pytest.mark.skipif(DETECTOR is None, reason="needs the 'faces' extra (dlib-bin, face-recognition-models)")


def _grace_hopper() -> np.ndarray:
    import matplotlib.cbook as cbook
    from PIL import Image

    return np.asarray(Image.open(cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)).convert("RGB"))


def _astronaut() -> np.ndarray:
    import skimage.data

    return skimage.data.astronaut()  # [512, 512, 3] uint8: Eileen Collins' official NASA portrait


# ------------------------------------------------------------------ fitter on synthetic truth
def test_fitter_recovers_pose_and_expression_on_synthetic_landmarks():
    r = evaluate(renders=8, views=4, noise_px=1.5, seed=3)
    assert np.median(r["rot_deg"]) < 3.0 and r["rot_deg"].max() < 8.0, r["rot_deg"]
    assert np.median(r["lateral_mm"]) < 10.0, r["lateral_mm"]
    assert np.median(r["depth_pct"]) < 15.0, r["depth_pct"]  # scale/distance ambiguity: loose
    # the fitted expression explains the face better than the neutral guess
    assert r["expr_geom_mm"].mean() < 0.8 * r["expr_geom_neutral_mm"].mean(), (r["expr_geom_mm"], r["expr_geom_neutral_mm"])
    assert (r["rms_px"] < 4.0).all()


def test_fit_exact_without_noise_or_identity_mismatch():
    """Truth inside the fitted model (30 identity modes), no noise: pose and jawOpen are recovered."""
    rng = np.random.default_rng(0)
    model = LandmarkModel.from_head_model(num_identity=30)
    beta = np.zeros(30)
    beta[:30] = rng.normal(size=30) * 0.5
    E = np.zeros((1, 53))
    jaw = 26  # jawOpen
    E[0, jaw] = 0.6
    R = FRONTAL_R @ _rot_y(math.radians(25.0))
    t = np.array([0.02, -0.01, 0.8])
    K = default_intrinsics(512, 512, 25.0)
    P = model.points(beta, E[0]) @ R.T + t
    uv = P @ K.T
    obs = uv[:, :2] / uv[:, 2:]
    res = fit_landmarks(obs[None], K, FitConfig(num_identity=30, identity_weight=1e-4, expression_weight=1e-3, weak_expression_weight=1e-3), model)
    assert rotation_error_deg(res.rotations[0], R) < 0.5
    assert np.linalg.norm(res.translations[0] - t) < 0.01
    assert abs(res.expressions[0, jaw] - 0.6) < 0.1
    assert res.rms_px[0] < 0.5
    assert (res.expressions >= 0).all() and (res.expressions <= 1).all()


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def test_block_sparse_gram_equals_the_dense_product():
    """``fit._gram`` (the Levenberg-Marquardt normal matrix, multiplied chunk by chunk over the
    columns each chunk of rows touches) against ``J.T @ J``: view-like blocks that share the identity
    columns, a chunk straddling two views, a diagonal prior, rows touching every column (the dense
    branch) and an all-zero chunk."""
    from fastgha_core.tracking.fit import _gram

    rng = np.random.default_rng(4)
    nid, nv, V = 10, 12, 4
    n = nid + V * nv
    J = np.zeros((V * 300 + n + 40 + 256, n))
    for v in range(V):
        rows = slice(v * 300, (v + 1) * 300)
        J[rows, :nid] = rng.standard_normal((300, nid))
        J[rows, nid + v * nv : nid + (v + 1) * nv] = rng.standard_normal((300, nv))
    r0 = V * 300
    J[r0 : r0 + n] = np.diag(rng.random(n) + 0.5)
    J[r0 + n : r0 + n + 40] = rng.standard_normal((40, n))  # rows 1298.. stay zero: the last chunk is empty
    H = _gram(J, chunk=256)
    np.testing.assert_allclose(H, J.T @ J, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(_gram(J, chunk=7), J.T @ J, rtol=1e-12, atol=1e-9)


def test_fit_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"\[V, 468, 2\] \(layout mediapipe\), got \[2, 60, 2\]"):
        fit_landmarks(np.zeros((2, 60, 2)), np.eye(3))
    with pytest.raises(ValueError, match=r"\[V, 68, 2\] \(layout dlib68\)"):
        fit_landmarks(np.zeros((2, 60, 2)), np.eye(3), model=LandmarkModel.from_head_model(num_identity=5))
    with pytest.raises(ValueError, match="K must"):
        fit_landmarks(np.zeros((2, 68, 2)), np.zeros((3, 3, 3)))


# ------------------------------------------------------------------ camera + crop
def test_pose_camera_projects_like_the_fit():
    rng = np.random.default_rng(1)
    beta, E, R, t, K = random_subject(rng, 2)
    model = LandmarkModel.from_head_model(num_identity=100)
    cams = pose_to_cameras(R, t, K, 512, 512)
    for v in range(2):
        X = model.points(beta, E[v])
        uv_ref = X @ R[v].T + t[v]
        uv_ref = (uv_ref @ K.T)[:, :2] / (uv_ref @ K.T)[:, 2:]
        uv, z = cams[v].project(torch.tensor(X, dtype=torch.float32))
        torch.testing.assert_close(uv.double(), torch.tensor(uv_ref), atol=1e-2, rtol=0)
        assert (z > 0).all()
    R2, t2 = cameras_to_pose(cams)
    np.testing.assert_allclose(R2, R, atol=1e-5)
    np.testing.assert_allclose(t2, t, atol=1e-5)


def test_crop_keeps_projection_and_pads_with_background():
    K = default_intrinsics(200, 100, 30.0)
    cam = Cameras(torch.tensor(K, dtype=torch.float32)[None], torch.eye(4)[None], 200, 100)
    box = head_crop_box(K, np.array([0.0, 0.0, 1.0]), extent_m=0.4)  # f = 373 px: side 149
    assert box.left + box.side / 2 == pytest.approx(100, abs=1) and box.top + box.side / 2 == pytest.approx(50, abs=1)
    assert box.side > 100  # taller than the photo: padding at top and bottom
    img = np.zeros((100, 200, 3), np.uint8)
    img[50, 100] = 200  # one bright pixel at the centre
    out = crop_array(img, box, 64, np.array([255, 255, 255], np.uint8))
    assert out.shape == (64, 64, 3)
    assert (out[0, 32] == np.round(np.array(BACKGROUND_RGB) * 255)).all()  # padding
    c2 = crop_cameras(cam, box, 64)
    X = torch.tensor([[0.01, 0.02, 1.0]])
    uv1, _ = cam.project(X)
    uv2, _ = c2.project(X)
    s = 64 / box.side
    torch.testing.assert_close(uv2, (uv1 - torch.tensor([box.left, box.top])) * s, atol=1e-3, rtol=0)


def test_crop_array_no_overlap_is_all_fill():
    img = np.full((10, 10, 1), 7.0, np.float32)
    out = crop_array(img, CropBox(50, 50, 20), 20, [0.0])
    assert (out == 0).all()


# ------------------------------------------------------------------ matting + smoothing
def test_gaussian_mixture_separates_colours():
    rng = np.random.default_rng(0)
    a = rng.normal([0.8, 0.6, 0.5], 0.03, size=(500, 3))
    b = rng.normal([0.1, 0.2, 0.7], 0.03, size=(500, 3))
    ga, gb = GaussianMixture(2).fit(a), GaussianMixture(2).fit(b)
    assert (ga.score(a) > gb.score(a)).mean() > 0.99
    assert (gb.score(b) > ga.score(b)).mean() > 0.99


def test_one_euro_filter_smooths_noise_and_follows_steps():
    rng = np.random.default_rng(0)
    f = OneEuroFilter(min_cutoff=1.0, beta=0.0)
    ts = np.arange(120) / 30.0
    noisy = 0.5 + rng.normal(0, 0.05, size=(120, 3))
    out = np.stack([f(x, t) for x, t in zip(noisy, ts)])
    assert out[30:].std(0).max() < 0.5 * noisy[30:].std(0).min()
    g = OneEuroFilter(min_cutoff=1.0, beta=0.5)
    step = [g(np.array([0.0 if t < 1 else 1.0]), t) for t in ts]
    assert step[-1][0] == pytest.approx(1.0, abs=0.02)


# ------------------------------------------------------------------ dlib pipeline on a real photo
@needs_faces
@pytest.mark.parametrize("photo", [_astronaut, _grace_hopper], ids=["astronaut", "grace_hopper"])
def test_portrait_is_near_frontal_and_masked(photo):
    from fastgha_core.tracking import track_request

    img = photo()
    crops, cams, masks, expr = track_request([img], size=128)
    assert crops.shape == (1, 3, 128, 128) and masks.shape == (1, 1, 128, 128) and expr.shape == (1, 53)
    assert cams.width == 128 and len(cams) == 1
    R = cams.R[0].double().numpy()
    # official portraits face the camera: yaw and roll within 10 degrees. Pitch within 20: the
    # MediaPipe correspondence (meshmap.py) puts frontal heads 5-7 degrees lower than dlib's 68 points
    # (astronaut: dlib -7.0, MediaPipe -14.7 degrees)
    from fastgha_core.tracking.realsets import head_angles_deg

    yaw, pitch, roll = head_angles_deg(R)
    assert abs(yaw) < 10.0 and abs(pitch) < 20.0 and abs(roll) < 10.0, (yaw, pitch, roll)
    z = float(cams.t[0, 2])
    assert 0.3 < z < 3.0  # plausible distance for a head filling a portrait with the 30-degree assumption
    m = masks[0, 0]
    assert m[64, 64] > 0.9 and m[40:90, 40:90].mean() > 0.9  # the face
    assert m[:10, :10].mean() < 0.2 and m[:10, -10:].mean() < 0.2  # flag and background at the top corners
    assert (expr >= 0).all() and (expr <= 1).all() and expr.mean() < 0.2


@needs_faces
def test_failure_cases_name_the_file(tmp_path):
    from PIL import Image

    from fastgha_core.tracking import TrackConfig, track_photos
    from fastgha_core.tracking.faces import NoFaceError, SeveralFacesError, TinyFaceError

    img = _grace_hopper()
    with pytest.raises(NoFaceError, match="blank.png"):
        track_photos([np.full((300, 300, 3), 128, np.uint8)], names=["blank.png"], detector=DETECTOR)
    with pytest.raises(SeveralFacesError, match="2 faces in twice.png"):
        track_photos([np.concatenate([img, img], axis=1)], names=["twice.png"], detector=DETECTOR)
    small = np.asarray(Image.fromarray(img).resize((img.shape[1] * 2 // 5, img.shape[0] * 2 // 5), Image.BILINEAR))
    with pytest.raises(TinyFaceError, match="small.png"):
        track_photos([small], TrackConfig(size=64), names=["small.png"], detector=DETECTOR)


def test_cli_rejects_non_image(tmp_path, capsys):
    from fastgha_core.cli import main

    bad = tmp_path / "notes.jpg"
    bad.write_text("this is not a picture")
    rc = main(["track", "--images", str(bad), "--out", str(tmp_path / "req")])
    assert rc == 2
    assert "notes.jpg is not an image" in capsys.readouterr().err


@needs_faces
def test_cli_writes_a_request_folder(tmp_path, capsys):
    import json

    from PIL import Image

    from fastgha_core.cameras import load_request_folder
    from fastgha_core.cli import main

    p = tmp_path / "gh.jpg"
    Image.fromarray(_grace_hopper()).save(p)
    rc = main(["track", "--images", str(p), "--out", str(tmp_path / "req"), "--size", "96", "--json", str(tmp_path / "reports" / "r.json")])
    assert rc == 0
    assert f"wrote the tracking report to {tmp_path / 'reports' / 'r.json'}" in capsys.readouterr().out  # the user is told where
    images, cams = load_request_folder(tmp_path / "req")
    assert len(images) == 1 and cams[0].width == 96
    assert Image.open(images[0]).size == (96, 96)
    assert (tmp_path / "req" / (images[0].stem + "_mask.png")).is_file()
    ex = json.loads((tmp_path / "req" / "expressions.json").read_text())
    assert ex["space"] == "ict53" and len(ex["expressions"][0]) == 53
    assert json.loads((tmp_path / "reports" / "r.json").read_text())["photos"][0]["mask"] == "estimated"  # its folder made


@needs_faces
def test_cli_tracking_again_into_a_folder_replaces_the_earlier_crops(tmp_path):
    """A second run into the same --out (fewer or other photos) used to leave the first run's crops,
    and reconstruct then found more photos than cameras."""
    from PIL import Image

    from fastgha_core.cameras import load_request_folder
    from fastgha_core.cli import main

    a, b = tmp_path / "first.jpg", tmp_path / "second.jpg"
    Image.fromarray(_grace_hopper()).save(a)
    Image.fromarray(_grace_hopper()[:, ::-1].copy()).save(b)
    req = tmp_path / "req"
    assert main(["track", "--images", str(a), str(b), "--out", str(req), "--size", "64"]) == 0
    assert len(load_request_folder(req)[0]) == 2
    assert main(["track", "--images", str(b), "--out", str(req), "--size", "64"]) == 0
    images, cams = load_request_folder(req)
    assert [p.name for p in images] == ["00_second.png"] and len(cams) == 1
    assert sorted(p.name for p in req.glob("*.png")) == ["00_second.png", "00_second_mask.png"]


def test_cli_refuses_an_out_folder_holding_other_photos(tmp_path, capsys):
    """Photos in --out that track did not write (the inputs themselves, say) would be taken as views
    by reconstruct: refused before tracking, and nothing in the folder is touched."""
    from PIL import Image

    from fastgha_core.cli import main

    me = tmp_path / "me.jpg"
    Image.new("RGB", (64, 64)).save(me)
    assert main(["track", "--images", str(me), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "already holds photos (me.jpg; the photos to track are in it)" in err and "empty or new folder" in err, err
    assert me.is_file() and not (tmp_path / "cameras.json").exists()
    assert main(["track", "--images", str(tmp_path), "--out", str(tmp_path / "req")]) == 2  # a folder, not photos
    assert f"--images {tmp_path} is a folder; give the photo files" in capsys.readouterr().err


def test_missing_faces_extra_names_the_extra(monkeypatch):
    from fastgha_core.tracking import faces

    hide_modules(monkeypatch, "dlib", "mediapipe")
    with pytest.raises(faces.FacesUnavailableError, match=r"pip install -e '\.\[faces\]'"):
        faces.load_face_detector()


# ------------------------------------------------------------------ video
@needs_faces
def test_video_tracker_follows_a_moving_face():
    from fastgha_core.tracking.video import VideoTracker, bench_frames

    frames = bench_frames(12)
    tr = VideoTracker(detector=DETECTOR)
    out = [tr.track(f) for f in frames]
    assert all(o is not None for o in out)
    assert out[0].detected and not out[1].detected  # later frames reuse the landmark box
    for o in out:
        assert rotation_error_deg(o.R, FRONTAL_R) < 15.0
        assert (o.expression >= 0).all() and (o.expression <= 1).all()
        assert o.rms_px < 6.0
    # the face moves right in the first frames (bench_frames: x offset 60 sin(2 pi i / 90))
    assert out[-1].t[0] > out[0].t[0]
    cams = out[-1].cameras(640, 480)
    assert cams.width == 640


def test_dlib_fallback_still_tracks_a_frontal_portrait():
    from fastgha_core.tracking import TrackConfig, track_photos
    from fastgha_core.tracking.faces import FacesUnavailableError, load_face_detector
    from fastgha_core.tracking.realsets import head_angles_deg

    try:
        det = load_face_detector(backend="dlib")
    except FacesUnavailableError:
        pytest.skip("needs dlib-bin and face-recognition-models (the 'faces' extra)")
    res = track_photos([_grace_hopper()], TrackConfig(size=64), detector=det, names=["hopper.jpg"])
    assert res.layout == "dlib68" and res.landmarks[0].shape == (68, 2)
    yaw, pitch, roll = head_angles_deg(res.fit.rotations[0])
    assert abs(yaw) < 10 and abs(pitch) < 15 and abs(roll) < 10, (yaw, pitch, roll)
    with pytest.raises(ValueError, match="backend must be"):
        load_face_detector(backend="opencv")
