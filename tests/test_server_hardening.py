"""Hardening tests without a server process (issue 18, items 2-12): hostile numbers in JSON,
cameras that pass the schema but cannot be rendered, the log throttle, the store's disk-full and
corrupt-file paths, the security middleware, the API-key file and the Dockerfiles' proxy trust.

The raw-socket tests against a real uvicorn process are in ``tests/test_server_hardening_e2e.py``.
"""

from __future__ import annotations

import errno
import json
import logging
from pathlib import Path

import pytest
import torch

from fastgha_core.cameras import Cameras, cameras_to_json
from fastgha_core.expressions import get_space
from fastgha_core.model.avatar import CanonicalAvatar
from server.protocol import ProtocolError, pack_binary_request, parse_binary_message, parse_cameras_json, parse_text_message
from server_process import random_avatar

SPACE = get_space("ict53")
REPO = Path(__file__).resolve().parent.parent
BIG_INT = "1" + "0" * 400  # an integer literal of 401 digits (overflows float64)


def _cam_json(w=64, h=48, z=1.0) -> dict:
    return cameras_to_json(Cameras.look_at((0.0, 0.0, z), fov_deg=25.0, width=w, height=h))[0]


def _frame(**kw) -> dict:
    return {"seq": 1, "expression": {}, **kw}


def _code(text: str) -> str:
    with pytest.raises(ProtocolError) as e:
        parse_text_message(text, SPACE)
    return e.value.code


# ---------------------------------------------------------------- item 4: WebSocket numbers
def test_seq_of_5000_digits_is_a_typed_error():
    # json.loads raises ValueError (int-string conversion limit, 4300 digits) before our code sees it
    assert _code('{"seq": ' + "7" * 5000 + ', "expression": {}}') == "non_finite_number"
    assert _code('{"seq": ' + "7" * 400 + ', "expression": {}}') == "non_finite_number"
    assert _code('{"seq": 4294967296, "expression": {}}') == "invalid_seq"


@pytest.mark.parametrize("literal", [BIG_INT, "-" + BIG_INT, "1" * 5000, "340282356779733661637539395458142568448", "1e39", "-3.5e38"])
def test_numbers_beyond_float32_are_non_finite(literal):
    """Integer or float literals whose value overflows float32, anywhere in a message."""
    assert _code('{"seq": 1, "expression": {"jawOpen": ' + literal + "}}") == "non_finite_number"
    vec = "[" + ",".join([literal] + ["0"] * (SPACE.dim - 1)) + "]"
    assert _code('{"seq": 1, "expression": ' + vec + "}") == "non_finite_number"
    cam = json.dumps(_frame(camera=_cam_json())).replace('"width": 64', '"width": ' + literal)
    assert _code(cam) == "non_finite_number"
    k = _cam_json()
    text = json.dumps(_frame(camera=k)).replace(json.dumps(k["K"][0][0]), literal, 1)
    assert _code(text) == "non_finite_number"
    assert _code('{"type": "ping", "t": ' + literal + "}") == "non_finite_number"


def test_camera_width_10_to_309_and_huge_sizes():
    for w in ("1" + "0" * 309, "1" + "0" * 30, "70000"):
        text = json.dumps(_frame(camera=_cam_json())).replace('"width": 64', '"width": ' + w)
        assert _code(text) in ("non_finite_number", "invalid_camera"), w
    # float32-representable but absurd sizes are refused as a camera error, not left to the renderer
    text = json.dumps(_frame(camera=_cam_json())).replace('"width": 64', '"width": 1000000000000000000000000000000')
    assert _code(text) == "invalid_camera"


# ---------------------------------------------------------------- item 2: cameras that pass the schema
def _cam_variants():
    """Camera objects that pass the JSON schema (3x3 K, rigid w2c, int sizes) but are not pinhole cameras
    the renderer can use."""
    base = _cam_json()
    out = []
    k = json.loads(json.dumps(base))
    k["K"][2] = [0, 0, 0]
    out.append(("K last row zero", k))
    k = json.loads(json.dumps(base))
    k["K"][2] = [0.1, 0, 1]
    out.append(("K last row not [0,0,1]", k))
    k = json.loads(json.dumps(base))
    k["K"][1][0] = 5.0
    out.append(("K lower triangle", k))
    k = json.loads(json.dumps(base))
    k["K"][0][0] = 1e30
    out.append(("focal 1e30", k))
    k = json.loads(json.dumps(base))
    k["K"][0][2] = -1e25
    out.append(("principal point far away", k))
    k = json.loads(json.dumps(base))
    k["w2c"][2][3] = 1e30
    out.append(("camera 1e30 m away", k))
    k = json.loads(json.dumps(base))
    k["width"] = 10**20
    out.append(("width 1e20", k))
    return out


