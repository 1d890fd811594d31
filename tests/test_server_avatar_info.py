"""What the server reports per avatar (``server/avatar_info.py``), its view-blending tau setting,
and the same-person check of an avatar's photos (``server/identity.py``).

In process: creation jobs through a real ``JobQueue`` with the 64 x 64 tiny test model, and the
HTTP routes through ``create_app`` under Starlette's ``TestClient`` (lifespan included). Real
photos: the public-domain Grace Hopper fixtures and scikit-image's astronaut; the real sets of
``../shared/realsets`` (or ``FASTGHA_REALSETS``) when present.
"""

from __future__ import annotations

import io
import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image, ImageOps

from client_demo.client import describe_avatar
from server.avatar_info import FACT_KEYS, avatar_options
from server.identity import IdentityChecker, same_person_groups
from server.jobs import CreationRequest, Photo
from extras import hide_modules
from server_process import SAMPLE_NAME, make_model_dir, make_sample_dir

pytestmark = pytest.mark.timeout(300)

REPO = Path(__file__).resolve().parent.parent
FIX = Path(__file__).resolve().parent / "fixtures" / "images"
REALSETS = Path(os.environ.get("FASTGHA_REALSETS", REPO.parent / "shared" / "realsets"))


def _dlib_ok() -> bool:
    return IdentityChecker().available


needs_dlib = pytest.mark.skipif(not _dlib_ok(), reason="needs dlib and face_recognition_models (the 'faces' extra)")


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    return make_model_dir(tmp_path_factory.mktemp("model"))


