"""Test-view pose alignment (``fastgha_core.refine.testpose``): with the avatar frozen, the camera of a
render is recovered from a perturbed start; the correction is rigid about the pivot and bounded; the
leave-one-out report's alignment columns (``refine/realsets.py --align-left-out``)."""

from __future__ import annotations

import math

import pytest
import torch

from fastgha_core import Cameras
from fastgha_core.constants import BACKGROUND_RGB
from fastgha_core.gaussians import Gaussians
from fastgha_core.refine.testpose import AlignConfig, align_camera, apply_correction, head_angles, pivot_of
from fastgha_core.render import render

FAST = AlignConfig(levels=((64, 2.0, 25), (128, 1.0, 20), (128, 0.0, 15)))


def _head(n: int = 3000, seed: int = 0) -> Gaussians:
    """A textured ellipsoid 'head' (metres; +y up, +z the front, as the tracker's head frame)."""
    g = torch.Generator().manual_seed(seed)
    i = torch.arange(n, dtype=torch.float32) + 0.5
    phi = torch.acos(1 - 2 * i / n)
    theta = math.pi * (1 + 5**0.5) * i
    d = torch.stack([torch.sin(phi) * torch.cos(theta), torch.cos(phi), torch.sin(phi) * torch.sin(theta)], -1)
    means = d * torch.tensor([0.08, 0.11, 0.095])
    dirs = torch.randn(6, 3, generator=g)
    freq = torch.tensor([40.0, 55.0, 70.0, 45.0, 60.0, 80.0])[:, None]
    waves = torch.sin((means @ (dirs * freq).T) + torch.rand(6, generator=g) * 6.28)  # [N, 6]
    colors = (0.5 + 0.25 * waves[:, :3] + 0.15 * waves[:, 3:]).clamp(0.02, 0.98)
    return Gaussians(
        means=means, quats=torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4).clone(), scales=torch.full((n, 3), 0.006),
        opacities=torch.full((n,), 0.9), colors=colors,
    )


def _camera(yaw_deg: float, pitch_deg: float = 0.0, side: int = 128) -> Cameras:
    y, p = math.radians(yaw_deg), math.radians(pitch_deg)
    eye = [0.6 * math.cos(p) * math.sin(y), 0.6 * math.sin(p), 0.6 * math.cos(p) * math.cos(y)]
    c = Cameras.look_at(eye, fov_deg=30.0, width=side, height=side)
    return Cameras(c.K[None], c.w2c[None], side, side)


def _errors(a: Cameras, b: Cameras) -> tuple[float, float]:
    """(rotation angle in degrees, camera-centre distance in mm) between two cameras."""
    dr = a.w2c[0, :3, :3] @ b.w2c[0, :3, :3].T
    ang = math.degrees(math.acos(max(-1.0, min(1.0, (float(torch.trace(dr)) - 1) / 2))))
    return ang, 1000 * float((a.centers - b.centers).norm())


def _target(g: Gaussians, cam: Cameras):
    ro = render(g, cam, background=BACKGROUND_RGB)
    return ro.rgb[0].clamp(0, 1), ro.alpha[0]


def test_head_angles_follow_the_tracker_convention():
    yaw, pitch, roll = head_angles(_camera(0.0))
    assert abs(yaw) < 1e-4 and abs(pitch) < 1e-4 and abs(roll) < 1e-4
    # a camera on the head's left (+x) sees the nose turned towards the image's left edge: - yaw
    assert head_angles(_camera(30.0))[0] == pytest.approx(-30.0, abs=1e-3)
    assert head_angles(_camera(0.0, pitch_deg=20.0))[1] == pytest.approx(-20.0, abs=1e-3)  # seen from above: nose down


def test_correction_is_rigid_about_the_pivot():
    cam = _camera(20.0)
    pivot = torch.tensor([0.01, 0.02, -0.01])
    out = apply_correction(cam, torch.tensor([0.1, -0.2, 0.05]), torch.zeros(3), pivot)
    # the pivot keeps its camera coordinates, any other point moves
    p0, p1 = cam.world_to_camera(pivot[None])[0, 0], out.world_to_camera(pivot[None])[0, 0]
    assert torch.allclose(p0, p1, atol=1e-6)
    q = torch.tensor([[0.08, 0.0, 0.0]])
    assert float((cam.world_to_camera(q) - out.world_to_camera(q)).norm()) > 0.01
    R = out.w2c[0, :3, :3]
    assert torch.allclose(R @ R.T, torch.eye(3), atol=1e-5)
    # a translation alone moves every point by it in the camera frame
    tr = apply_correction(cam, torch.zeros(3), torch.tensor([0.01, -0.02, 0.005]), pivot)
    assert torch.allclose(tr.world_to_camera(q) - cam.world_to_camera(q), torch.tensor([[0.01, -0.02, 0.005]]), atol=1e-6)
    # a rotation about the head's up axis changes the yaw by its angle
    up_cam = cam.w2c[0, :3, 1]
    yawed = apply_correction(cam, math.radians(7.0) * up_cam, torch.zeros(3), torch.zeros(3))
    assert abs(head_angles(yawed)[0] - head_angles(cam)[0]) == pytest.approx(7.0, abs=1e-3)