@pytest.mark.parametrize("name, cam", _cam_variants(), ids=[n for n, _ in _cam_variants()])
def test_unrenderable_cameras_are_refused_in_both_paths(name, cam):
    with pytest.raises(ProtocolError) as e:
        parse_cameras_json(json.dumps([cam]))
    assert e.value.code == "invalid_cameras", (name, e.value.message)
    assert _code(json.dumps(_frame(camera=cam))) == "invalid_camera"


def test_creation_cameras_with_huge_integers():
    cam = json.dumps([_cam_json()])
    k = _cam_json()["K"][0][0]
    with pytest.raises(ProtocolError) as e:
        parse_cameras_json(cam.replace(json.dumps(k), BIG_INT, 1))
    assert e.value.code == "non_finite_number"
    with pytest.raises(ProtocolError) as e:
        parse_cameras_json(cam.replace('"height": 48', '"height": ' + "9" * 5000))
    assert e.value.code == "non_finite_number"
    cams = parse_cameras_json(cam)
    assert len(cams) == 1 and (cams[0].width, cams[0].height) == (64, 48)


@pytest.mark.parametrize(
    "text, code, words",
    [
        ('[{"K": [[1, 2', "invalid_json", ["cameras is not valid JSON", "expected a JSON array of camera objects"]),
        ("[]", "invalid_cameras", ["non-empty JSON array of camera objects", "got an empty array"]),
        ('"front"', "invalid_cameras", ["non-empty JSON array of camera objects", "got a JSON string"]),
        ("[1e39]", "non_finite_number", ["cameras:", "1e39"]),
    ],
)
def test_creation_cameras_errors_name_the_field_and_what_came(text, code, words):
    """The upload has several parts: a bad ``cameras`` part is named as such (not "message"), with
    what was expected and what came."""
    with pytest.raises(ProtocolError) as e:
        parse_cameras_json(text)
    assert e.value.code == code
    for w in words:
        assert w in e.value.message, e.value.message
    assert "message is not" not in e.value.message


def test_binary_camera_bounds():
    cam = Cameras.look_at((0.0, 0.0, 1.0), fov_deg=25.0, width=64, height=48)[None]
    far = Cameras(cam.K.clone(), cam.w2c.clone(), 64, 48)
    far.w2c[0, 2, 3] = 1e30
    with pytest.raises(ProtocolError) as e:
        parse_binary_message(pack_binary_request(1, [0.0] * SPACE.dim, far), SPACE)
    assert e.value.code == "invalid_camera"
    ok = parse_binary_message(pack_binary_request(1, [0.0] * SPACE.dim, cam), SPACE)
    assert ok.camera.width == 64


def test_cameras_refuse_a_k_that_is_not_a_pinhole_matrix():
    cam = Cameras.look_at((0.0, 0.0, 1.0), fov_deg=25.0, width=64, height=48)
    K = cam.K.clone()
    K[..., 2, :] = 0.0
    with pytest.raises(ValueError, match="last row"):
        Cameras(K, cam.w2c, 64, 48)


# ---------------------------------------------------------------- item 4: whole kind, fuzzed
_HOSTILE = [BIG_INT, "9" * 5000, "1e400", "-1e39", "3.4e38", "1e30", "-1e30", "1e-45", "0", "-0.0", "65536", "1e7"]