@pytest.fixture(scope="module")
def samples(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("samples")
    make_sample_dir(root)
    return root / SAMPLE_NAME / "request"


def _ctx(model_dir, tmp_path, **settings):
    from fastgha_core import load_model
    from fastgha_core.model.avatar import CanonicalAvatar
    from server.app import apply_model_overrides
    from server.context import ServerContext
    from server.settings import Settings
    from server.store import AvatarStore

    s = Settings(data_dir=tmp_path, warmup=False, **settings)
    ctx = ServerContext(settings=s)
    ctx.model = load_model(str(model_dir), device="cpu")
    apply_model_overrides(ctx.model, s)  # as the server's start-up does
    ctx.store = AvatarStore(tmp_path, 10**9, 0, load_fn=CanonicalAvatar.load)
    ctx.identity = IdentityChecker(s.same_person_check, s.same_person_max_distance)
    return ctx


def _run_job(ctx, request, tracker=None):
    import asyncio

    from server.jobs import JobQueue

    async def run():
        q = JobQueue(ctx, tracker=tracker, extra_stages=[])
        await q.start()
        try:
            job, _ = q.submit(q.reserve("test", 1), request)
            await q.wait(job)
            return job
        finally:
            await q.stop()

    return asyncio.run(run())


def _sample_request(samples, with_cameras=True):
    from fastgha_core.cameras import cameras_from_json

    imgs = sorted(samples.glob("[0-9][0-9].jpg"))
    cams = cameras_from_json(json.loads((samples / "cameras.json").read_text())) if with_cameras else None
    return [Photo(p.name, p.read_bytes()) for p in imgs], cams


class _Tracker:
    """Stands in for server.tracking.PhotoTracker: the sample's own cameras and a generic head
    (reconstruction on a tracked head records per-view data)."""

    def __init__(self, cams):
        self.cams = cams

    def track(self, images, masks, size, names=None):
        from fastgha_core.cameras import Cameras
        from fastgha_core.model.surface import HeadSurface

        v = len(images)
        crops = torch.stack(list(images))
        return crops, Cameras.stack([self.cams[i] for i in range(v)]), torch.ones(v, 1, *crops.shape[-2:]), torch.zeros(v, 53), HeadSurface(np.zeros(100), np.zeros((v, 53)))


# ---------------------------------------------------------------- view blending and prior, per avatar
@pytest.mark.parametrize("tau,views", [(20.0, 4), (0.0, 4), (20.0, 1)])
def test_tracked_avatar_reports_per_view_data_and_whether_frames_are_blended(model_dir, samples, tmp_path, tau, views):
    """An avatar built on a tracked head has per-view data: the report says so, with the number of
    views, the server's tau, and ``active`` exactly when a side camera changes the frame's opacities
    (never with one view: its every weight is 1). Mirrored views off (FASTGHA_MIRROR_VIEWS=false),
    so the views are the photos."""
    from fastgha_core.cameras import Cameras

    ctx = _ctx(model_dir, tmp_path, view_blend_tau_deg=tau, mirror_views=False)
    photos, cams = _sample_request(samples)
    photos = photos[:views]
    job = _run_job(ctx, CreationRequest(photos, None, None), tracker=_Tracker(cams))
    assert job.status == "ready", job.error and job.error.message
    stored = ctx.store.get(job.id).avatar
    assert stored.view_blend is not None
    rep = job.result["view_blend"]
    assert rep == {"per_view_data": True, "views": views, "tau_deg": tau, "active": tau > 0 and views > 1}
    side = Cameras.look_at((0.7, 0.0, 0.7), fov_deg=20.0, width=64, height=64)
    z = ctx.model.expression_space.neutral()
    with torch.inference_mode():
        plain = ctx.model.animate(stored, z).opacities
        blended = ctx.model.animate(stored, z, camera=side).opacities
    assert (not torch.equal(plain, blended)) == rep["active"]  # the report tells what the frames do
    prior = job.result["expression_prior"]
    assert prior["enabled"] is True and prior["bound"] == (stored.prior is not None)  # tiny runs the prior
    assert prior["mouth_interior_gaussians"] == stored.num_interior > 0
    d = ctx.model.config.deform
    assert (prior["shading"], prior["rotate"], prior["back_shell"], prior["chin_shell"], prior["cheek_shell"], prior["face_shell"]) == (
        d.prior_shading, d.prior_rotate, d.back_shell, d.chin_shell, d.cheek_shell, d.face_shell)
    meta = ctx.store.get_meta(job.id)
    assert avatar_options(ctx.model, meta) == {k: job.result[k] for k in ("view_blend", "expression_prior")}


def test_mirrored_views_count_in_the_report_and_the_setting_turns_them_off(model_dir, samples, tmp_path):
    """With the model's default (mirrored views on), the sample's turned photos add mirrored virtual
    views: the report counts the avatar's recorded views, more than the 4 photos; FASTGHA_MIRROR_VIEWS=false
    (``mirror_views=False``) leaves the photos alone."""
    photos, cams = _sample_request(samples)
    counts = {}
    for setting in (None, False):
        ctx = _ctx(model_dir, tmp_path / str(setting), mirror_views=setting)
        assert ctx.model.config.gaussians.mirror_views is (setting is None)  # tiny's own default is on
        job = _run_job(ctx, CreationRequest(photos, None, None), tracker=_Tracker(cams))
        assert job.status == "ready", job.error and job.error.message
        vb = ctx.store.get(job.id).avatar.view_blend
        assert job.result["view_blend"]["views"] == vb.directions.shape[0]
        counts[setting] = vb.directions.shape[0]
    assert counts[False] == 4 and 4 < counts[None] <= 8, counts


def test_avatar_from_photos_with_cameras_has_no_per_view_data(model_dir, samples, tmp_path):
    ctx = _ctx(model_dir, tmp_path)
    photos, cams = _sample_request(samples)
    job = _run_job(ctx, CreationRequest(photos, None, cams))
    assert job.status == "ready", job.error and job.error.message
    assert ctx.store.get(job.id).avatar.view_blend is None
    assert job.result["view_blend"] == {"per_view_data": False, "views": 0, "tau_deg": 20.0, "active": False}


def test_describe_avatar_says_each_case():
    vb = {"per_view_data": True, "views": 4, "tau_deg": 20.0, "active": True}
    sp = {"checked": True, "photos_compared": 3, "photos_without_face": ["side.jpg"], "max_distance": 0.47, "check_ms": 300.0}
    said = describe_avatar({"view_blend": vb, "expression_prior": {"enabled": False}, "same_person": sp})
    assert said == ("view blending on (4 views, tau 20 deg); expression prior off (the deformation MLP alone); "
                    "same person: 3 photos compared (largest distance 0.47); no frontal face in side.jpg (not compared)")  # fmt: skip
    assert describe_avatar({"view_blend": {**vb, "tau_deg": 0.0, "active": False}}) == "view blending off (the server's tau is 0)"
    assert describe_avatar({"view_blend": {**vb, "views": 1, "active": False}}) == "view blending off (one input view)"
    assert describe_avatar({"same_person": {"checked": False, "reason": "one photo"}}) == "same person: not checked (one photo)"
    assert describe_avatar({}) == ""  # an older server: nothing to say


def test_describe_avatar_names_mirrored_views_apart_from_photos():
    """``view_blend.views`` counts the mirrored views of turned photos (docs/protocol.md): 4 photos with
    two turned blend 6 views; the line says where the 2 extra come from instead of "6 views" alone."""
    vb = {"per_view_data": True, "views": 6, "tau_deg": 20.0, "active": True}
    assert describe_avatar({"view_blend": vb, "num_images": 4}) == "view blending on (6 views: 4 photos + 2 mirrored, tau 20 deg)"
    one = describe_avatar({"view_blend": {**vb, "views": 2}, "num_images": 1})
    assert one == "view blending on (2 views: 1 photo + 1 mirrored, tau 20 deg)"
    assert describe_avatar({"view_blend": {**vb, "views": 4}, "num_images": 4}) == "view blending on (4 views, tau 20 deg)"
    assert describe_avatar({"view_blend": vb}) == "view blending on (6 views, tau 20 deg)"  # no photo count given


# ---------------------------------------------------------------- the tau setting
@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), 361.0])
def test_tau_setting_refuses_bad_values_with_a_clear_error(bad):
    from pydantic import ValidationError

    from server.settings import Settings

    with pytest.raises(ValidationError, match=r"view_blend_tau_deg must be 0 \(off\) or a number of degrees in \(0, 360\]"):
        Settings(view_blend_tau_deg=bad)
    assert Settings(view_blend_tau_deg=0).view_blend_tau_deg == 0.0 and Settings().view_blend_tau_deg is None