@pytest.mark.parametrize(
    "yaw, rot_deg, trans_mm",
    [
        (0.0, (2.0, 6.0, -1.5), (4.0, -3.0, 8.0)),
        (40.0, (-3.0, -8.0, 2.0), (-5.0, 2.0, -6.0)),
        (-70.0, (0.0, 18.0, 0.0), (0.0, 0.0, 0.0)),  # an 18-degree yaw error: the sweep's start
    ],
)
def test_alignment_recovers_a_perturbed_camera(yaw, rot_deg, trans_mm):
    g = _head()
    true = _camera(yaw)
    target, mask = _target(g, true)
    pivot = pivot_of(g)
    start = apply_correction(true, torch.tensor([math.radians(a) for a in rot_deg]), torch.tensor(trans_mm) / 1000, pivot)
    ang0, _ = _errors(start, true)
    assert ang0 > 0.9 * math.sqrt(sum(a * a for a in rot_deg))  # the start is wrong
    res = align_camera(g, start, target, mask, FAST)
    ang, cen = _errors(res.camera, true)
    assert ang < 1.0, (ang, cen)
    assert cen < 10.0, (ang, cen)  # the camera sits 0.6 m away: 1 degree about the head moves it ~10 mm
    assert head_angles(res.camera)[0] == pytest.approx(head_angles(true)[0], abs=1.0)
    assert res.loss_end < 0.3 * res.loss_start
    assert res.camera.w2c.shape == start.w2c.shape and torch.equal(res.camera.K, start.K.float())


def test_alignment_leaves_an_exact_camera_alone():
    g = _head()
    true = _camera(25.0, pitch_deg=10.0)
    target, mask = _target(g, true)
    res = align_camera(g, true, target, mask, FAST)
    ang, cen = _errors(res.camera, true)
    assert ang < 0.6 and cen < 6.0  # below a pixel of motion of the head at 128²
    assert res.start_yaw_deg == 0.0


def test_correction_stays_within_its_bounds():
    g = _head()
    true = _camera(0.0)
    target, mask = _target(g, true)
    start = apply_correction(true, torch.tensor([0.0, math.radians(40.0), 0.0]), torch.tensor([0.05, 0.0, 0.0]), pivot_of(g))
    cfg = AlignConfig(levels=((64, 2.0, 15),), max_rotation_deg=12.0, max_translation_m=0.01, yaw_sweep_deg=(-10.0, 0.0, 10.0))
    res = align_camera(g, start, target, mask, cfg)
    assert res.rotation_deg <= 12.0 + 1e-3 and res.translation_mm <= 10.0 + 1e-3
    assert res.rotation_deg > 6.0  # it did move towards the truth, up to the bound
    with pytest.raises(ValueError, match="yaw_sweep_deg"):
        AlignConfig(max_rotation_deg=10.0, yaw_sweep_deg=(-20.0, 0.0))
    with pytest.raises(ValueError, match="multiples of 16"):
        AlignConfig(levels=((60, 1.0, 5),))
    with pytest.raises(ValueError, match="target must be"):
        align_camera(g, true, target[:, :64], mask, cfg)


@pytest.fixture(scope="module")
def sample():
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.refine.measure import SAMPLE_REQUEST, read_request

    model = load_model("tiny")
    images, masks, cams, expr = read_request(SAMPLE_REQUEST)
    imgs, in_cams = model.prepare(list(images), [cams[i : i + 1] for i in range(len(cams.K))], list(masks))
    avatar = model.reconstruct(imgs, in_cams, expressions=expr)
    return model, avatar, in_cams, expr