def _numeric_paths(obj, path=()):
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _numeric_paths(v, path + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _numeric_paths(v, path + (i,))
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        yield path


def _with_literal(obj, path, literal: str) -> str:
    marker = "__HOSTILE__"
    o = json.loads(json.dumps(obj))
    cur = o
    for p in path[:-1]:
        cur = cur[p]
    cur[path[-1]] = marker
    return json.dumps(o).replace(json.dumps(marker), literal)


def test_every_numeric_field_of_a_frame_message_gives_a_typed_result():
    """Each hostile number in each numeric field of a frame request: a parsed request whose camera
    the frame path can fit, or a ProtocolError, never another exception (which would close the
    socket with 1011)."""
    from server.frames import fit_camera

    msg = {"seq": 3, "expression": [0.1] * 4 + [0.0] * (SPACE.dim - 4), "camera": _cam_json()}
    paths = list(_numeric_paths(msg))
    assert len(paths) == 1 + SPACE.dim + 9 + 16 + 2
    seen = set()
    for path in paths:
        for lit in _HOSTILE:
            try:
                r = parse_text_message(_with_literal(msg, path, lit), SPACE)
            except ProtocolError as e:
                seen.add(e.code)
                continue
            assert torch.isfinite(r.expression).all()
            c = fit_camera(r.camera, 1024)
            assert torch.isfinite(c.K).all() and torch.isfinite(c.w2c).all() and 1 <= c.width <= 1024
    assert "non_finite_number" in seen and "invalid_camera" in seen


def test_unexpected_parser_exceptions_are_typed(monkeypatch):
    """A bug in a parser must give an error message, not end the stream."""
    from server import protocol

    def boom(value, space):
        raise OverflowError("simulated")

    monkeypatch.setattr(protocol, "parse_expression", boom)
    assert _code('{"seq": 1, "expression": {}}') == "invalid_message"


# ---------------------------------------------------------------- item 3: log throttle
def test_log_throttle_one_traceback_then_counts(caplog):
    from server.streaming import LogThrottle

    now = [0.0]
    t = LogThrottle(interval=60.0, clock=lambda: now[0])
    lg = logging.getLogger("fastgha.test.throttle")
    with caplog.at_level(logging.INFO, logger="fastgha.test.throttle"):
        for i in range(1000):
            try:
                raise RuntimeError("render blew up")
            except RuntimeError:
                t.exception(lg, "render", "rendering a frame of avatar %s failed", "abc")
            now[0] += 0.005  # 5 s in all
        assert sum(r.exc_info is not None for r in caplog.records) == 1
        now[0] += 61.0
        try:
            raise RuntimeError("again")
        except RuntimeError:
            t.exception(lg, "render", "rendering a frame of avatar %s failed", "abc")
    texts = [r.getMessage() for r in caplog.records]
    assert len(caplog.records) <= 3, texts
    assert any("999" in m for m in texts), texts  # the suppressed ones are counted
    assert sum(r.exc_info is not None for r in caplog.records) == 1


# ---------------------------------------------------------------- items 6 and 8: store


def test_store_disk_full_is_typed_and_leaves_nothing(tmp_path, monkeypatch):
    from server.store import AvatarStore, StorageFullError

    store = AvatarStore(tmp_path, 1 << 30, 0, load_fn=CanonicalAvatar.load)
    def full(self, *a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    av = random_avatar()
    # the avatar file cannot be written
    monkeypatch.setattr(CanonicalAvatar, "save", lambda self, p: full(p))
    with pytest.raises(StorageFullError):
        store.put("A" * 22, av, {"avatar_id": "A" * 22})
    monkeypatch.undo()
    assert list(store.dir.iterdir()) == []
    # the avatar is written, the metadata is not: the avatar file goes too
    import server.store as store_mod

    monkeypatch.setattr(store_mod, "_atomic_write_bytes", lambda path, data: full(path))
    with pytest.raises(StorageFullError):
        store.put("B" * 22, av, {"avatar_id": "B" * 22})
    assert list(store.dir.iterdir()) == [] and store.get_meta("B" * 22) is None


def test_store_quarantines_a_corrupt_avatar_once(tmp_path, caplog):
    from server.store import AvatarStore, AvatarUnreadableError

    store = AvatarStore(tmp_path, 1 << 30, 0, load_fn=CanonicalAvatar.load)
    aid, bid = "C" * 22, "D" * 22
    store.put(aid, random_avatar(), {"avatar_id": aid})
    store.put(bid, random_avatar(), {"avatar_id": bid})
    fresh = AvatarStore(tmp_path, 1 << 30, 0, load_fn=CanonicalAvatar.load)  # nothing cached
    p = fresh.dir / f"{aid}.safetensors"
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])  # truncated
    (fresh.dir / f"{bid}.json").write_text('{"avatar_id": ')  # truncated metadata
    with caplog.at_level(logging.WARNING, logger="server.store"):
        with pytest.raises(AvatarUnreadableError):
            fresh.get(aid)
        with pytest.raises(AvatarUnreadableError):
            fresh.get_meta(bid)
        # set aside: later reads see no avatar, and nothing is logged again
        assert fresh.get_meta(aid) is None and fresh.get(aid) is None and fresh.get_meta(bid) is None
    assert len([r for r in caplog.records if "quarantine" in r.getMessage()]) == 2
    q = sorted(x.name for x in (tmp_path / "quarantine").iterdir())
    assert f"{aid}.safetensors" in q and f"{aid}.json" in q and f"{bid}.json" in q
    assert not (fresh.dir / f"{aid}.safetensors").exists()