def test_tau_from_env_and_serve_flag(monkeypatch, capsys):
    import socket

    from fastgha_core.cli import main
    from server.settings import Settings

    monkeypatch.setenv("FASTGHA_VIEW_BLEND_TAU_DEG", "35")
    assert Settings().view_blend_tau_deg == 35.0
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = str(s.getsockname()[1])
    assert main(["serve", "--port", port, "--view-blend-tau-deg", "-5"]) == 2
    assert "--view-blend-tau-deg=-5.0: view_blend_tau_deg must be 0 (off)" in capsys.readouterr().err
    monkeypatch.setenv("FASTGHA_VIEW_BLEND_TAU_DEG", "nan")
    assert main(["serve", "--port", port]) == 2
    assert "FASTGHA_VIEW_BLEND_TAU_DEG=" in capsys.readouterr().err


def test_http_routes_report_tau_prior_and_same_person(model_dir, samples, tmp_path):
    """``GET /v1/model`` reports the server's tau (here 0: off) and prior options; the 201 answer,
    ``GET /v1/avatars/{id}`` and its ready status report the avatar's; an avatar whose metadata
    predates these facts gets them from its file."""
    from starlette.testclient import TestClient

    from server.app import create_app
    from server.settings import Settings

    s = Settings(model=str(model_dir), data_dir=tmp_path, warmup=False, compile="off", mlp_precision="fp32", view_blend_tau_deg=0)
    with TestClient(create_app(s)) as client:
        info = client.get("/v1/model").json()
        assert info["view_blend_tau_deg"] == 0.0 and info["expression_prior"]["enabled"] is True
        assert client.app.state.ctx.model.config.gaussians.view_blend_tau_deg == 0.0  # the frames use it
        photos, cams = _sample_request(samples)
        from fastgha_core.cameras import cameras_to_json

        files = [("images", (p.name, p.data, "image/jpeg")) for p in photos]
        r = client.post("/v1/avatars", files=files, data={"cameras": json.dumps([cameras_to_json(c)[0] for c in cams])})
        assert r.status_code == 201, r.text
        created = r.json()
        auth = {"Authorization": f"Bearer {created['token']}"}
        got = client.get(f"/v1/avatars/{created['avatar_id']}", headers=auth).json()
        for key in ("view_blend", "expression_prior", "same_person"):
            assert got[key] == created[key], key
        assert got["view_blend"]["tau_deg"] == 0.0 and not got["view_blend"]["active"]
        assert not set(FACT_KEYS) & set(got)  # the raw facts stay internal
        assert got["num_gaussians"] == created["num_gaussians"] and "active_streams" in got  # the old fields are still there
        said = describe_avatar(got)  # what `fastgha client` prints
        assert "view blending off (no per-view data" in said and "expression prior on" in said and "same person:" in said, said
        status = client.get(f"/v1/avatars/{created['avatar_id']}/status", headers=auth).json()
        assert status["avatar"]["view_blend"] == got["view_blend"]
        # the stream's ready message says the same: tests/test_server.py (a real uvicorn process; the
        # TestClient's websocket teardown cancels the stream's tasks and raises CancelledError)
    # metadata written before the facts were recorded (an older server): read from the avatar file after a restart
    meta_path = tmp_path / "avatars" / f"{created['avatar_id']}.json"
    meta = json.loads(meta_path.read_text())
    assert set(FACT_KEYS) <= set(meta)
    meta_path.write_text(json.dumps({k: v for k, v in meta.items() if k not in FACT_KEYS}))
    with TestClient(create_app(s)) as client:
        again = client.get(f"/v1/avatars/{created['avatar_id']}", headers=auth).json()
    assert again["expression_prior"] == got["expression_prior"] and again["view_blend"] == got["view_blend"]


