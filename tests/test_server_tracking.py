"""``POST /v1/avatars`` without cameras: the server tracks the photos (``server/tracking.py``).

End to end against a real server process (``server_process.py``: a 64 x 64 tiny model) with a
real photo (matplotlib's Grace Hopper portrait) and a blank image; the missing-extra answer is
tested on ``PhotoTracker`` with dlib hidden from the import system.
"""

from __future__ import annotations

import io
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest
import torch
from PIL import Image

from server.errors import ApiError
from server.tracking import PhotoTracker
from server_process import API_KEY, ServerProcess, make_model_dir
from extras import needs_faces

pytestmark = pytest.mark.timeout(300)






def _png(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="PNG")
    return buf.getvalue()


def _portrait_jpeg() -> bytes:
    import matplotlib.cbook as cbook

    return Path(cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)).read_bytes()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    model = make_model_dir(tmp_path_factory.mktemp("model"))
    srv = ServerProcess(model, tmp_path_factory.mktemp("data"), None, tmp_path_factory.mktemp("logs") / "server.log")
    yield srv
    srv.stop()


def _post(server, files) -> httpx.Response:
    return httpx.post(server.base + "/v1/avatars", files=files, headers={"X-API-Key": API_KEY}, timeout=120)


@needs_faces
def test_photo_without_cameras_is_tracked_and_reconstructed(server):
    r = _post(server, [("images", ("hopper.jpg", _portrait_jpeg(), "image/jpeg"))])
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["num_gaussians"] > 0 and body["tracking_ms"] > 0
    meta = httpx.get(f"{server.base}/v1/avatars/{body['avatar_id']}", headers={"Authorization": f"Bearer {body['token']}"}, timeout=30).json()
    assert meta["num_images"] == 1 and meta["tracking_ms"] == body["tracking_ms"]


@needs_faces
def test_python_client_creates_an_avatar_from_a_photo_without_cameras(server):
    from client_demo.client import FastGHAClient

    client = FastGHAClient(server.base, api_key=API_KEY, timeout=120)
    avatar = client.create_avatar([_portrait_jpeg()])
    assert avatar.num_gaussians > 0 and avatar.tracking_ms is not None and avatar.tracking_ms > 0
    assert client.avatar_info(avatar)["num_images"] == 1
    client.delete(avatar)


@needs_faces
def test_photo_without_face_gets_no_face_with_its_filename(server):
    blank = _png(np.full((240, 320, 3), 128, np.uint8))
    r = _post(server, [("images", ("blank.png", blank, "image/png"))])
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "no_face" and "blank.png" in err["message"] and "image 0" not in err["message"]
    # the second photo is the faceless one: the message names it by its filename, never by an index
    r = _post(server, [("images", ("hopper.jpg", _portrait_jpeg(), "image/jpeg")), ("images", ("IMG_0042.png", blank, "image/png"))])
    assert r.status_code == 422 and r.json()["error"]["code"] == "no_face"
    msg = r.json()["error"]["message"]
    assert "IMG_0042.png" in msg and "image 1" not in msg and "hopper.jpg" not in msg


@needs_faces
def test_tiny_face_is_refused(server):
    small = Image.open(io.BytesIO(_portrait_jpeg())).convert("RGB")
    small = small.resize((small.width // 4, small.height // 4), Image.BILINEAR)  # face box ~45 px < 80 px
    r = _post(server, [("images", ("small.png", _png(np.asarray(small)), "image/png"))])
    assert r.status_code == 422, r.text
    assert r.json()["error"]["code"] == "face_too_small" and "small.png" in r.json()["error"]["message"]


@needs_faces
def test_photo_tracker_output_matches_model_input():
    from fastgha_core.cameras import Cameras

    img = torch.from_numpy(np.array(Image.open(io.BytesIO(_portrait_jpeg())).convert("RGB"))).permute(2, 0, 1).float() / 255.0
    crops, cams, masks, expr, surface = PhotoTracker().track([img], None, 64)
    assert crops.shape == (1, 3, 256, 256) and masks.shape == (1, 1, 256, 256) and expr.shape == (1, 53)  # tracked at >= 256
    assert len(surface) == 1 and np.allclose(surface.expressions, expr.numpy()) and np.abs(surface.identity).max() > 0
    assert isinstance(cams, Cameras) and (cams.width, cams.height) == (256, 256)
    # the head centre (world origin) projects near the crop centre, in front of the camera
    uv, z = cams.project(torch.zeros(1, 1, 3))
    assert float(z.reshape(-1)[0]) > 0.3
    assert torch.allclose(uv.reshape(2), torch.tensor([128.0, 128.0]), atol=40.0)
    assert 0.1 < float(masks.mean()) < 0.9  # a head-sized foreground, not empty, not everything


def test_missing_faces_extra_says_what_is_missing(monkeypatch):
    monkeypatch.setitem(sys.modules, "dlib", None)  # `import dlib` now raises ImportError
    monkeypatch.setitem(sys.modules, "mediapipe", None)  # and so does `import mediapipe`
    tracker = PhotoTracker()
    with pytest.raises(ApiError) as e:
        tracker.check_available()
    assert e.value.status == 422 and e.value.code == "cameras_required"
    msg = e.value.message
    assert "'cameras' field is required" in msg and "faces" in msg and "pip install -e '.[faces]'" in msg
    img = torch.rand(3, 32, 32)
    with pytest.raises(ApiError) as e2:  # the tracking call itself answers the same
        tracker.track([img], None, 64)
    assert e2.value.code == "cameras_required"