# ---------------------------------------------------------------- item 9: API keys from a file
def test_api_keys_file(tmp_path, monkeypatch):
    from server.settings import Settings

    f = tmp_path / "keys"
    f.write_text("# operators\nkey-one\n\nkey-two, key-three\n")
    f.chmod(0o600)
    monkeypatch.delenv("FASTGHA_API_KEYS", raising=False)
    monkeypatch.setenv("FASTGHA_API_KEYS_FILE", str(f))
    s = Settings()
    assert s.api_key_list == ["key-one", "key-two", "key-three"]
    with pytest.raises(ValueError, match="api_keys_file"):
        Settings(api_keys_file=tmp_path / "missing")


def _capture_uvicorn(monkeypatch) -> dict:
    """Replace ``uvicorn.Server`` (``fastgha serve`` builds a Config and runs a Server on the socket it
    bound first) by one that records the config's settings and closes the socket instead of serving."""
    import uvicorn

    seen: dict = {}

    class FakeServer:
        def __init__(self, config):
            self.config = config

        def run(self, sockets=None):
            seen.update(vars(self.config))
            for sock in sockets or []:
                sock.close()

    monkeypatch.setattr(uvicorn, "Server", FakeServer)
    return seen


def _free_port() -> str:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return str(s.getsockname()[1])


def test_serve_warns_about_keys_on_the_command_line(tmp_path, monkeypatch, capsys):
    from fastgha_core.cli import main

    seen = _capture_uvicorn(monkeypatch)
    monkeypatch.delenv("FASTGHA_API_KEYS", raising=False)
    f = tmp_path / "keys"
    f.write_text("secret-from-file\n")
    assert main(["serve", "--port", _free_port(), "--model", "tiny", "--data-dir", str(tmp_path), "--api-keys-file", str(f)]) == 0
    assert seen["app"].state.ctx.settings.api_key_list == ["secret-from-file"]
    assert "command line" not in capsys.readouterr().err
    assert main(["serve", "--port", _free_port(), "--model", "tiny", "--data-dir", str(tmp_path), "--api-keys", "k1"]) == 0
    err = capsys.readouterr().err
    assert "command line" in err and "--api-keys-file" in err and "k1" not in err


# ---------------------------------------------------------------- item 11: proxy trust
@pytest.mark.parametrize("name", ["Dockerfile.cpu", "Dockerfile.cuda"])
def test_dockerfiles_trust_only_the_configured_proxy(name, monkeypatch, tmp_path):
    text = (REPO / "docker" / name).read_text()
    cmd = [line for line in text.splitlines() if line.startswith("CMD ")][-1]
    argv = json.loads(cmd[4:])
    assert argv[:2] == ["fastgha", "serve"]
    assert "*" not in argv, argv
    from fastgha_core.cli import main

    seen = _capture_uvicorn(monkeypatch)
    monkeypatch.delenv("FASTGHA_FORWARDED_ALLOW_IPS", raising=False)
    rest = [a for a in argv[2:] if a not in ("--device", "cuda")]
    assert main(["serve", *rest, "--port", _free_port(), "--model", "tiny", "--data-dir", str(tmp_path)]) == 0
    assert seen["forwarded_allow_ips"] not in ("*", None) and "*" not in str(seen["forwarded_allow_ips"])
    monkeypatch.setenv("FASTGHA_FORWARDED_ALLOW_IPS", "10.0.0.5")
    assert main(["serve", *rest, "--port", _free_port(), "--model", "tiny", "--data-dir", str(tmp_path)]) == 0
    assert seen["forwarded_allow_ips"] == "10.0.0.5"


def test_serve_passes_connection_limits_to_uvicorn(monkeypatch, tmp_path):
    from fastgha_core.cli import main
    from server.security import GuardedH11Protocol, GuardedWebSocketProtocol

    seen = _capture_uvicorn(monkeypatch)
    assert main(["serve", "--port", _free_port(), "--model", "tiny", "--data-dir", str(tmp_path)]) == 0
    assert seen["http"] is GuardedH11Protocol and seen["ws"] is GuardedWebSocketProtocol
    assert seen["limit_concurrency"] > 0 and 0 < seen["timeout_keep_alive"] <= 30
    assert seen["h11_max_incomplete_event_size"] <= 32 * 1024