# ---------------------------------------------------------------- same person
def test_groups_link_through_chains_and_skip_photos_without_a_face():
    e = np.eye(128)
    a, b, c = np.zeros(128), 0.5 * e[0], 1.0 * e[0]  # a-b 0.5, b-c 0.5, a-c 1.0: one chain
    far = 3.0 * e[1]
    groups, dist = same_person_groups([a, None, b, c], 0.6)
    assert groups == [[0, 2, 3]] and math.isnan(dist[1, 0]) and dist[0, 3] == pytest.approx(1.0)
    groups, _ = same_person_groups([a, far, b, None], 0.6)
    assert groups == [[0, 2], [1]]
    assert same_person_groups([None, None], 0.6)[0] == []


def test_check_names_the_photos_of_each_person():
    from server.errors import ApiError

    chk = IdentityChecker()
    chk._models = object()  # as if dlib were loaded: check() only compares descriptors
    e = np.eye(128)
    with pytest.raises(ApiError) as err:
        chk.check(["me1.jpg", "me2.jpg", "you.jpg", "profile.jpg"], [np.zeros(128), 0.3 * e[0], 0.9 * e[1], None])
    assert err.value.status == 422 and err.value.code == "different_people"
    msg = err.value.message
    assert "photos me1.jpg, me2.jpg / photo you.jpg" in msg and "profile.jpg" not in msg and "0.6" in msg, msg
    ok = chk.check(["a.jpg", "side.jpg"], [np.zeros(128), None]).as_dict()
    assert ok["checked"] and ok["photos_compared"] == 1 and ok["photos_without_face"] == ["side.jpg"] and ok["max_distance"] is None


def test_without_dlib_nothing_is_checked_and_the_avatar_says_so(model_dir, samples, tmp_path, monkeypatch):
    hide_modules(monkeypatch, "dlib", "face_recognition_models")
    ctx = _ctx(model_dir, tmp_path)
    photos, cams = _sample_request(samples)
    job = _run_job(ctx, CreationRequest(photos, None, cams))
    assert job.status == "ready", job.error and job.error.message
    sp = job.result["same_person"]
    assert sp["checked"] is False and "dlib" in sp["reason"] and "faces" in sp["reason"]
    assert ctx.store.get_meta(job.id)["same_person"] == sp


def _jpeg(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="JPEG", quality=92)
    return buf.getvalue()


def _astronaut() -> bytes:
    skimage_data = pytest.importorskip("skimage.data", reason="needs scikit-image (dev extra) for the astronaut portrait")
    return _jpeg(skimage_data.astronaut())


