"""Unit tests of the server's pieces that need no model: protocol, auth, store, imaging, rate limits."""

from __future__ import annotations

import asyncio
import io
import json
import math
import os
import struct
import time

import numpy as np
import pytest
import torch
from PIL import Image

from fastgha_core.cameras import Cameras, cameras_to_json
from fastgha_core.expressions import get_space
from fastgha_core.model.avatar import CanonicalAvatar
from server import auth
from server.errors import ApiError
from server.frames import fit_camera
from server.imaging import decode_image, decode_mask, encode_jpeg, frame_to_uint8
from server.protocol import (
    FrameRequest,
    OptionsMessage,
    PingMessage,
    ProtocolError,
    pack_binary_request,
    pack_frame,
    parse_binary_message,
    parse_text_message,
    unpack_frame,
)
from server.store import AvatarStore
from server.streaming import LatestSlot, RateLimiter
from server_process import random_avatar

SPACE = get_space("ict53")


def _cam(w=64, h=48):
    return Cameras.look_at((0.2, 0.1, 1.0), fov_deg=25.0, width=w, height=h)[None]


# ---------------------------------------------------------------- protocol
def test_text_frame_vector_and_map():
    vec = [0.0] * SPACE.dim
    vec[3] = 0.5
    r = parse_text_message(json.dumps({"seq": 7, "expression": vec}), SPACE)
    assert isinstance(r, FrameRequest) and r.seq == 7 and r.camera is None
    torch.testing.assert_close(r.expression, torch.tensor(vec))
    name = SPACE.names[5]
    r = parse_text_message(json.dumps({"type": "frame", "seq": 1, "expression": {name: 0.25}}), SPACE)
    assert float(r.expression[5]) == 0.25 and float(r.expression.abs().sum()) == 0.25


def test_text_frame_camera_is_parsed():
    cam = _cam()
    msg = {"seq": 0, "expression": [0.0] * SPACE.dim, "camera": cameras_to_json(cam)[0]}
    r = parse_text_message(json.dumps(msg), SPACE)
    assert (r.camera.width, r.camera.height) == (64, 48)
    torch.testing.assert_close(r.camera.w2c.reshape(4, 4), cam.w2c.reshape(4, 4))


@pytest.mark.parametrize(
    "text, code",
    [
        ("{not json", "invalid_json"),
        ("[1, 2]", "invalid_message"),
        ('{"type": "dance"}', "unknown_message_type"),
        ('{"expression": []}', "invalid_seq"),
        ('{"seq": -1, "expression": []}', "invalid_seq"),
        ('{"seq": true, "expression": []}', "invalid_seq"),
        ('{"seq": 1.5, "expression": []}', "invalid_seq"),
        ('{"seq": 1}', "invalid_expression"),
        ('{"seq": 1, "expression": [1, 2, 3]}', "invalid_expression_length"),
        ('{"seq": 1, "expression": {"notAName": 1}}', "unknown_expression_name"),
        ('{"seq": 1, "expression": "smile"}', "invalid_expression"),
        ('{"seq": 1, "expression": {"jawOpen": NaN}}', "non_finite_number"),
        ('{"seq": 1, "expression": {"jawOpen": Infinity}}', "non_finite_number"),
        ('{"seq": 1, "expression": {"jawOpen": 1e999}}', "non_finite_number"),
        ('{"seq": 1, "expression": {"jawOpen": 1e6}}', "invalid_expression"),
        ('{"seq": 1, "expression": {}, "camera": {"K": 1}}', "invalid_camera"),
        ('{"type": "options", "jpeg_quality": 0}', "invalid_options"),
        ('{"type": "options", "max_size": "big"}', "invalid_options"),
        ('{"type": "options", "colour": 1}', "invalid_options"),
    ],
)
def test_text_errors(text, code):
    with pytest.raises(ProtocolError) as e:
        parse_text_message(text, SPACE)
    assert e.value.code == code, e.value.message


def test_non_finite_in_vector_and_camera():
    vec = ["NaN_PLACEHOLDER"] + [0.0] * (SPACE.dim - 1)
    text = json.dumps({"seq": 1, "expression": vec}).replace('"NaN_PLACEHOLDER"', "NaN")
    with pytest.raises(ProtocolError) as e:
        parse_text_message(text, SPACE)
    assert e.value.code == "non_finite_number"
    cam = cameras_to_json(_cam())[0]
    text = json.dumps({"seq": 1, "expression": {}, "camera": cam}).replace('"width": 64', '"width": 64, "x": -Infinity')
    with pytest.raises(ProtocolError) as e:
        parse_text_message(text, SPACE)
    assert e.value.code == "non_finite_number"


