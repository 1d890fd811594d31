"""Reconstruction on the tracked head surface (``fastgha_core/model/surface.py``, issue 17)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastgha_core.data.headmodel import HeadModel
from fastgha_core.model.surface import HeadSurface, surface_ray_depth
from fastgha_core.tracking.camera import pose_to_cameras
from fastgha_core.tracking.fit import FRONTAL_R, default_intrinsics, rodrigues
from extras import needs_faces


def _cameras(yaws_deg, size=128, dist=0.6, drop_m=0.01):
    """Head-centric cameras looking at the head from ``yaws_deg`` (OpenCV, world = head frame), the
    head ``dist`` metres in front and ``drop_m`` below each camera's optical axis (camera y down)."""
    R = np.stack([FRONTAL_R @ rodrigues(np.array([0.0, np.radians(y), 0.0])) for y in yaws_deg])
    t = np.tile([0.0, drop_m, dist], (len(yaws_deg), 1))
    return pose_to_cameras(R, t, default_intrinsics(size, size, 30.0), size, size)


@pytest.fixture(scope="module")
def surface():
    rng = np.random.default_rng(5)
    ident = np.zeros(100, np.float32)
    ident[:20] = rng.standard_normal(20) * 0.7
    expr = np.zeros((3, 53), np.float32)
    expr[1, HeadModel.load().expression_names.index("jawOpen")] = 0.6
    return HeadSurface(ident, expr)


def _points(cams, t):
    origins, dirs = cams.pixel_rays()
    return origins + t[..., None] * dirs  # [V, H, W, 3]


def test_hit_pixels_lie_on_the_tracked_mesh_and_the_rest_continue_it(surface):
    from scipy.spatial import cKDTree

    cams = _cameras([0.0, 35.0, -70.0])
    t = surface_ray_depth(surface, cams).t
    assert t.shape == (3, 128, 128) and torch.isfinite(t).all()
    pts = _points(cams, t)
    head = HeadModel.load()
    for v in range(3):
        tree = cKDTree(surface.vertices(v, head))
        d, _ = tree.query(pts[v].reshape(-1, 3).numpy())
        d = d.reshape(128, 128)
        centre = d[48:80, 48:80]  # the face fills the middle of the view
        assert np.median(centre) < 0.002 and np.percentile(centre, 95) < 0.006, (v, np.median(centre))
        # pixels off the head take the distance of the nearest head pixel: bounded by the head's range
        corner = float(t[v, 0, 0])
        assert float(t[v, 40:88, 40:88].min()) - 0.15 < corner < float(t[v].max()) + 1e-6


def test_a_surface_point_seen_by_two_views_lands_in_one_place(surface):
    """The point of the feature: views of one head agree on where a feature is, at any pose."""
    head = HeadModel.load()
    cams = _cameras([0.0, 35.0], size=256)
    two = surface.subset([0, 0])  # same expression in both views
    t = surface_ray_depth(two, cams).t
    pts = _points(cams, t)
    verts = two.vertices(0, head)
    lm = head.landmarks68[[30, 33, 36, 39, 42, 45, 48, 54]]  # nose, eye corners, mouth corners (seen from both)
    P = torch.from_numpy(verts[lm]).double()
    c = cams.flatten()
    got, seen = [], torch.ones(len(lm), dtype=torch.bool)
    for v in range(2):
        x = P @ c.R[v].double().T + c.t[v].double()
        uv = (x @ c.K[v].double().T)[:, :2] / x[:, 2:3]
        col, row = uv[:, 0].long().clamp(0, 255), uv[:, 1].long().clamp(0, 255)
        got.append(pts[v, row, col].double())
        seen &= (x.norm(dim=-1) - t[v, row, col].double()).abs() < 0.003  # not hidden in this view
    assert int(seen.sum()) >= 5, seen
    err_surface = (got[0] - got[1]).norm(dim=-1)[seen]
    assert float(err_surface.max()) < 0.004, err_surface
    # the network's zero-depth guess (the sphere through the head centre) puts them centimetres apart
    sphere = [_points(c[v : v + 1], torch.full((1, 256, 256), float(c.centers[v].norm())))[0] for v in range(2)]
    rows_cols = []
    for v in range(2):
        x = P @ c.R[v].double().T + c.t[v].double()
        uv = (x @ c.K[v].double().T)[:, :2] / x[:, 2:3]
        rows_cols.append((uv[:, 1].long(), uv[:, 0].long()))
    err_sphere = (sphere[0][rows_cols[0]] - sphere[1][rows_cols[1]]).norm(dim=-1)[seen]
    assert float(err_sphere.median()) > 5 * float(err_surface.median())


