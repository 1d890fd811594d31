"""End-to-end tests of the server: a real uvicorn process on 127.0.0.1 and a real websockets client.

One server process is shared by the module. The model is a `tiny`-architecture model whose
deformation output layer is given small random weights (a freshly initialised one is the
identity, so expressions would not change the picture) and whose input is 64 x 64, so
that frames are cheap on two CPU cores.
"""

from __future__ import annotations

import contextlib
import io
import json
import signal
from pathlib import Path

import httpx
import numpy as np
import pytest
import torch
from PIL import Image
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from fastgha_core.cameras import Cameras, cameras_to_json, load_request_folder, orbit_cameras
from server.protocol import pack_binary_request, unpack_frame
from server_process import ServerProcess as _ServerProcess

pytestmark = pytest.mark.timeout(300)

REPO = Path(__file__).resolve().parent.parent
API_KEY = "test-api-key"
MAX_WS_BYTES = 16384
MAX_UPLOAD = 4 * 1024 * 1024
MAX_PIXELS = 1024 * 1024
OUT_W, OUT_H = 48, 40


# ---------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    from fastgha_core.config import get_preset
    from fastgha_core.model.fastgha import FastGHA

    cfg = get_preset("tiny")
    cfg.input_size = 64
    cfg.render_size = 64
    torch.manual_seed(0)
    model = FastGHA(cfg)
    with torch.no_grad():
        model.deform.out.weight.normal_(0.0, 0.2)
    d = tmp_path_factory.mktemp("model")
    model.save_pretrained(d)
    return d


def ServerProcess(model_dir: Path, data_dir: Path, log_path: Path, warmup: bool = True, fast_mlp: bool = False) -> _ServerProcess:
    """The shared test server (``tests/server_process.py``) with this module's keys and limits.

    ``fast_mlp``: the deformation MLP in bf16 and compiled (``torch.compile`` at start-up), the
    production path on CPUs with AVX512-BF16 and a C++ compiler."""
    return _ServerProcess(
        model_dir, data_dir, None, log_path,
        FASTGHA_WARMUP="true" if warmup else "false",
        FASTGHA_MLP_PRECISION="bf16" if fast_mlp else "fp32",
        FASTGHA_COMPILE="on" if fast_mlp else "off",
        FASTGHA_API_KEYS=f"other-key,{API_KEY}",
        FASTGHA_MAX_UPLOAD_BYTES=str(MAX_UPLOAD),
        FASTGHA_MAX_IMAGE_PIXELS=str(MAX_PIXELS),
        FASTGHA_MAX_OUTPUT_SIZE="96",
        FASTGHA_WS_MAX_MESSAGE_BYTES=str(MAX_WS_BYTES),
        FASTGHA_MAX_STREAMS_PER_AVATAR="3",
    )  # fmt: skip


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("data")


@pytest.fixture(scope="module")
def server(model_dir, data_dir, tmp_path_factory):
    srv = ServerProcess(model_dir, data_dir, tmp_path_factory.mktemp("logs") / "server.log", fast_mlp=True)
    yield srv
    srv.stop()


def _jpeg(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="JPEG", quality=90)
    return buf.getvalue()


def _request_parts(num: int | None = None):
    """(files, cameras JSON) from a shipped sample request folder, or synthesised ones."""
    folders = sorted((REPO / "fastgha_core" / "assets" / "samples").glob("*/request"))
    if folders:
        paths, cams = load_request_folder(folders[0])
        paths, cams = paths[:num] if num else paths, cams[:num] if num else cams
        blobs = [p.read_bytes() for p in paths]
        cam_json = [cameras_to_json(c)[0] for c in cams]
    else:
        n = num or 4
        cams = orbit_cameras(n, width=96, height=72)
        rng = np.random.default_rng(1)
        blobs = []
        for _ in range(n):
            img = np.full((72, 96, 3), 255, np.uint8)
            img[12:60, 28:68] = rng.integers(60, 200, 3, dtype=np.uint8)  # a face-sized blob on white
            img = np.clip(img.astype(int) + rng.integers(-20, 20, img.shape), 0, 255).astype(np.uint8)
            blobs.append(_jpeg(img))
        cam_json = cameras_to_json(cams)
    files = [("images", (f"{i}.jpg", b, "image/jpeg")) for i, b in enumerate(blobs)]
    return files, cam_json