def test_options_and_ping():
    r = parse_text_message('{"type": "options", "jpeg_quality": 40, "max_size": 128}', SPACE)
    assert r == OptionsMessage(40, 128)
    r = parse_text_message('{"type": "ping", "t": 3}', SPACE)
    assert isinstance(r, PingMessage) and r.payload["t"] == 3


def test_binary_request_matches_json_form():
    cam = _cam(80, 60)
    expr = torch.linspace(-1, 1, SPACE.dim)
    for camera in (None, cam):
        data = pack_binary_request(123456, expr, camera)
        b = parse_binary_message(data, SPACE)
        msg = {"seq": 123456, "expression": expr.tolist()}
        if camera is not None:
            msg["camera"] = cameras_to_json(camera)[0]
        j = parse_text_message(json.dumps(msg), SPACE)
        assert b.seq == j.seq == 123456
        torch.testing.assert_close(b.expression, j.expression)
        if camera is None:
            assert b.camera is None
        else:
            assert (b.camera.width, b.camera.height) == (80, 60)
            torch.testing.assert_close(b.camera.K, j.camera.K)
            torch.testing.assert_close(b.camera.w2c, j.camera.w2c)


def test_binary_layout_is_documented_one():
    # b"FGHQ" | uint32 seq | uint16 E | E f32 | uint8 has_camera
    e = SPACE.dim
    data = b"FGHQ" + struct.pack("<IH", 9, e) + struct.pack(f"<{e}f", *([0.5] * e)) + b"\x00"
    r = parse_binary_message(data, SPACE)
    assert r.seq == 9 and torch.allclose(r.expression, torch.full((e,), 0.5))


def test_binary_errors():
    good = pack_binary_request(1, torch.zeros(SPACE.dim), _cam())
    bad_len = pack_binary_request(1, torch.zeros(SPACE.dim + 1))
    nan = pack_binary_request(1, torch.full((SPACE.dim,), float("nan")))
    cases = {
        "invalid_binary": [b"XXXX" + good[4:], good[:-3], good[:10], good + b"\x00"],
        "invalid_expression_length": [bad_len],
        "non_finite_number": [nan],
    }
    for code, blobs in cases.items():
        for blob in blobs:
            with pytest.raises(ProtocolError) as e:
                parse_binary_message(blob, SPACE)
            assert e.value.code == code


def test_frame_message_roundtrip():
    header = {"seq": 5, "render_ms": 1.5, "encode_ms": 0.5, "width": 8, "height": 4, "dropped": 2}
    msg = pack_frame(header, b"\xff\xd8jpeg")
    assert msg[:4] == b"FGHA"
    (n,) = struct.unpack("<I", msg[4:8])
    assert json.loads(msg[8 : 8 + n]) == header
    assert unpack_frame(msg) == (header, b"\xff\xd8jpeg")
    with pytest.raises(ValueError):
        unpack_frame(b"FGHA" + struct.pack("<I", 999) + b"{}")


# ---------------------------------------------------------------- auth
def test_ids_and_tokens():
    ids = {auth.new_avatar_id() for _ in range(50)}
    assert len(ids) == 50 and all(auth.is_valid_avatar_id(i) for i in ids)
    for bad in ("../../etc/passwd", "a" * 21, "a" * 23, "a" * 21 + "/", "a" * 21 + ".", ""):
        assert not auth.is_valid_avatar_id(bad)
        with pytest.raises(ApiError) as e:
            auth.check_avatar_id(bad)
        assert e.value.status == 404
    tok = auth.new_token()
    h = auth.hash_token(tok)
    assert tok not in h and auth.token_matches(tok, h)
    assert not auth.token_matches(auth.new_token(), h)
    assert not auth.token_matches(None, h) and not auth.token_matches("", h)