def test_only_the_air_in_front_of_the_face_is_dropped(surface):
    """In a profile, pixels in front of the nose and chin are air (``beyond_face``); above and
    behind the head (hair) and below it (neck, shoulders) they are kept."""
    head = HeadModel.load()
    cams = _cameras([0.0, 90.0])
    sd = surface_ray_depth(surface.subset([0, 0]), cams)
    c = cams.flatten()
    tip = torch.from_numpy(surface.vertices(0, head)[head.landmarks68[30]]).double()  # nose tip
    x = c.R[1].double() @ tip + c.t[1].double()
    u, v = ((c.K[1].double() @ x)[:2] / x[2]).tolist()
    row = sd.beyond_face[1, int(v)]
    step = 1 if u > 64 else -1  # the side the face points to in the image
    ahead = row[int(u) + 3 * step :: step] if step > 0 else row[: int(u) - 2].flip(0)
    assert bool(ahead[:10].all())  # in front of the nose: air
    hit = sd.hit[1]
    rows = torch.nonzero(hit.any(1)).flatten()
    top = int(rows.min())
    assert not bool(sd.beyond_face[1, : max(top - 2, 1)].any())  # above the head: hair may be there
    chin = torch.from_numpy(surface.vertices(0, head)[head.landmarks68[8]]).double()
    xc = c.R[1].double() @ chin + c.t[1].double()
    chin_row = int((c.K[1].double() @ xc)[1] / xc[2])
    assert not bool(sd.beyond_face[1, chin_row + 2 :].any())  # below the chin: neck, chest
    assert not bool(sd.beyond_face[0].any())  # frontal: beside the head (ears, hair) is kept
    assert not bool(sd.beyond_face[1][hit].any())  # never on the head itself


def test_the_open_jaw_view_follows_its_own_expression(surface):
    cams = _cameras([0.0, 0.0])
    t = surface_ray_depth(surface.subset([0, 1]), cams).t  # neutral, jaw open 0.6
    head = HeadModel.load()
    chin = surface.vertices(1, head)[head.landmarks68[8]]
    x = chin @ cams.R[1].numpy().T + cams.t[1].numpy()
    u, v = (cams.K[1].numpy() @ x)[:2] / x[2]
    assert float((t[0] - t[1]).abs().max()) > 0.005  # the two views do not share one depth map
    assert int(v) < 128 and np.isfinite(float(t[1, int(v), int(u)]))


def test_head_surface_checks_its_input_and_subsets():
    with pytest.raises(ValueError, match="53"):
        HeadSurface(np.zeros(100), np.zeros((2, 52)))
    with pytest.raises(ValueError, match="at most 100"):
        HeadSurface(np.zeros(101), np.zeros((2, 53)))
    with pytest.raises(ValueError, match="finite"):
        HeadSurface(np.full(100, np.nan), np.zeros((2, 53)))
    s = HeadSurface(np.zeros(100), np.arange(3 * 53, dtype=np.float32).reshape(3, 53) / 200)
    assert len(s.subset([2, 0])) == 2 and s.subset([2, 0]).expressions[0, 0] == s.expressions[2, 0]
    with pytest.raises(ValueError, match="2 surface views but 3 cameras"):
        surface_ray_depth(s.subset([0, 1]), _cameras([0, 10, 20]))


