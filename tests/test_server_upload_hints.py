"""What a hand-written upload gets told when its parts are misnamed (``curl -F image=@me.jpg``):
the 400 names the parts it did get. In process: ``create_app`` under Starlette's ``TestClient``
with the 64 x 64 tiny test model."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from server_process import make_model_dir

pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    from starlette.testclient import TestClient

    from server.app import create_app
    from server.settings import Settings

    model = make_model_dir(tmp_path_factory.mktemp("model"))
    s = Settings(model=str(model), data_dir=tmp_path_factory.mktemp("data"), warmup=False, compile="off", mlp_precision="fp32")
    with TestClient(create_app(s)) as c:
        yield c


def _png() -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.full((32, 32, 3), 128, np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def test_misnamed_photo_parts_are_named_in_the_error(client):
    r = client.post("/v1/avatars", files=[("image", ("me.png", _png(), "image/png")), ("photo", ("you.png", _png(), "image/png"))])
    assert r.status_code == 400 and r.json()["error"]["code"] == "invalid_image_count", r.text
    msg = r.json()["error"]["message"]
    assert "got 0" in msg and "'image'" in msg and "'photo'" in msg and "name each photo's part 'images'" in msg, msg


def test_a_missing_photo_with_only_known_parts_keeps_the_plain_message(client):
    r = client.post("/v1/avatars", files=[("masks", ("m.png", _png(), "image/png"))], data={"cameras": "[]"})
    assert r.status_code == 400 and r.json()["error"]["code"] == "invalid_image_count", r.text
    assert "name each photo" not in r.json()["error"]["message"]