@needs_dlib
def test_photos_of_two_people_are_refused_naming_them(model_dir, tmp_path):
    """Grace Hopper (upright, and the same photo stored sideways with EXIF orientation 6) and the
    astronaut: 422 different_people naming the two groups; Grace Hopper's two alone pass."""
    from fastgha_core.cameras import orbit_cameras

    ctx = _ctx(model_dir, tmp_path)
    grace = [Photo("hopper_upright.jpg", (FIX / "grace_hopper_upright.jpg").read_bytes()),
             Photo("hopper_exif6.jpg", (FIX / "grace_hopper_exif6.jpg").read_bytes())]  # fmt: skip
    astro = Photo("astronaut.jpg", _astronaut())

    def cams_for(photos):
        out = []
        for p in photos:
            w, h = ImageOps.exif_transpose(Image.open(io.BytesIO(p.data))).size
            out.append(orbit_cameras(1, width=w, height=h))
        return out

    job = _run_job(ctx, CreationRequest([*grace, astro], None, cams_for([*grace, astro])))
    assert job.status == "failed" and job.error.status == 422 and job.error.code == "different_people", job.error
    assert "photos hopper_upright.jpg, hopper_exif6.jpg / photo astronaut.jpg" in job.error.message
    job = _run_job(_ctx(model_dir, tmp_path / "one"), CreationRequest(grace, None, cams_for(grace)))
    assert job.status == "ready", job.error and job.error.message
    sp = job.result["same_person"]
    assert sp["checked"] and sp["photos_compared"] == 2 and sp["max_distance"] < 0.6


def _realset_descriptors(chk):
    out = {}
    for d in sorted(p for p in REALSETS.iterdir() if p.is_dir()):
        out[d.name] = [(f.name, chk.descriptor(np.asarray(ImageOps.exif_transpose(Image.open(f)).convert("RGB")))) for f in sorted(d.glob("*.jpg"))]
    return out


@needs_dlib
@pytest.mark.skipif(not REALSETS.is_dir(), reason="needs the real photo sets (../shared/realsets or FASTGHA_REALSETS)")
def test_real_sets_pass_and_mixing_two_sets_is_refused():
    """Each real set is one person: it passes (side views without a frontal face are skipped, not
    refused); every pair of sets mixed is refused."""
    from server.errors import ApiError

    chk = IdentityChecker()
    sets = _realset_descriptors(chk)
    assert len(sets) >= 2
    for name, photos in sets.items():
        res = chk.check([n for n, _ in photos], [d for _, d in photos])
        assert res.checked and len(res.compared) >= 2, (name, res)
    names = sorted(sets)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            mixed = sets[a] + sets[b]
            with pytest.raises(ApiError) as err:
                chk.check([f"{a}/{n}" for n, _ in sets[a]] + [f"{b}/{n}" for n, _ in sets[b]], [d for _, d in mixed])
            assert err.value.code == "different_people" and a in err.value.message and b in err.value.message


@needs_dlib
def test_track_refuses_photos_of_two_people_as_the_server_does(tmp_path, capsys):
    """``fastgha track`` fits one head to all its photos: photos of two people are refused in one line
    naming them, before any fitting; one person's two photos (a mirrored copy) track."""
    from fastgha_core.cli import main

    hopper, astro, mirror = tmp_path / "hopper.jpg", tmp_path / "astronaut.jpg", tmp_path / "hopper_mirrored.jpg"
    hopper.write_bytes((FIX / "grace_hopper_upright.jpg").read_bytes())
    astro.write_bytes(_astronaut())
    Image.open(hopper).transpose(Image.Transpose.FLIP_LEFT_RIGHT).save(mirror, quality=92)
    assert main(["track", "--images", str(hopper), str(astro), "--out", str(tmp_path / "mixed"), "--size", "64"]) == 2
    err = capsys.readouterr().err
    assert "do not all show the same person" in err and "hopper.jpg" in err and "astronaut.jpg" in err, err
    assert "tracking 2 photo(s)" not in err and not (tmp_path / "mixed").exists()  # refused before tracking
    assert main(["track", "--images", str(hopper), str(mirror), "--out", str(tmp_path / "one"), "--size", "64"]) == 0
    assert "tracking 2 photo(s): finding the face" in capsys.readouterr().err  # progress before the fit