def test_bearer_and_api_keys():
    assert auth.bearer_from({"authorization": "Bearer abc"}, {"token": "q"}) == "abc"
    assert auth.bearer_from({}, {"token": "q"}) == "q"
    assert auth.bearer_from({"authorization": "Basic xyz"}, {}) is None
    auth.check_api_key({}, [])  # no keys configured: open
    auth.check_api_key({"x-api-key": "k2"}, ["k1", "k2"])
    auth.check_api_key({"authorization": "Bearer k1"}, ["k1", "k2"])
    for headers, code in (({}, "api_key_required"), ({"x-api-key": "nope"}, "invalid_api_key")):
        with pytest.raises(ApiError) as e:
            auth.check_api_key(headers, ["k1"])
        assert e.value.status == 401 and e.value.code == code


# ---------------------------------------------------------------- store


def test_store_lru_budget_reload_delete(tmp_path):
    a = [random_avatar(100, i) for i in range(3)]
    size = a[0].nbytes
    store = AvatarStore(tmp_path, max_bytes=2 * size, ttl_seconds=0, load_fn=CanonicalAvatar.load)
    ids = [auth.new_avatar_id() for _ in a]
    for i, av in zip(ids, a):
        store.put(i, av, {"avatar_id": i, "n": len(av)})
    # budget holds two: the oldest left memory but not disk
    assert store.cached_count == 2 and store.cached_bytes == 2 * size
    assert set(store.disk_ids()) == set(ids)
    item = store.get(ids[0])  # reload on demand, evicting ids[1] (least recently used)
    assert item is not None and item.meta["avatar_id"] == ids[0]
    torch.testing.assert_close(item.avatar.gaussians.means, a[0].gaussians.means)
    torch.testing.assert_close(item.avatar.gaussians.features, a[0].gaussians.features)
    assert store.cached_count == 2
    # a new store on the same folder (a restart) sees everything
    store2 = AvatarStore(tmp_path, max_bytes=10 * size, ttl_seconds=0, load_fn=CanonicalAvatar.load)
    torch.testing.assert_close(store2.get(ids[1]).avatar.gaussians.colors, a[1].gaussians.colors)
    assert store2.delete(ids[1]) and not store2.delete(ids[1])
    assert store2.get(ids[1]) is None and store2.get_meta(ids[1]) is None
    assert not any(p.name.startswith(ids[1]) for p in (tmp_path / "avatars").iterdir())
    assert store.get(ids[1]) is None  # gone from disk for the other instance too, once not cached
    with pytest.raises(ValueError):
        store.get("../../../../etc/passwd")


def test_store_cleans_partial_writes_and_expires(tmp_path):
    store = AvatarStore(tmp_path, max_bytes=1 << 30, ttl_seconds=100, load_fn=CanonicalAvatar.load)
    keep, old, streaming = (auth.new_avatar_id() for _ in range(3))
    for i in (keep, old, streaming):
        store.put(i, random_avatar(10, 0), {"avatar_id": i})
    d = tmp_path / "avatars"
    (d / ".tmp-abc-x.safetensors").write_bytes(b"partial")
    orphan = auth.new_avatar_id()
    (d / f"{orphan}.safetensors").write_bytes(b"uncommitted")
    past = time.time() - 1000
    for i in (old, streaming):
        os.utime(d / f"{i}.json", (past, past))
    assert store.sweep_expired(keep={streaming}) == [old]
    assert store.get(old) is None and store.get(keep) is not None and store.get(streaming) is not None
    AvatarStore(tmp_path, max_bytes=0, ttl_seconds=0, load_fn=CanonicalAvatar.load)  # restart
    names = {p.name for p in d.iterdir()}
    assert not any(n.startswith(".tmp-") for n in names) and f"{orphan}.safetensors" not in names
    assert f"{keep}.json" in names and f"{keep}.safetensors" in names


def test_store_failed_write_leaves_nothing(tmp_path):
    store = AvatarStore(tmp_path, max_bytes=1 << 30, ttl_seconds=0, load_fn=CanonicalAvatar.load)

    class Broken:
        nbytes = 1

        def save(self, path):
            with open(path, "wb") as f:
                f.write(b"half")
            raise OSError("disk full")

    aid = auth.new_avatar_id()
    with pytest.raises(OSError):
        store.put(aid, Broken(), {"avatar_id": aid})
    assert list((tmp_path / "avatars").iterdir()) == [] and store.get_meta(aid) is None