def test_gaussian_head_puts_centres_at_the_given_ray_depth():
    from fastgha_core.config import get_preset
    from fastgha_core.model.gaussian_head import GaussianHead

    cfg = get_preset("tiny").gaussians
    head = GaussianHead(cfg)
    cams = _cameras([0.0, 20.0], size=16)
    maps = torch.randn(1, 2, head.layout.channels, 16, 16)
    images = torch.rand(1, 2, 3, 16, 16)
    depth = 0.5 + 0.1 * torch.rand(1, 2, 16, 16)
    g = head(maps, cams[None], images, ray_depth=depth)[0]
    g0 = head(maps, cams[None], images)[0]
    origins, dirs = cams.pixel_rays(16, 16)
    want = (origins + depth[0][..., None] * dirs).reshape(-1, 3)
    assert torch.allclose(g.means, want, atol=1e-5)
    t0 = ((g0.means - origins.reshape(-1, 3)) * dirs.reshape(-1, 3)).sum(-1)
    ratio = (g.scales / g0.scales)[:, 0]
    assert torch.allclose(ratio, depth.reshape(-1) / t0, rtol=1e-4)  # footprint scales with the distance
    assert torch.equal(g.colors, g0.colors) and torch.equal(g.opacities, g0.opacities)
    with pytest.raises(ValueError, match="ray_depth must have shape"):
        head(maps, cams[None], images, ray_depth=depth[:, :1])


def test_reconstruct_on_a_surface_binds_the_prior_to_it(surface):
    from fastgha_core.model.fastgha import load_model

    model = load_model("tiny")
    s = model.config.input_size
    cams = _cameras([0.0, 35.0, -35.0], size=s)
    from fastgha_core.constants import BACKGROUND_RGB

    imgs = torch.tensor(BACKGROUND_RGB, dtype=torch.float32).view(1, 3, 1, 1).repeat(3, 1, s, s)
    imgs[:, :, s // 4 : 3 * s // 4, 3 * s // 8 : 5 * s // 8] = torch.rand(3, 3, s // 2, s // 4)  # the face: the rest is matted away
    av = model.reconstruct(imgs, cams, surface=surface)
    k = av.prior.identity.shape[0]
    assert np.allclose(av.prior.identity.numpy(), surface.identity[:k])
    assert torch.allclose(av.prior.transform, torch.eye(4))
    # every reconstructed Gaussian sits on (or continues) the tracked head: at most a few cm from it
    from scipy.spatial import cKDTree

    neutral = HeadSurface(surface.identity, np.zeros((1, 53))).vertices(0)
    d, _ = cKDTree(neutral).query(av.gaussians.means[: av.num_reconstructed].numpy())
    assert np.median(d) < 0.004, np.median(d)
    with pytest.raises(ValueError, match="surface has 2 views but 3 images"):
        model.reconstruct(imgs, cams, surface=surface.subset([0, 1]))
    with pytest.raises(ValueError, match="surface_mode"):
        model.reconstruct(imgs, cams, surface=surface, surface_mode="mesh")
    # blend: the face's Gaussians on the head, as with replace; the rest is the network's depth.
    # The matte fill (model/coverage.py) raises opacities by where the views' Gaussians land, which
    # depends on depth: compare the kept pixels without it. Replace mode alone adds the mirrored views
    # of the +-35-degree views (model/mirror.py; blend mode has none): compare the real views' pixels.
    model.config.gaussians.coverage_target, model.config.gaussians.mirror_views = 0.0, False
    av = model.reconstruct(imgs, cams, surface=surface)
    d, _ = cKDTree(neutral).query(av.gaussians.means[: av.num_reconstructed].numpy())
    bl = model.reconstruct(imgs, cams, surface=surface, surface_mode="blend")
    model.config.gaussians.coverage_target, model.config.gaussians.mirror_views = 0.9, True
    sd = surface_ray_depth(surface, cams)
    n = bl.num_reconstructed
    assert n == av.num_reconstructed  # same pixels kept (the opacities do not depend on depth)
    d_bl, _ = cKDTree(neutral).query(bl.gaussians.means[:n].numpy())
    assert np.median(d_bl) > np.median(d)  # off the face the network's depth, not the head
    assert bool(sd.face_hit.any())




@needs_faces
def test_track_then_reconstruct_uses_the_tracked_head(tmp_path, capsys):
    """`fastgha track` writes head.json; `fastgha reconstruct` binds to that head (not with --no-surface)."""
    import json

    import matplotlib.cbook as cbook
    from PIL import Image

    from fastgha_core.cli import main
    from fastgha_core.model.avatar import CanonicalAvatar

    photo = tmp_path / "gh.jpg"
    Image.open(cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)).convert("RGB").save(photo)
    req = tmp_path / "req"
    assert main(["track", "--images", str(photo), "--out", str(req), "--size", "128"]) == 0
    head = json.loads((req / "head.json").read_text())
    ident = np.asarray(head["identity"], np.float32)
    assert ident.shape == (100,) and np.abs(ident).max() > 0
    crops = sorted(p.name for p in req.glob("[0-9][0-9]_*.png") if not p.stem.endswith("_mask"))
    assert sorted(head["frames"]) == crops  # each crop's photo, by file name (HeadSurface.frames)
    f = np.asarray(head["frames"][crops[0]])
    assert f.shape == (4,) and f[2] > f[0] and f[3] > f[1]
    assert main(["reconstruct", "--input", str(req), "--out", str(tmp_path / "a.safetensors")]) == 0
    assert main(["reconstruct", "--input", str(req), "--out", str(tmp_path / "b.safetensors"), "--no-surface"]) == 0
    a, b = CanonicalAvatar.load(tmp_path / "a.safetensors"), CanonicalAvatar.load(tmp_path / "b.safetensors")
    k = a.prior.identity.shape[0]
    assert np.allclose(a.prior.identity.numpy(), ident[:k], atol=1e-5) and torch.allclose(a.prior.transform, torch.eye(4))
    assert not np.allclose(b.prior.identity.numpy(), ident[:k], atol=1e-3)  # an ICP fit to the network's Gaussians
    (req / "expressions.json").unlink()
    assert main(["reconstruct", "--input", str(req), "--out", str(tmp_path / "c.safetensors")]) == 2
    assert "needs expressions.json" in capsys.readouterr().err