def test_report_columns_recover_the_camera_of_an_avatar_render(sample):
    """The leave-one-out report's alignment (``aligned_columns``): a render of the sample's avatar at
    one of its cameras is the 'photo', the start is that camera turned by 10 degrees about the head
    and shifted by 5 mm; the aligned camera scores far higher and reads the true yaw again."""
    from fastgha_core.refine.realsets import aligned_columns

    model, avatar, in_cams, expr = sample
    c = in_cams[0:1].resize(128, 128)
    true = Cameras(c.K.reshape(1, 3, 3).clone(), c.w2c.reshape(1, 4, 4).clone(), 128, 128)
    ro = render(model.animate(avatar, expr[0], camera=true), true, background=BACKGROUND_RGB)
    target, m = ro.rgb.clamp(0, 1), (ro.alpha > 0.5).float()
    pivot = pivot_of(model.animate(avatar, expr[0], camera=true))
    up = true.w2c[0, :3, 1]
    start = apply_correction(true, math.radians(10.0) * up, torch.tensor([0.005, 0.0, 0.0]), pivot)
    yaw_true = head_angles(true)[0]
    ann = round(yaw_true) - 2  # the file name's yaw: 12 degrees from the start, near the truth
    cols, pred = aligned_columns(model, avatar, expr[0], start, target, m, None, None, None, f"00_yaw{ann:+d}.jpg", FAST)
    assert abs(cols["yaw_tracked"] - yaw_true) == pytest.approx(10.0, abs=0.5)
    assert cols["yaw_aligned"] == pytest.approx(yaw_true, abs=1.0)
    assert cols["align_rotation_deg"] == pytest.approx(10.0, abs=1.0)
    assert cols["align_dyaw_deg"] == pytest.approx(yaw_true - cols["yaw_tracked"], abs=1.0)
    assert cols["yaw_annotated"] == ann
    # the second alignment starts at the annotated yaw (turned the right way) and ends at the truth too
    assert cols["annot_start_yaw"] == pytest.approx(ann, abs=0.5)
    assert cols["annot_start_yaw_aligned"] == pytest.approx(yaw_true, abs=1.0)
    assert cols["annot_start_masked_psnr"] > cols["annot_start_masked_psnr_start"] + 3.0
    assert cols["aligned_masked_psnr"] > 30.0
    assert cols["aligned_identity_distance"] is None and cols["aligned_faces_in_render"] is None  # no face detector given
    assert pred.shape == (3, 128, 128)
    ro0 = render(model.animate(avatar, expr[0], camera=start), start, background=BACKGROUND_RGB)
    mse0 = float(((ro0.rgb.clamp(0, 1) - target) ** 2 * m).sum() / (3 * m.sum()))
    assert cols["aligned_masked_psnr"] > -10 * math.log10(mse0) + 8.0


def test_alignment_tables_put_both_cameras_side_by_side():
    from fastgha_core.refine.realsets import align_photo_table, align_summary_table

    base = {"set": "a", "steps": 0, "masked_ssim": 0.8, "aligned_masked_ssim": 0.85, "faces_in_render": 1, "aligned_faces_in_render": 1,
            "cnn_faces_in_render": 1, "aligned_cnn_faces_in_render": 1, "pitch_tracked": 1.0, "pitch_aligned": 2.0, "align_droll_deg": 0.5,
            "align_translation_mm": 4.0}
    rows = [
        dict(base, left_out="00_yaw+55.jpg", masked_psnr=15.0, aligned_masked_psnr=17.0, identity_distance=0.6, aligned_identity_distance=0.5,
             yaw_annotated=55.0, yaw_tracked=36.7, yaw_aligned=41.2, align_rotation_deg=4.6, align_loss_end=0.02,
             annot_start_yaw_aligned=52.0, annot_start_masked_psnr_start=14.0, annot_start_masked_psnr=16.5, annot_start_loss_end=0.03),
        dict(base, left_out="01.jpg", masked_psnr=19.0, aligned_masked_psnr=20.0, identity_distance=None, aligned_identity_distance=0.4,
             yaw_annotated=None, yaw_tracked=1.0, yaw_aligned=0.0, align_rotation_deg=1.0),
        {"set": "a", "steps": 0, "left_out": "x", "masked_psnr": 1.0},  # a row without the alignment is left out
    ]
    cells = [c.strip() for c in align_summary_table(rows).strip().splitlines()[2].strip("|").split("|")]
    assert cells[2] == "2" and cells[3] == "17.00 -> 18.50" and cells[5] == "0.600 -> 0.450"
    assert cells[8] == "2.8; 4.0"
    lines = align_photo_table(rows).strip().splitlines()
    assert len(lines) == 4
    c0 = [c.strip() for c in lines[2].strip("|").split("|")]
    assert c0[3:6] == ["+55", "36.7", "41.2"] and c0[9] == "15.00 -> 17.00"
    assert c0[11] == "52.0 (14.00 -> 16.50; no)"  # from the annotation it ends at a higher loss than from the tracked yaw
    assert [c.strip() for c in lines[3].strip("|").split("|")][3] == "n/a"
    assert align_summary_table(rows[2:]) == "" and align_photo_table([]) == ""


def test_alignment_never_ends_worse_than_the_given_camera():
    """Steps far too large throw the camera off; the given camera is then returned unchanged."""
    g = _head()
    true = _camera(10.0)
    target, mask = _target(g, true)
    cfg = AlignConfig(levels=((64, 0.0, 4),), lr_rotation=0.4, lr_translation=0.03, yaw_sweep_deg=())
    res = align_camera(g, true, target, mask, cfg)
    assert res.losses[-1] > res.loss_start  # the optimiser did end worse
    assert res.loss_end == res.loss_start and res.rotation_deg == 0.0 and res.translation_mm == 0.0
    assert torch.equal(res.camera.w2c, true.w2c)