# ---------------------------------------------------------------- imaging
def _encoded(arr: np.ndarray, fmt: str) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format=fmt)
    return buf.getvalue()


def test_decode_png_exact_and_alpha():
    rng = np.random.default_rng(0)
    rgba = rng.integers(0, 256, (12, 20, 4), dtype=np.uint8)
    img, alpha = decode_image(_encoded(rgba, "PNG"), "image 0", 10_000)
    assert img.shape == (3, 12, 20) and alpha.shape == (1, 12, 20)
    torch.testing.assert_close(img, torch.from_numpy(rgba[..., :3]).permute(2, 0, 1).float() / 255)
    torch.testing.assert_close(alpha[0], torch.from_numpy(rgba[..., 3]).float() / 255)
    m = decode_mask(_encoded(rgba[..., 0], "PNG"), "mask 0", 10_000)
    torch.testing.assert_close(m[0], torch.from_numpy(rgba[..., 0]).float() / 255)


def test_decode_refuses_corrupt_and_huge():
    jpeg = _encoded(np.zeros((40, 40, 3), np.uint8), "JPEG")
    for blob in (b"", b"hello", jpeg[: len(jpeg) // 2], _encoded(np.zeros((4, 4, 3), np.uint8), "BMP")):
        with pytest.raises(ApiError) as e:
            decode_image(blob, "image 0", 10_000)
        assert (e.value.status, e.value.code) == (400, "invalid_image")
    with pytest.raises(ApiError) as e:
        decode_image(jpeg, "image 0", 40 * 40 - 1)
    assert (e.value.status, e.value.code) == (413, "image_too_large")


def test_jpeg_encode_roundtrip():
    rgb = torch.zeros(3, 30, 50)
    rgb[0, :, :25] = 1.0
    rgb[2, :, 25:] = 0.5
    frame = frame_to_uint8(rgb)
    assert frame.shape == (30, 50, 3) and frame.dtype == np.uint8 and frame.flags.c_contiguous
    np.testing.assert_array_equal(frame[0, 0], [255, 0, 0])
    np.testing.assert_array_equal(frame[0, -1], [0, 0, 128])
    dec = np.asarray(Image.open(io.BytesIO(encode_jpeg(frame, 95))))
    assert dec.shape == (30, 50, 3)
    assert np.abs(dec[5:-5, 5:20].astype(int) - [255, 0, 0]).max() < 12
    assert np.abs(dec[5:-5, 30:-5].astype(int) - [0, 0, 128]).max() < 12


def test_fit_camera_keeps_aspect_and_scales_K():
    cam = _cam(400, 200)
    f = fit_camera(cam, 100)
    assert (f.width, f.height) == (100, 50)
    torch.testing.assert_close(f.K[..., :2, :], cam.K[..., :2, :] * 0.25)
    assert fit_camera(cam, 400) is cam


# ---------------------------------------------------------------- latest-wins and rate limits
def test_latest_slot_keeps_newest_and_counts_drops():
    async def go():
        slot = LatestSlot()
        for i in range(5):
            slot.put(i)
        first = await slot.take()
        slot.put(10)
        second = await slot.take()
        return first, second, slot.dropped

    assert asyncio.run(go()) == (4, 10, 4)


def test_rate_limiter():
    now = [0.0]
    rl = RateLimiter(rate=10, abuse_factor=3, clock=lambda: now[0])
    verdicts = [rl.hit() for _ in range(10)]
    assert verdicts == ["ok"] * 10
    assert rl.hit() == "limited"
    now[0] += 0.5  # 5 tokens refill
    assert [rl.hit() for _ in range(6)].count("ok") == 5
    now[0] += 0.6  # new window
    out = [rl.hit() for _ in range(31)]
    assert out[-1] == "abuse" and "abuse" not in out[:30]
    assert math.isclose(rl.abuse_limit, 30)


# ---------------------------------------------------------------- settings and CLI
def test_settings_from_env_and_serve_flags(monkeypatch, tmp_path):
    from fastgha_core.cli import build_parser, main
    from server.settings import Settings, get_settings

    monkeypatch.setenv("FASTGHA_API_KEYS", " a, b ,")
    monkeypatch.setenv("FASTGHA_MAX_IMAGES", "3")
    monkeypatch.setenv("FASTGHA_DATA_DIR", str(tmp_path))
    s = get_settings()
    assert s.api_key_list == ["a", "b"] and s.max_images == 3 and s.data_dir == tmp_path
    assert s.cors_origin_list == [] and Settings(max_images=5).max_images == 5  # explicit values win over env
    args = build_parser().parse_args(["serve", "--port", "9001", "--model", "tiny", "--data-dir", str(tmp_path)])
    assert (args.port, args.model, args.data_dir, args.host) == (9001, "tiny", str(tmp_path), "127.0.0.1")
    assert main(["serve", "--model", "no-such-model"]) == 2
    assert main(["serve", "--port", "0"]) == 2


@pytest.mark.parametrize("stmt", ["import server.app", "from server.protocol import unpack_frame"])
def test_server_imports_set_openmp_defaults_before_torch(stmt):
    """Importing the server (plain uvicorn, or the protocol helpers as in docs/protocol.md) applies
    fastgha_core's OpenMP defaults before torch loads: GOMP_SPINCOUNT is set and no warning says
    it came too late."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[1])
    code = f"{stmt}\nimport os, torch; print(os.environ.get('GOMP_SPINCOUNT'))"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "10000"
    assert "ran after torch was imported" not in r.stderr, r.stderr


def test_multipart_boundary_is_read_without_a_deprecation_warning():
    """Every upload's boundary is read through python-multipart's own module name; the old
    ``multipart`` alias warned (PendingDeprecationWarning) into the server log and every test run."""
    import warnings

    from server.app import _boundary

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _boundary('multipart/form-data; boundary="ab-12"') == b"ab-12"
        assert _boundary("multipart/form-data") is None


def test_binary_request_sizes_are_the_ones_docs_protocol_md_gives():
    """docs/protocol.md states the compact request's total sizes; they are what
    ``pack_binary_request`` builds and the server parses (it said 115 more bytes with a camera, not 104)."""
    import re
    from pathlib import Path

    from fastgha_core.cameras import orbit_cameras

    text = (Path(__file__).resolve().parents[1] / "docs" / "protocol.md").read_text(encoding="utf-8")
    m = re.search(r"Total 11 \+ 4·E bytes without a camera \((\d+) for `ict53`\), (\d+) more with one", text)
    assert m, "the sentence giving the binary request's sizes"
    e = SPACE.dim
    bare = pack_binary_request(3, [0.0] * e)
    with_cam = pack_binary_request(3, [0.0] * e, orbit_cameras(1, width=96, height=80))
    assert len(bare) == 11 + 4 * e == int(m.group(1))
    assert len(with_cam) - len(bare) == int(m.group(2))
    assert parse_binary_message(with_cam, SPACE).camera.width == 96


@pytest.mark.parametrize(("ctype", "got"), [("", "got no Content-Type"), ("application/json", "got Content-Type 'application/json'")])
def test_a_creation_that_is_not_multipart_says_what_to_send(ctype, got):
    """``curl -X POST .../v1/avatars`` (no body) was answered "expected multipart/form-data, got ''"."""
    from types import SimpleNamespace

    from server.app import _parse_form

    request = SimpleNamespace(headers={"content-type": ctype} if ctype else {})
    with pytest.raises(ApiError) as e:
        asyncio.run(_parse_form(request, SimpleNamespace(max_upload_bytes=1024)))
    assert e.value.status == 415 and e.value.code == "invalid_multipart"
    assert e.value.message.endswith(got) and "'images'" in e.value.message and "curl -F images=@me.jpg" in e.value.message


def test_an_oversized_upload_names_the_setting_and_what_to_do():
    """A 60 MB upload was answered "upload of 60000174 bytes exceeds the limit of 33554432": no unit,
    nothing for the user to do, nothing for the operator to change."""
    from types import SimpleNamespace

    from server.app import _read_body

    async def chunks():
        yield b"x" * 600
        yield b"x" * 600

    for headers in ({"content-length": "2000"}, {}):  # declared too long, or found too long while reading
        request = SimpleNamespace(headers=headers, stream=chunks)
        with pytest.raises(ApiError) as e:
            asyncio.run(_read_body(request, 1000))
        assert (e.value.status, e.value.code) == (413, "upload_too_large")
        assert "limit of 1000 bytes" in e.value.message and "FASTGHA_MAX_UPLOAD_BYTES" in e.value.message, e.value.message