# ---------------------------------------------------------------- photos with known cameras
def _world_cameras(yaws_deg, G, size=256, dist=0.8):
    """Cameras around the head at ``yaws_deg`` whose world is the head frame moved by ``G [4, 4]``
    (head -> world): ``w2c = w2c_head @ inv(G)``."""
    from fastgha_core.cameras import Cameras

    c = _cameras(yaws_deg, size=size, dist=dist)
    w2c = c.w2c.double() @ torch.from_numpy(np.linalg.inv(G))
    return Cameras(c.K, w2c.float(), size, size)


def _rigid(rot_deg, axis, t):
    G = np.eye(4)
    a = np.asarray(axis, float)
    G[:3, :3] = rodrigues(np.radians(rot_deg) * a / np.linalg.norm(a))
    G[:3, 3] = t
    return G


def test_known_camera_fit_recovers_head_pose_and_shape_from_exact_landmarks():
    """Landmarks of a known head projected through known cameras whose world is not the head frame:
    one shared head -> world transform, identity and per-view expressions come back."""
    from fastgha_core.tracking.fit import FitConfig, LandmarkModel, fit_known_cameras

    head = HeadModel.load()
    rng = np.random.default_rng(11)
    ident = np.zeros(100)
    ident[:30] = rng.standard_normal(30) * 0.6
    expr = np.zeros((3, 53))
    expr[1, head.expression_names.index("jawOpen")] = 0.5
    G = _rigid(25.0, [0.3, 1.0, 0.2], [0.12, -0.05, 0.3])
    cams = _world_cameras([-30.0, 0.0, 40.0], G)
    model = LandmarkModel.from_head_model(num_identity=30)
    lms = []
    for v in range(3):
        X = model.points(ident[:30], expr[v]) @ G[:3, :3].T + G[:3, 3]
        x = X @ cams.R[v].double().numpy().T + cams.t[v].double().numpy()
        uv = x @ cams.K[v].double().numpy().T
        lms.append(uv[:, :2] / uv[:, 2:])
    lms.append(None)  # a fourth photo without landmarks keeps a neutral expression
    K = np.concatenate([cams.K.double().numpy(), cams.K[:1].double().numpy()])
    w2c = np.concatenate([cams.w2c.double().numpy(), cams.w2c[:1].double().numpy()])
    fit = fit_known_cameras(lms, K, w2c, FitConfig(num_identity=30, identity_weight=0.01, expression_weight=0.1, weak_expression_weight=0.1), model)
    assert fit.detected.tolist() == [True, True, True, False]
    R_err = np.degrees(np.arccos(np.clip((np.trace(fit.head_to_world[:3, :3].T @ G[:3, :3]) - 1) / 2, -1, 1)))
    assert R_err < 0.3 and np.linalg.norm(fit.head_to_world[:3, 3] - G[:3, 3]) < 0.002, (R_err, fit.head_to_world)
    assert np.nanmax(fit.rms_px) < 0.5 and np.isnan(fit.rms_px[3])
    assert abs(fit.expressions[1, head.expression_names.index("jawOpen")] - 0.5) < 0.1 and not fit.expressions[3].any()
    surf = HeadSurface(fit.identity, fit.expressions, fit.head_to_world)
    truth = head.vertices(ident.astype(np.float32), expr[1].astype(np.float32)) @ G[:3, :3].T + G[:3, 3]
    err = np.linalg.norm(surf.vertices(1, head) - truth, axis=1)[head.landmarks68]
    assert np.median(err) < 0.002, np.median(err)