def _create(server, num: int | None = None, key: str = API_KEY) -> httpx.Response:
    files, cams = _request_parts(num)
    return httpx.post(
        server.base + "/v1/avatars", files=files, data={"cameras": json.dumps(cams)}, headers={"X-API-Key": key}, timeout=120
    )


@pytest.fixture(scope="module")
def avatar(server) -> dict:
    r = _create(server)
    assert r.status_code == 201, r.text
    return r.json()


@pytest.fixture(scope="module")
def other_avatar(server) -> dict:
    r = _create(server, num=1)
    assert r.status_code == 201, r.text
    return r.json()


def _ws(server, av, token: str | None = "own", **kw):
    tok = av["token"] if token == "own" else token
    url = f"{server.ws_base}/v1/avatars/{av['avatar_id']}/stream" + (f"?token={tok}" if tok else "")
    return connect(url, open_timeout=30, close_timeout=5, **kw)


def _camera(w=OUT_W, h=OUT_H, x=0.0) -> dict:
    return cameras_to_json(Cameras.look_at((x, 0.0, 1.0), fov_deg=20.0, width=w, height=h))[0]


def _recv_frame(ws, timeout=60.0):
    """The next binary frame (text messages are returned as dicts in the second slot)."""
    msg = ws.recv(timeout=timeout)
    if isinstance(msg, str):
        return None, json.loads(msg)
    header, jpeg = unpack_frame(msg)
    return header, jpeg