# ---------------------------------------------------------------- items 6, 8, 12: the app-level handlers
def test_install_maps_store_errors_and_adds_security_headers():
    from fastapi import FastAPI
    from starlette.testclient import TestClient

    from server.security import install
    from server.settings import Settings
    from server.store import AvatarUnreadableError, StorageFullError

    app = FastAPI()
    install(app, Settings())

    @app.get("/full")
    async def full():
        raise StorageFullError(errno.ENOSPC, "no space left for avatar x")

    @app.get("/corrupt")
    async def corrupt():
        raise AvatarUnreadableError("A" * 22, "ValueError: truncated")

    client = TestClient(app, raise_server_exceptions=False)
    r = client.get("/full")
    assert r.status_code == 507 and r.json()["error"]["code"] == "insufficient_storage"
    r = client.get("/corrupt")
    assert r.status_code == 410 and r.json()["error"]["code"] == "avatar_unreadable"
    assert "frame-ancestors 'none'" in r.headers["content-security-policy"] and r.headers["x-frame-options"] == "DENY"
    r = client.get("/docs")  # the interactive docs load a CDN script: no CSP there, the rest still
    assert r.status_code == 200 and "content-security-policy" not in r.headers and r.headers["x-frame-options"] == "DENY"


def test_origin_rules():
    from server.streaming import origin_allowed

    allowed = ["https://app.example"]
    assert origin_allowed({"origin": "https://app.example", "host": "srv:8000"}, allowed)
    assert origin_allowed({"origin": "http://srv:8000", "host": "srv:8000"}, allowed)  # the server's own page
    assert origin_allowed({"host": "srv:8000"}, allowed)  # not a browser
    assert not origin_allowed({"origin": "https://evil.example", "host": "srv:8000"}, allowed)
    assert not origin_allowed({"origin": "null", "host": "srv:8000"}, allowed)
    assert not origin_allowed({"origin": "https://app.example.evil", "host": "srv:8000"}, allowed)
    assert origin_allowed({"origin": "https://evil.example"}, []) and origin_allowed({"origin": "https://evil.example"}, ["*"])


def test_serve_names_a_wrong_setting_as_the_user_set_it(monkeypatch, tmp_path, capsys):
    """A bad FASTGHA_* value or flag is reported in one line by its variable (or flag) and value,
    with what was expected: no pydantic dump with documentation links."""
    from fastgha_core.cli import main

    monkeypatch.setenv("FASTGHA_COMPILE", "maybe")
    monkeypatch.setenv("FASTGHA_MAX_IMAGES", "abc")
    assert main(["serve", "--port", _free_port(), "--data-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "errors.pydantic.dev" not in err, err
    assert "FASTGHA_COMPILE='maybe': Input should be 'auto', 'on' or 'off'" in err, err
    assert "FASTGHA_MAX_IMAGES='abc'" in err and "integer" in err, err
    monkeypatch.delenv("FASTGHA_COMPILE")
    monkeypatch.delenv("FASTGHA_MAX_IMAGES")
    assert main(["serve", "--port", _free_port(), "--data-dir", str(tmp_path), "--api-keys-file", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err
    assert f"--api-keys-file='{tmp_path / 'none'}'" in err and "cannot be read" in err, err


def test_serve_reports_an_unusable_data_folder_before_loading_the_model(monkeypatch, tmp_path, capsys):
    """A data folder that cannot be created or written is one line naming it (flag or variable),
    before the model loads, instead of a start-up traceback."""
    import server.app as app_mod
    from fastgha_core.cli import main

    monkeypatch.setattr(app_mod, "create_app", lambda *a, **k: (_ for _ in ()).throw(AssertionError("must not start")))
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    assert main(["serve", "--port", _free_port(), "--data-dir", str(blocker / "avatars")]) == 2
    err = capsys.readouterr().err
    assert f"--data-dir '{blocker / 'avatars'}' cannot hold avatars" in err and "writable folder" in err, err
    monkeypatch.setenv("FASTGHA_DATA_DIR", str(blocker))
    assert main(["serve", "--port", _free_port()]) == 2
    assert f"FASTGHA_DATA_DIR '{blocker}' cannot hold avatars" in capsys.readouterr().err
    fresh = tmp_path / "new" / "data"  # a folder that does not exist yet is created, as before
    seen = _capture_uvicorn(monkeypatch)
    monkeypatch.setattr(app_mod, "create_app", lambda settings: object())
    assert main(["serve", "--port", _free_port(), "--data-dir", str(fresh)]) == 0
    assert fresh.is_dir() and not list(fresh.iterdir()) and seen