def test_head_surface_transform_moves_vertices_and_the_prior_fit():
    head = HeadModel.load()
    G = _rigid(30.0, [0, 1, 0], [0.1, 0.0, -0.2])
    a = HeadSurface(np.zeros(100), np.zeros((1, 53)))
    b = HeadSurface(np.zeros(100), np.zeros((1, 53)), G)
    np.testing.assert_allclose(b.vertices(0, head), a.vertices(0, head) @ G[:3, :3].T + G[:3, 3], atol=1e-5)
    assert b.subset([0, 0]).head_to_world is b.head_to_world
    with pytest.raises(ValueError, match="rigid"):
        HeadSurface(np.zeros(100), np.zeros((1, 53)), np.diag([2.0, 2.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match=r"\[4, 4\]"):
        HeadSurface(np.zeros(100), np.zeros((1, 53)), np.eye(3))


def test_ray_depth_follows_the_world_frame():
    """The same head seen by the same cameras gives the same ray depth whichever world they share."""
    s0 = HeadSurface(np.zeros(100), np.zeros((2, 53)))
    G = _rigid(40.0, [0.2, 1.0, 0.0], [0.3, 0.1, -0.5])
    s1 = HeadSurface(np.zeros(100), np.zeros((2, 53)), G)
    d0 = surface_ray_depth(s0, _cameras([0.0, 45.0])).t
    d1 = surface_ray_depth(s1, _world_cameras([0.0, 45.0], G, size=128, dist=0.6)).t
    assert float((d0 - d1).abs().max()) < 1e-3


@needs_faces
def test_known_camera_fit_places_a_synthetic_head_through_the_detector():
    """Held-out synthetic subject (seed 1000300, not an evaluation or tuning seed), the evaluation
    protocol's 4 inputs at 256^2 (2 of them profiles without landmarks): the head fitted through the
    true cameras lies within 1 cm of the true mesh on average, and far closer than the per-photo
    (photo-only) poses placed through the same cameras."""
    from fastgha_core.data.synthetic import make_sequence
    from fastgha_core.train.evaluate import EvalConfig, _cameras_at, fit_input_surface, select_protocol, surface_error_mm

    src = make_sequence(1000300, timesteps=16, num_cameras=16, resolution=256)
    proto = select_protocol(src, EvalConfig())
    pairs = list(zip(proto.input_timesteps, proto.input_cameras))
    images = torch.stack([src.view(t, c).image for t, c in pairs])
    surf, fit = fit_input_surface(images, _cameras_at(src, pairs))
    assert surf is not None, fit
    assert fit.detected.sum() >= 2 and surf.head_to_world is not None
    err = surface_error_mm(src, proto.input_timesteps, surf)
    assert err["all_mm"] < 10.0 and err["face_mm"] < 12.0, err
    # the photos' own poses disagree by centimetres along their viewing rays; the shared one does not
    assert np.nanmax(fit.pose_spread_mm) > 15.0, fit.pose_spread_mm


def test_evaluation_reconstructs_on_the_fitted_head_when_asked(monkeypatch):
    """``EvalConfig.surface``: "tracked"/"blend" fit the head to the input photos through their cameras
    and reconstruct on it (the fit's failure falls back to the network's depth and is counted);
    "none" fits nothing."""
    import fastgha_core.train.evaluate as ev
    from fastgha_core.data.synthetic import make_sequence
    from fastgha_core.model.fastgha import FastGHA
    from fastgha_core.train.toy import toy_model_config

    src = make_sequence(1000301, timesteps=4, num_cameras=8, resolution=64)
    torch.manual_seed(0)
    model = FastGHA(toy_model_config(32)).eval()
    head = HeadSurface(np.zeros(100), np.zeros((4, 53)), np.eye(4))
    calls, got = [], []

    class Fit:
        detected = np.array([True, False, False, True])
        rms_px = np.array([1.0, np.nan, np.nan, 2.0])

    def fake_fit(images, cameras, detector=None, masks=None):
        calls.append((tuple(images.shape), cameras.width, None if masks is None else tuple(masks.shape)))
        return (head, Fit()) if len(calls) == 1 else (None, "no face")

    monkeypatch.setattr(ev, "fit_input_surface", fake_fit)
    recon = model.reconstruct
    monkeypatch.setattr(model, "reconstruct", lambda *a, **k: (got.append((k.get("surface"), k.get("surface_mode"))), recon(*a, **k))[1])
    cfg = dict(num_inputs=4, num_target_timesteps=1, num_target_views=1, backend="cpu")
    rep = ev.evaluate(model, [src], ev.EvalConfig(surface="blend", **cfg), progress=False)
    assert calls == [((4, 3, 64, 64), 64, (4, 1, 64, 64))] and got == [(head, "blend")]
    assert rep["subjects"][0]["surface"]["fitted"] and rep["subjects"][0]["surface"]["views_with_landmarks"] == 2
    assert rep["subjects"][0]["surface"]["error"]["all_mm"] > 0 and rep["surface_fallbacks"] == 0
    rep = ev.evaluate(model, [src], ev.EvalConfig(surface="tracked", **cfg), progress=False)
    assert got[-1] == (None, "replace") and rep["surface_fallbacks"] == 1 and not rep["subjects"][0]["surface"]["fitted"]
    n = len(calls)
    ev.evaluate(model, [src], ev.EvalConfig(surface="none", **cfg), progress=False)
    assert len(calls) == n and got[-1] == (None, "replace")
    with pytest.raises(ValueError, match="surface"):
        ev.EvalConfig(surface="mesh")


def test_blend_puts_the_face_on_the_surface_and_leaves_the_far_rest_to_the_network(surface):
    from fastgha_core.model.surface import blend_network_depth

    cams = _cameras([0.0, 40.0], size=128)
    sd = surface_ray_depth(surface.subset([0, 0]), cams)
    assert sd.face_hit is not None and sd.face_hit.any() and not (sd.face_hit & ~sd.hit).any()
    # the bare face only: no hair region (top rows of the frontal view are the scalp, not the face)
    assert not sd.face_hit[0, :20].any()
    t_net = sd.t + 0.03 + 0.01 * torch.randn(sd.t.shape, generator=torch.Generator().manual_seed(0))
    out = blend_network_depth(sd, t_net, falloff_px=8.0)
    fh = sd.face_hit
    assert torch.equal(out[fh], sd.t[fh])
    from scipy.ndimage import distance_transform_edt

    for v in range(2):
        d = torch.from_numpy(distance_transform_edt(~fh[v].numpy()))
        far, near = d > 25, (d > 0) & (d <= 2)
        assert far.sum() > 500
        # far from the face: the network's own depth, within the fading offset (falloff 8 px at 256 = 4 px here)
        assert float((out[v][far] - t_net[v][far]).abs().max()) < 0.05 * np.exp(-25 / 4), v
        # next to the face: moved most of the way onto the surface (no 3 cm step at the face's edge)
        assert float((out[v][near] - sd.t[v][near]).abs().median()) < 0.012
    with pytest.raises(ValueError, match="shape"):
        blend_network_depth(sd, t_net[:1])


@needs_faces
def test_reconstruct_with_cameras_fits_the_head_through_them(tmp_path):
    """`fastgha reconstruct --surface-fit blend` on a folder with its own cameras (the shipped sample):
    the avatar's prior is bound to the head fitted through those cameras (near the synthetic truth's
    origin, since the sample's world is its head frame); `off` keeps the ICP fit."""
    from fastgha_core.cli import main
    from fastgha_core.data.samples import SAMPLES_DIR
    from fastgha_core.model.avatar import CanonicalAvatar

    req = SAMPLES_DIR / "synth_1000000" / "request"
    assert main(["reconstruct", "--input", str(req), "--out", str(tmp_path / "a.safetensors"), "--surface-fit", "blend"]) == 0
    assert main(["reconstruct", "--input", str(req), "--out", str(tmp_path / "b.safetensors")]) == 0
    a, b = CanonicalAvatar.load(tmp_path / "a.safetensors"), CanonicalAvatar.load(tmp_path / "b.safetensors")
    Ta, Tb = a.prior.transform.double().numpy(), b.prior.transform.double().numpy()
    R = Ta[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-4)  # rigid: the known-camera fit, not a scaled ICP fit
    assert np.linalg.norm(Ta[:3, 3]) < 0.02 and np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) < 8.0
    assert not np.allclose(Ta, Tb, atol=1e-4)


@needs_faces
def test_server_tracker_fits_the_head_through_posted_cameras():
    """``PhotoTracker.fit_known_cameras`` (the server's with-cameras path) on the shipped sample's photos,
    masks and cameras: a rigid head near the sample's head frame; a camera of the wrong size gives None."""
    import json

    from PIL import Image

    from fastgha_core.cameras import cameras_from_json
    from fastgha_core.data.samples import SAMPLES_DIR
    from server.tracking import PhotoTracker

    req = SAMPLES_DIR / "synth_1000000" / "request"
    paths = sorted(req.glob("[0-9][0-9].jpg"))
    imgs = [torch.from_numpy(np.asarray(Image.open(p).convert("RGB"), np.float32) / 255.0).permute(2, 0, 1) for p in paths]
    masks = [torch.from_numpy(np.asarray(Image.open(p.with_name(p.stem + "_mask.png")).convert("L"), np.float32) / 255.0)[None] for p in paths]
    cams = cameras_from_json(json.loads((req / "cameras.json").read_text()))
    tracker = PhotoTracker()
    surf = tracker.fit_known_cameras(imgs, cams, masks=masks)
    assert surf is not None and len(surf) == len(paths)
    H = surf.head_to_world
    assert np.linalg.norm(H[:3, 3]) < 0.02 and np.degrees(np.arccos(np.clip((np.trace(H[:3, :3]) - 1) / 2, -1, 1))) < 8.0
    assert tracker.fit_known_cameras(imgs, [c.resize(c.width // 2, c.height // 2) for c in cams]) is None