def _decode(jpeg: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB")).astype(np.float32)


def _close_code(ws) -> int:
    with pytest.raises(ConnectionClosed) as e:
        for _ in range(10):
            ws.recv(timeout=30)
    return e.value.rcvd.code if e.value.rcvd is not None else -1


def _error(r: httpx.Response, status: int, code: str) -> None:
    assert r.status_code == status, r.text
    body = r.json()
    assert set(body) == {"error"} and body["error"]["code"] == code, body
    assert isinstance(body["error"]["message"], str) and body["error"]["message"]


# ---------------------------------------------------------------- HTTP basics
def test_health_model_docs(server):
    from fastgha_core.perf import cpp_compiler

    health = httpx.get(server.base + "/healthz").json()
    assert health["status"] == "ok"
    # the module's server asked for a bf16, compiled MLP; compiling needs a C++ compiler, else it runs eagerly
    mlp = health["mlp"]
    assert (mlp["precision"], mlp["compiled"]) == ("bf16", cpp_compiler() is not None), health
    assert mlp["choice"]["precision"] == "bf16" and mlp["choice"]["reason"] == "configured", health
    m = httpx.get(server.base + "/v1/model").json()
    assert m["expression_space"] == "ict53" and m["expression_dim"] == len(m["expression_names"]) == 53
    assert m["input_size"] == [64, 64] and m["output_size"] == [64, 64]
    assert httpx.get(server.base + "/openapi.json").json()["paths"]["/v1/avatars"]["post"]
    assert httpx.get(server.base + "/docs").status_code == 200
    _error(httpx.get(server.base + "/v1/nothing"), 404, "not_found")


def test_create_and_read_metadata_and_ply(server, avatar, data_dir):
    from plyfile import PlyData

    # the original fields, what the frames are made with (server/avatar_info.py) and the refinement's time
    # (photos with cameras are refined by default: FASTGHA_REFINE_STEPS=auto); nothing else
    assert set(avatar) == {"avatar_id", "token", "num_gaussians", "reconstruction_ms", "expression_space",
                           "same_person", "view_blend", "expression_prior", "refining_ms"}  # fmt: skip
    assert avatar["refining_ms"] > 0
    assert avatar["num_gaussians"] > 0 and avatar["expression_space"] == "ict53"
    h = {"Authorization": f"Bearer {avatar['token']}"}
    meta = httpx.get(f"{server.base}/v1/avatars/{avatar['avatar_id']}", headers=h).json()
    assert meta["avatar_id"] == avatar["avatar_id"] and meta["num_gaussians"] == avatar["num_gaussians"]
    assert "token_sha256" not in meta and avatar["token"] not in json.dumps(meta)
    r = httpx.get(f"{server.base}/v1/avatars/{avatar['avatar_id']}/ply", params={"token": avatar["token"]}, timeout=60)
    assert r.status_code == 200
    ply = PlyData.read(io.BytesIO(r.content))
    names = [p.name for p in ply["vertex"].properties]
    assert names[:3] == ["x", "y", "z"] and {"f_dc_0", "opacity", "scale_0", "rot_0"} <= set(names)
    from fastgha_core.io import drop_outliers
    from fastgha_core.model.avatar import CanonicalAvatar

    stored = CanonicalAvatar.load(data_dir / "avatars" / f"{avatar['avatar_id']}.safetensors").gaussians
    assert len(stored) == avatar["num_gaussians"]
    assert ply["vertex"].count == avatar["num_gaussians"] - drop_outliers(stored)[1]  # stray Gaussians dropped (docs/protocol.md)
    # nothing but committed files in the data folder, and the token is not stored in clear
    files = sorted(p.name for p in (data_dir / "avatars").iterdir())
    assert f"{avatar['avatar_id']}.json" in files and f"{avatar['avatar_id']}.safetensors" in files
    assert avatar["token"] not in (data_dir / "avatars" / f"{avatar['avatar_id']}.json").read_text()


# ---------------------------------------------------------------- streaming
def test_stream_100_frames_and_expressions_change_the_picture(server, avatar):
    names = httpx.get(server.base + "/v1/model").json()["expression_names"]
    with _ws(server, avatar) as ws:
        ready = json.loads(ws.recv(timeout=30))
        assert ready["type"] == "ready" and ready["avatar_id"] == avatar["avatar_id"]
        assert ready["expression_dim"] == 53 and ready["expression_names"] == names
        assert (ready["width"], ready["height"]) == (64, 64)
        h = {"Authorization": f"Bearer {avatar['token']}"}
        meta = httpx.get(f"{server.base}/v1/avatars/{avatar['avatar_id']}", headers=h).json()
        # what the frames are made with, as GET /v1/avatars/{id} says (server/avatar_info.py)
        assert ready["view_blend"] == meta["view_blend"] and ready["expression_prior"] == meta["expression_prior"]
        frames = {}
        for i in range(100):
            expr = [0.0] * 53 if i % 2 == 0 else {"jawOpen": 1.0, "mouthSmile_L": 1.0, "eyeBlink_R": 1.0}
            req = {"seq": i, "expression": expr}
            if i == 0:
                req["camera"] = _camera()  # sticky from here on
            if i % 3 == 0 and i > 0:  # every third request in the compact binary form
                ws.send(pack_binary_request(i, [0.0] * 53) if i % 2 == 0 else json.dumps(req))
            else:
                ws.send(json.dumps(req))
            header, jpeg = _recv_frame(ws)
            assert header is not None, jpeg
            assert header["seq"] == i and (header["width"], header["height"]) == (OUT_W, OUT_H)
            assert header["dropped"] == 0 and header["render_ms"] >= 0 and header["encode_ms"] >= 0
            img = _decode(jpeg)
            assert img.shape == (OUT_H, OUT_W, 3)
            frames[i] = img
    neutral_a, neutral_b, expressive = frames[0], frames[98], frames[1]
    same = np.abs(neutral_a - neutral_b).mean()
    diff = np.abs(neutral_a - expressive).mean()
    assert same < 0.5 and diff > 1.0, (same, diff)
    np.testing.assert_allclose(frames[1], frames[99], atol=1.0)


def test_camera_options_ping_and_size_cap(server, avatar):
    with _ws(server, avatar) as ws:
        json.loads(ws.recv(timeout=30))
        ws.send(json.dumps({"type": "ping", "t": 42}))
        assert json.loads(ws.recv(timeout=30)) == {"type": "pong", "t": 42}
        ws.send(json.dumps({"type": "options", "jpeg_quality": 30, "max_size": 500}))
        assert json.loads(ws.recv(timeout=30)) == {"type": "options", "jpeg_quality": 30, "max_size": 96}
        ws.send(json.dumps({"seq": 1, "expression": {}, "camera": _camera(400, 200)}))  # capped to 96 x 48
        header, jpeg = _recv_frame(ws)
        assert (header["width"], header["height"]) == (96, 48) and _decode(jpeg).shape == (48, 96, 3)
        ws.send(json.dumps({"type": "options", "max_size": 32}))
        json.loads(ws.recv(timeout=30))
        ws.send(json.dumps({"seq": 2, "expression": {}}))  # the camera is sticky, the cap applies
        header, jpeg = _recv_frame(ws)
        assert (header["width"], header["height"]) == (32, 16) and _decode(jpeg).shape == (16, 32, 3)


def test_latest_wins_under_flood(server, avatar):
    n = 150
    with _ws(server, avatar) as ws:
        json.loads(ws.recv(timeout=30))
        for i in range(n):
            ws.send(json.dumps({"seq": i, "expression": [i / n] * 53, "camera": _camera(32, 32) if i == 0 else None}))
        seqs, last = [], None
        while not seqs or seqs[-1] != n - 1:
            header, jpeg = _recv_frame(ws)
            assert header is not None, jpeg
            seqs.append(header["seq"])
            last = header
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert len(seqs) < n and last["dropped"] > 0
    assert last["dropped"] + len(seqs) == n  # every request was either rendered or counted as dropped


def test_two_streams_at_once_are_independent(server, avatar, other_avatar):
    with _ws(server, avatar) as a, _ws(server, other_avatar) as b:
        json.loads(a.recv(timeout=30)), json.loads(b.recv(timeout=30))
        a.send(json.dumps({"seq": 1, "expression": [1.0] * 3}))  # bad on a ...
        b.send(json.dumps({"seq": 7, "expression": {}, "camera": _camera(24, 24)}))  # ... good on b
        _, err = _recv_frame(a)
        assert err["type"] == "error" and err["code"] == "invalid_expression_length"
        header, _ = _recv_frame(b)
        assert header["seq"] == 7 and header["width"] == 24


# ---------------------------------------------------------------- auth
def test_auth_refusals_http(server, avatar, other_avatar):
    aid = avatar["avatar_id"]
    for method, path in (("GET", ""), ("GET", "/ply"), ("DELETE", "")):
        url = f"{server.base}/v1/avatars/{aid}{path}"
        _error(httpx.request(method, url), 401, "token_required")
        _error(httpx.request(method, url, headers={"Authorization": "Bearer nope"}), 403, "invalid_token")
        _error(httpx.request(method, url, params={"token": other_avatar["token"]}), 403, "invalid_token")
    _error(_create(server, num=1, key=""), 401, "api_key_required")
    _error(_create(server, num=1, key="wrong"), 401, "invalid_api_key")
    assert httpx.get(f"{server.base}/v1/avatars/{aid}", params={"token": avatar["token"]}).status_code == 200


def test_auth_refusals_ws(server, avatar, other_avatar):
    for token in (None, "wrong-token", other_avatar["token"]):
        with _ws(server, avatar, token=token) as ws:
            assert _close_code(ws) == 4401
    bogus = {"avatar_id": "A" * 22, "token": avatar["token"]}
    with _ws(server, bogus) as ws:
        assert _close_code(ws) == 4404
    assert server.alive()


# ---------------------------------------------------------------- bad inputs
def _multipart(files, fields, boundary=b"testboundary1234"):
    out = []
    for name, value in fields.items():
        out.append(b"--" + boundary + b'\r\nContent-Disposition: form-data; name="' + name.encode() + b'"\r\n\r\n' + value + b"\r\n")
    for name, (fname, data, ctype) in files:
        out.append(
            b"--" + boundary + b'\r\nContent-Disposition: form-data; name="' + name.encode() + b'"; filename="'
            + fname.encode() + b'"\r\nContent-Type: ' + ctype.encode() + b"\r\n\r\n" + data + b"\r\n"
        )  # fmt: skip
    out.append(b"--" + boundary + b"--\r\n")
    return b"".join(out), f"multipart/form-data; boundary={boundary.decode()}"


def test_bad_uploads_get_their_error(server):
    files, cams = _request_parts(2)
    post = lambda **kw: httpx.post(server.base + "/v1/avatars", headers={"X-API-Key": API_KEY, **kw.pop("headers", {})}, timeout=60, **kw)  # noqa: E731
    cj = json.dumps(cams)
    # corrupt image
    bad = [files[0], ("images", ("x.jpg", files[1][1][1][:200], "image/jpeg"))]
    _error(post(files=bad, data={"cameras": cj}), 400, "invalid_image")
    _error(post(files=[("images", ("x.png", b"not an image at all", "image/png"))], data={"cameras": json.dumps(cams[:1])}), 400, "invalid_image")
    # truncated multipart body
    body, ctype = _multipart(files, {"cameras": cj.encode()})
    _error(post(content=body[: len(body) // 2], headers={"Content-Type": ctype}), 400, "invalid_multipart")
    _error(post(content=b"garbage", headers={"Content-Type": "multipart/form-data"}), 400, "invalid_multipart")
    _error(post(json={"images": []}), 415, "invalid_multipart")
    # wrong cameras JSON
    for bad_cams in ("{not json", "[]", json.dumps([{"K": [[1, 0], [0, 1]], "w2c": cams[0]["w2c"], "width": 96, "height": 72}] * 2),
                     json.dumps([{"w2c": cams[0]["w2c"]}] * 2), json.dumps([{**c, "width": "wide"} for c in cams])):  # fmt: skip
        _error(post(files=files, data={"cameras": bad_cams}), 400, "invalid_cameras")
    # no cameras: the server tracks the photos (faces extra) or says cameras are required
    r = post(files=files)
    assert r.status_code == 422 and r.json()["error"]["code"] in ("no_face", "cameras_required"), r.text
    # non-finite numbers
    nan_cams = cj.replace(json.dumps(cams[0]["K"][0][0]), "NaN", 1)
    _error(post(files=files, data={"cameras": nan_cams}), 400, "non_finite_number")
    # mismatched counts and sizes
    _error(post(files=files, data={"cameras": json.dumps(cams[:1])}), 400, "camera_count_mismatch")
    _error(post(files=files, data={"cameras": json.dumps(cams + cams[:1])}), 400, "camera_count_mismatch")
    _error(post(files=files + [("masks", ("m.png", files[0][1][1], "image/jpeg"))], data={"cameras": cj}), 400, "mask_count_mismatch")
    _error(post(files=files * 5, data={"cameras": json.dumps(cams * 5)}), 400, "invalid_image_count")
    body0, ctype0 = _multipart([], {"cameras": b"[]"})
    _error(post(content=body0, headers={"Content-Type": ctype0}), 400, "invalid_image_count")
    small = [{**c, "width": 50} for c in cams]
    _error(post(files=files, data={"cameras": json.dumps(small)}), 400, "camera_size_mismatch")
    # limits
    big = _jpeg(np.zeros((1000, 1100, 3), np.uint8))  # small file, too many pixels
    big_cam = [{**cams[0], "width": 1100, "height": 1000}]
    _error(post(files=[("images", ("b.jpg", big, "image/jpeg"))], data={"cameras": json.dumps(big_cam)}), 413, "image_too_large")
    _error(post(content=b"x" * (MAX_UPLOAD + 1), headers={"Content-Type": ctype}), 413, "upload_too_large")
    assert server.alive()


def test_unknown_and_malformed_avatar_ids(server, avatar):
    for aid in ("A" * 22, "a" * 23, "short", "....................ab"):
        r = httpx.get(f"{server.base}/v1/avatars/{aid}", params={"token": avatar["token"]})
        _error(r, 404, "avatar_not_found")
    for path in (f"..%2F..%2F{avatar['avatar_id']}", "..%2F..%2Fetc%2Fpasswd", "%2E%2E%2F" * 3 + "abcdefghijklm"):
        r = httpx.get(f"{server.base}/v1/avatars/{path}", params={"token": avatar["token"]})
        assert r.status_code == 404 and r.json()["error"]["code"] in ("avatar_not_found", "not_found")
    assert server.alive()


def test_bad_ws_messages_keep_the_socket_open(server, avatar):
    bad = [
        ("{not json", "invalid_json"),
        (json.dumps({"seq": 1, "expression": [0.0] * 52}), "invalid_expression_length"),
        (json.dumps({"seq": 1, "expression": {"notAnExpression": 1.0}}), "unknown_expression_name"),
        ('{"seq": 1, "expression": {"jawOpen": NaN}}', "non_finite_number"),
        ('{"seq": 1, "expression": [' + ",".join(["1e999"] * 53) + "]}", "non_finite_number"),
        (json.dumps({"seq": 1, "expression": {}, "camera": {"K": [[1]], "w2c": [], "width": 4, "height": 4}}), "invalid_camera"),
        (json.dumps({"seq": "one", "expression": {}}), "invalid_seq"),
        (json.dumps({"type": "rewind"}), "unknown_message_type"),
        (json.dumps({"type": "options", "jpeg_quality": 1000}), "invalid_options"),
        (b"FGHQ\x01", "invalid_binary"),
        (pack_binary_request(1, [0.0] * 10), "invalid_expression_length"),
        (pack_binary_request(1, [float("inf")] * 53), "non_finite_number"),
    ]
    with _ws(server, avatar) as ws:
        json.loads(ws.recv(timeout=30))
        for msg, code in bad:
            ws.send(msg)
            header, err = _recv_frame(ws)
            assert header is None and err == {"type": "error", "code": code, "message": err["message"]}, (msg, err)
        ws.send(json.dumps({"seq": 5, "expression": {}, "camera": _camera(16, 16)}))
        header, jpeg = _recv_frame(ws)
        assert header["seq"] == 5 and _decode(jpeg).shape == (16, 16, 3)
    # a message over the size limit closes with 1009, and the server carries on
    with _ws(server, avatar, max_size=None) as ws:
        json.loads(ws.recv(timeout=30))
        ws.send(json.dumps({"seq": 1, "expression": {}, "pad": "x" * (2 * MAX_WS_BYTES)}))
        assert _close_code(ws) == 1009
    assert server.alive()


def test_stream_limits_per_avatar(server, other_avatar):
    with contextlib.ExitStack() as stack:
        socks = [stack.enter_context(_ws(server, other_avatar)) for _ in range(3)]
        for s in socks:
            assert json.loads(s.recv(timeout=30))["type"] == "ready"
        with _ws(server, other_avatar) as extra:
            assert _close_code(extra) == 4503
    with _ws(server, other_avatar) as again:  # closed streams free their slots
        assert json.loads(again.recv(timeout=30))["type"] == "ready"


def test_metrics(server, avatar):
    text = httpx.get(server.base + "/metrics").text
    values = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            name, _, v = line.rpartition(" ")
            values[name] = float(v)
    assert values["fastgha_frames_rendered_total"] >= 100
    assert values["fastgha_frames_dropped_total"] > 0
    assert values["fastgha_render_seconds_count"] >= 100 and values["fastgha_encode_seconds_count"] >= 100
    assert values["fastgha_cached_avatars"] >= 1 and values["fastgha_cached_avatar_bytes"] > 0
    assert "fastgha_active_streams" in values


# ---------------------------------------------------------------- lifecycle (last: they stop the server)
def test_delete(server, data_dir):
    r = _create(server, num=1)
    av = r.json()
    h = {"Authorization": f"Bearer {av['token']}"}
    with _ws(server, av) as ws:
        json.loads(ws.recv(timeout=30))
        assert httpx.delete(f"{server.base}/v1/avatars/{av['avatar_id']}", headers=h).status_code == 204
        assert _close_code(ws) == 4404  # open streams of a deleted avatar end
    _error(httpx.get(f"{server.base}/v1/avatars/{av['avatar_id']}", headers=h), 404, "avatar_not_found")
    assert not list((data_dir / "avatars").glob(f"{av['avatar_id']}*"))
    with _ws(server, av) as ws2:
        assert _close_code(ws2) == 4404


def test_kill_restart_and_graceful_shutdown(server, avatar, model_dir, data_dir, tmp_path):
    server.stop(signal.SIGKILL)  # a crash: nothing gets to flush
    srv = ServerProcess(model_dir, data_dir, tmp_path / "restart.log", warmup=False)
    try:
        with _ws(srv, avatar) as ws:
            assert json.loads(ws.recv(timeout=30))["type"] == "ready"
            ws.send(json.dumps({"seq": 3, "expression": {"jawOpen": 0.5}, "camera": _camera(20, 20)}))
            header, jpeg = _recv_frame(ws)
            assert header["seq"] == 3 and _decode(jpeg).shape == (20, 20, 3)
            # graceful shutdown closes open streams with a code, and the process exits cleanly
            srv.proc.send_signal(signal.SIGTERM)
            assert _close_code(ws) in (1001, 1012)
        assert srv.proc.wait(timeout=30) in (0, -signal.SIGTERM)  # uvicorn re-raises the signal after a clean exit
    finally:
        srv.stop()
    assert "Application shutdown complete" in (tmp_path / "restart.log").read_text()
    assert not [p for p in (data_dir / "avatars").iterdir() if p.name.startswith(".tmp-")]
