"""The Python client, ``fastgha client``, ``fastgha loadtest`` and the samples routes, against a
real server process (``server_process.py``: a 64 x 64 tiny model with a non-zero deformation
output layer, and a synthetic sample subject)."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import httpx
import numpy as np
import pytest
import torch
from PIL import Image

from client_demo.client import (
    FastGHAClient,
    StreamStats,
    load_request_dir,
    look_at_camera,
    orbit_camera,
    pack_request,
    unpack_frame,
)
from client_demo.loadtest import LoadTestConfig, check_target
from fastgha_core.cameras import Cameras, cameras_from_json, look_at_w2c
from fastgha_core.cli import main as cli_main
from server.protocol import pack_binary_request, pack_frame
from server.protocol import unpack_frame as server_unpack_frame
from server_process import API_KEY, SAMPLE_NAME, ServerProcess, make_model_dir, make_sample_dir

pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def samples_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("samples")
    make_sample_dir(root)
    return root


@pytest.fixture(scope="module")
def server(tmp_path_factory, samples_dir):
    model = make_model_dir(tmp_path_factory.mktemp("model"))
    srv = ServerProcess(model, tmp_path_factory.mktemp("data"), samples_dir, tmp_path_factory.mktemp("logs") / "server.log")
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def request_dir(samples_dir) -> Path:
    return samples_dir / SAMPLE_NAME / "request"


@pytest.fixture(scope="module")
def client(server) -> FastGHAClient:
    return FastGHAClient(server.base, api_key=API_KEY)


# ---------------------------------------------------------------- pure helpers against the library / server code
@pytest.mark.parametrize("eye", [(0.0, 0.0, 1.0), (0.3, 0.2, 0.9), (-0.8, -0.4, 0.5), (0.1, 0.9, 0.2)])
def test_look_at_camera_matches_library(eye):
    cam = look_at_camera(eye, fov_deg=25.0, width=80, height=60)
    ref = Cameras.look_at(torch.tensor(eye), fov_deg=25.0, width=80, height=60)
    torch.testing.assert_close(torch.tensor(cam["w2c"], dtype=torch.float32), look_at_w2c(torch.tensor(eye)), atol=1e-6, rtol=0)
    torch.testing.assert_close(torch.tensor(cam["K"], dtype=torch.float32), ref.K, atol=1e-4, rtol=0)
    assert cameras_from_json([cam])[0].width == 80  # a valid camera object for the server


def test_orbit_camera_looks_at_target_from_radius():
    cam = cameras_from_json([orbit_camera(30.0, 10.0, 1.5, width=32, height=32)])[0]
    c = cam.centers.reshape(3)
    assert math.isclose(float(c.norm()), 1.5, rel_tol=1e-5)
    assert float(c[0]) > 0 and float(c[1]) > 0  # yaw towards +x (subject's left), pitch up
    uv, z = cam.project(torch.zeros(1, 1, 3))  # the head centre projects to the image centre
    torch.testing.assert_close(uv.reshape(2), torch.tensor([16.0, 16.0]), atol=1e-3, rtol=0)


def test_wire_format_matches_server():
    rng = np.random.default_rng(0)
    expr = rng.normal(size=53).astype(np.float32)
    cam = orbit_camera(12.0, -5.0, 1.1, width=96, height=64)
    ref_cam = cameras_from_json([cam])[0]
    assert pack_request(7, expr, cam) == pack_binary_request(7, expr, ref_cam)
    assert pack_request(2**32 - 1, expr) == pack_binary_request(2**32 - 1, expr)
    header, jpeg = {"seq": 3, "width": 4, "height": 2, "dropped": 1}, b"\xff\xd8jpegbytes"
    msg = pack_frame(header, jpeg)
    assert unpack_frame(msg) == server_unpack_frame(msg) == (header, jpeg)
    with pytest.raises(ValueError):
        unpack_frame(b"XXXX" + msg[4:])


def test_load_request_dir(request_dir, tmp_path):
    images, cams, masks = load_request_dir(request_dir)
    assert [p.name for p in images] == ["00.jpg", "01.jpg", "02.jpg", "03.jpg"]
    assert len(cams) == 4 and masks is not None and [m.name for m in masks] == [f"{i:02d}_mask.png" for i in range(4)]
    with pytest.raises(ValueError, match="no .jpg"):
        load_request_dir(tmp_path)
    # photos without cameras.json: the cameras are left to the server's tracker
    bare = tmp_path / "bare"
    bare.mkdir()
    for p in images[:2]:
        (bare / p.name).write_bytes(p.read_bytes())
    got_images, got_cams, got_masks = load_request_dir(bare)
    assert [p.name for p in got_images] == ["00.jpg", "01.jpg"] and got_cams is None and got_masks is None
    (bare / "cameras.json").write_text("[{}]")
    with pytest.raises(ValueError, match=r"2 images \(00.jpg, 01.jpg\) but cameras.json holds 1 cameras"):  # names them: which one is extra?
        load_request_dir(bare)
    (bare / "cameras.json").write_text("[{K: 1}]")  # a hand-edited file: the error names it
    with pytest.raises(ValueError, match=r"bare/cameras.json does not parse as JSON: Expecting property name"):
        load_request_dir(bare)


def test_loadtest_target_and_bounds():
    for ok in ("http://127.0.0.1:8000", "http://localhost:1", "http://[::1]:8000", "http://127.3.4.5"):
        check_target(ok, allow_remote=False)
    for bad in ("http://10.0.0.2:8000", "http://example.com", "https://0.0.0.0:80"):
        with pytest.raises(ValueError, match="allow-remote"):
            check_target(bad, allow_remote=False)
    check_target("http://example.com", allow_remote=True)
    for kw, msg in [({"clients": 0}, "clients"), ({"clients": 257}, "clients"), ({"duration_s": 4000}, "duration"),
                    ({"rate_hz": 1000}, "rate"), ({"size": 8}, "size"),
                    ({"clients": 256, "duration_s": 3600, "rate_hz": 200}, "exceeds the bound")]:  # fmt: skip
        with pytest.raises(ValueError, match=msg):
            LoadTestConfig(url="http://127.0.0.1:1", **kw).validate()


def test_loadtest_cli_refuses_remote_host(capsys):
    rc = cli_main(["loadtest", "--url", "http://192.0.2.10:8000", "--clients", "1", "--duration", "1"])
    assert rc == 2
    assert "--allow-remote" in capsys.readouterr().err


# ---------------------------------------------------------------- against the server
def test_samples_routes(server, request_dir):
    r = httpx.get(server.base + "/v1/samples")
    assert r.status_code == 200
    (entry,) = r.json()["samples"]
    assert entry["name"] == SAMPLE_NAME and entry["images"] == ["00.jpg", "01.jpg", "02.jpg", "03.jpg"]
    assert entry["has_expressions"] and entry["num_expression_frames"] == 12 and entry["has_orbit"]
    base = f"{server.base}/v1/samples/{SAMPLE_NAME}/"
    assert httpx.get(base + "00.jpg").content == (request_dir / "00.jpg").read_bytes()
    assert httpx.get(base + "01_mask.png").headers["content-type"] == "image/png"
    assert httpx.get(base + "cameras.json").json() == json.loads((request_dir / "cameras.json").read_text())
    assert len(cameras_from_json(httpx.get(base + "orbit.json").json())) == 8
    ex = httpx.get(base + "expressions.json").json()
    ref = np.load(request_dir.parent / "expressions.npy")
    assert (ex["num_frames"], ex["dim"]) == ref.shape
    np.testing.assert_allclose(np.array(ex["frames"]), ref, atol=1e-5)
    for bad in ["../request/cameras.json", "..%2F..%2Fexpressions.npy", "expressions.npy", "request/00.jpg", "gt", "%2Fetc%2Fpasswd"]:
        r = httpx.get(base + bad)
        assert r.status_code == 404 and r.json()["error"]["code"] in ("sample_file_not_found", "sample_not_found", "not_found"), bad
    for name in ["..", "nope", "a%2F..", ".hidden"]:
        r = httpx.get(f"{server.base}/v1/samples/{name}/cameras.json")
        assert r.status_code == 404, name


def test_client_creates_streams_and_deletes(client, request_dir):
    info = client.model_info()
    assert info["expression_space"] == "ict53" and "jawOpen" in info["expression_names"]
    images, cams, masks = load_request_dir(request_dir)
    avatar = client.create_avatar(images, cams, masks)
    assert avatar.num_gaussians > 0 and avatar.expression_space == "ict53"
    assert avatar.tracking_ms is None and avatar.refining_ms > 0  # photos with cameras: refined by default, not tracked
    sizes = [(48, 40), (48, 40), (64, 64), (64, 64)]
    expr = [{"jawOpen": 0.0}, {"jawOpen": 1.0, "eyeBlink_L": 1.0}, [0.0] * 53, list(np.linspace(0, 1, 53))]
    reqs = [{"expression": e, "camera": orbit_camera(10.0 * i, 0.0, 1.0, width=w, height=h)} for i, ((w, h), e) in enumerate(zip(sizes, expr))]
    stats = StreamStats()
    frames = client.stream_sync(avatar, reqs, stats=stats)
    assert [f.seq for f in frames] == [0, 1, 2, 3]
    assert stats.sent == 4 and stats.received == 4 and stats.dropped == 0 and not stats.errors
    imgs = [f.image() for f in frames]
    assert [im.shape for im in imgs] == [(h, w, 3) for w, h in sizes]
    assert all(im.dtype == np.uint8 and im.std() > 1.0 for im in imgs)  # not a blank picture
    assert np.abs(imgs[0].astype(int) - imgs[1].astype(int)).mean() > 0.1  # the expression changes the frame
    assert client.download_ply(avatar).startswith(b"ply")
    got = client.avatar_info(avatar)
    assert got["num_gaussians"] == avatar.num_gaussians
    assert avatar.info == {k: got[k] for k in ("view_blend", "expression_prior", "same_person", "num_images")}  # what the server reports
    assert avatar.info["num_images"] == len(images)  # the photos sent: describe() names blended views beyond them as mirrored
    assert "view blending off (no per-view data" in avatar.describe()  # photos with cameras alone
    client.delete(avatar)
    with pytest.raises(RuntimeError, match="avatar_not_found"):
        client.avatar_info(avatar)


def test_client_pipelined_stream_accounts_for_every_request(client, request_dir):
    avatar = client.create_avatar_from_dir(request_dir)
    cam = orbit_camera(width=32, height=32)
    stats = StreamStats()
    frames = client.stream_sync(avatar, [{"expression": {"jawOpen": i / 10}, "camera": cam} for i in range(10)], stats=stats, max_in_flight=3)
    seqs = [f.seq for f in frames]
    assert seqs == sorted(seqs) and seqs[-1] == 9  # the newest request is always rendered
    assert stats.received + stats.dropped == 10 == stats.sent
    assert frames[-1].header["dropped"] == stats.dropped
    client.delete(avatar)


def test_client_command_writes_frames_and_mp4(server, request_dir, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("FASTGHA_API_KEY", API_KEY)
    out, fdir = tmp_path / "clip.mp4", tmp_path / "frames"
    rc = cli_main(["client", "--url", server.base, "--input", str(request_dir), "--orbit", "--out", str(out),
                   "--frames-dir", str(fdir), "--size", "48", "--frames", "6"])  # fmt: skip
    text = capsys.readouterr().out
    assert rc == 0, text
    jpgs = sorted(fdir.glob("frame_*.jpg"))
    assert [p.name for p in jpgs] == [f"frame_{i:05d}.jpg" for i in range(6)]
    assert Image.open(jpgs[0]).size == (48, 48)
    assert out.stat().st_size > 0 and out.read_bytes()[4:8] == b"ftyp"
    assert "6 frames of 6 requested" in text and "fps" in text and "p95" in text
    assert "creating the avatar: decoding" in text or "creating the avatar: queued" in text  # the job's progress
    assert ", refinement " in text.split("avatar ", 1)[1].split("\n", 1)[0]  # the server's refinement time, on the avatar's line
    assert "view blending off" in text and "expression prior on" in text and "same person:" in text  # what the avatar runs with


def test_client_command_keep_prints_what_reaches_the_kept_avatar(server, request_dir, tmp_path, capsys):
    """``--keep`` leaves the avatar on the server; its token is shown by the server only once, so the
    command prints it (else the kept avatar could never be streamed, exported or deleted)."""
    rc = cli_main(["client", "--url", server.base, "--input", str(request_dir), "--api-key", API_KEY, "--keep",
                   "--out", str(tmp_path / "k.mp4"), "--size", "32", "--frames", "2"])  # fmt: skip
    text = capsys.readouterr().out
    assert rc == 0, text
    line = next(x for x in text.splitlines() if x.startswith("kept avatar "))
    aid, token = line.split()[2], line.rsplit("token ", 1)[1].split()[0]
    auth = {"Authorization": f"Bearer {token}"}
    r = httpx.get(f"{server.base}/v1/avatars/{aid}", headers=auth, timeout=30)
    assert r.status_code == 200 and r.json()["avatar_id"] == aid
    assert httpx.delete(f"{server.base}/v1/avatars/{aid}", headers=auth, timeout=30).status_code == 204


def test_load_request_dir_says_a_file_is_not_a_folder(request_dir):
    photo = next(request_dir.glob("*.jpg"))
    with pytest.raises(ValueError, match=r"is a file; expected a folder of photos"):
        load_request_dir(photo)


def _created_total(server) -> float:
    text = httpx.get(server.base + "/metrics", timeout=30).text
    return sum(float(line.split()[-1]) for line in text.splitlines() if line.startswith("fastgha_avatars_created_total"))


def test_client_command_refuses_unknown_expression_names_before_creating(server, request_dir, tmp_path, capsys):
    """A typo in --expressions is found before the avatar is made (one line, exit 2), not as a
    traceback mid-stream."""
    seq = tmp_path / "seq.json"
    seq.write_text(json.dumps([{"jawOpen": 0.5}, {"jawOpenn": 0.6}]))
    before = _created_total(server)
    rc = cli_main(["client", "--url", server.base, "--input", str(request_dir), "--api-key", API_KEY,
                   "--expressions", str(seq), "--out", str(tmp_path / "c.mp4"), "--size", "32"])  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 2
    assert "--expressions" in err and "frame 1" in err and "jawOpenn" in err and "Traceback" not in err, err
    assert _created_total(server) == before


def test_client_command_reports_a_refused_frame_as_one_line(server, request_dir, tmp_path, capsys):
    """What only the server checks (weights within +-100) comes back as a typed stream error: one
    line with its code, exit 2, the avatar deleted."""
    seq = tmp_path / "seq.json"
    seq.write_text(json.dumps([{"jawOpen": 0.5}, {"jawOpen": 500.0}]))
    rc = cli_main(["client", "--url", server.base, "--input", str(request_dir), "--api-key", API_KEY,
                   "--expressions", str(seq), "--out", str(tmp_path / "c.mp4"), "--size", "32"])  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 2
    assert "the stream failed: invalid_expression" in err and "Traceback" not in err, err


def test_loadtest_two_clients_report(server, request_dir, tmp_path, capsys):
    js, png = tmp_path / "report.json", tmp_path / "plot.png"
    rc = cli_main(["loadtest", "--url", server.base, "--clients", "2", "--duration", "3", "--rate", "8", "--size", "48",
                   "--input", str(request_dir), "--api-key", API_KEY, "--json", str(js), "--plot", str(png)])  # fmt: skip
    out = capsys.readouterr().out
    assert rc == 0, out
    rep = json.loads(js.read_text())
    assert set(rep) >= {"config", "server", "avatars", "aggregate", "clients", "timeline"}
    agg = rep["aggregate"]
    for key in ["clients", "duration_s", "requests_sent", "frames_received", "dropped_requests", "unanswered_requests",
                "delivered_fps", "delivered_fps_per_client", "latency_ms", "server_total_ms", "bytes_per_s", "errors"]:  # fmt: skip
        assert key in agg, key
    assert set(agg["latency_ms"]) == {"p50", "p95", "p99", "mean", "max"}
    assert agg["errors"] == 0 and agg["delivered_fps"] > 0 and agg["bytes_per_s"] > 0
    assert agg["requests_sent"] == 2 * 24
    assert len(rep["clients"]) == 2 and rep["avatars"]["count"] == 2
    for c in rep["clients"]:
        assert c["frames_received"] > 0 and c["errors"] == 0
        assert c["frames_received"] + c["dropped_requests"] + c["unanswered_requests"] == c["requests_sent"]
        assert c["latency_ms"]["p50"] <= c["latency_ms"]["p95"] <= c["latency_ms"]["p99"]
    assert agg["frames_received"] == sum(c["frames_received"] for c in rep["clients"])
    assert sum(f * rep["timeline"]["bucket_s"] for f in rep["timeline"]["fps"]) == pytest.approx(agg["frames_received"])
    assert Image.open(io.BytesIO(png.read_bytes())).format == "PNG"
    # the avatars were deleted afterwards
    for c in rep["clients"]:
        r = httpx.get(f"{server.base}/v1/avatars/{c['avatar_id']}", headers={"Authorization": "Bearer x"})
        assert r.status_code == 404


def _protocol_example() -> str:
    text = (Path(__file__).resolve().parents[1] / "docs" / "protocol.md").read_text(encoding="utf-8")
    return text.split("## Example (Python)", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]


def test_protocol_docs_python_example_runs_as_written(server, request_dir, tmp_path, monkeypatch):
    """docs/protocol.md's hand-written example, run as a user would (its URLs pointed at the test
    server, its shipped sample folder swapped for the test's, which has the same file names): it creates
    an avatar and gets a frame. Its synchronous creation waits for the job, so it must not keep
    httpx's 5 s default timeout: behind
    three queued creations of tracked photos that example failed with ``httpx.ReadTimeout``."""
    import ast

    code = _protocol_example()
    posts = [n for n in ast.walk(ast.parse(code)) if isinstance(n, ast.Call) and ast.unparse(n.func) == "httpx.post"]
    assert posts
    for call in posts:
        timeout = next((k.value for k in call.keywords if k.arg == "timeout"), None)
        assert isinstance(timeout, ast.Constant) and timeout.value >= 60, ast.unparse(call)
    shipped = 'req = "fastgha_core/assets/samples/synth_1000000/request"'  # the example reads the shipped sample
    assert shipped in code and sorted(p.name for p in request_dir.glob("[0-9][0-9].jpg")) == [f"{i:02d}.jpg" for i in range(4)]
    code = code.replace(shipped, f"req = {str(request_dir)!r}")  # same names (00.jpg ... 03.jpg), the test's sample
    key_line = 'KEY = ""'  # the example defines its key (empty: a server without FASTGHA_API_KEYS); the test server has keys
    assert key_line in code
    code = code.replace(key_line, f"KEY = {API_KEY!r}")
    monkeypatch.chdir(tmp_path)
    scope = {}
    host = server.base.split("://", 1)[1]
    exec(compile(code.replace("127.0.0.1:8000", host), "protocol.md example", "exec"), scope)
    assert scope["r"].status_code == 201
    assert scope["header"]["seq"] == 0 and scope["jpeg"][:2] == b"\xff\xd8"


def test_loadtest_says_once_why_the_server_closed_a_stream(server, request_dir, tmp_path, capsys):
    """Five clients on one avatar, over the server's four streams per avatar: the fifth is closed with
    4503, and the report says so in one readable line (it used to repeat the close three times)."""
    js = tmp_path / "report.json"
    rc = cli_main(["loadtest", "--url", server.base, "--clients", "5", "--shared-avatar", "--duration", "2", "--rate", "4",
                   "--size", "32", "--input", str(request_dir), "--api-key", API_KEY, "--json", str(js)])  # fmt: skip
    out = capsys.readouterr().out
    assert rc == 1, out  # a run with errors exits 1
    msgs = json.loads(js.read_text())["aggregate"]["error_messages"]
    assert len(msgs) == 1 and msgs[0].startswith("closed by the server: 4503 at_capacity: this avatar already has 4 open streams"), msgs
    assert msgs[0].count("4503") == 1 and "FASTGHA_MAX_STREAMS_PER_AVATAR" in msgs[0]
    assert f"error: {msgs[0]}" in out


def test_client_command_says_when_the_folder_holds_more_photos_than_the_server_takes(server, request_dir, tmp_path, capsys):
    """A folder of 9 photos got the server's 'send 1 to 8 'images' parts, got 9', in terms of the
    multipart request the user never wrote; it is now refused before any upload, in the folder's terms."""
    import shutil

    max_images = httpx.get(server.base + "/v1/model", timeout=30).json()["max_images"]
    folder = tmp_path / "many"
    folder.mkdir()
    photo = sorted(request_dir.glob("*.jpg"))[0]
    for i in range(max_images + 1):
        shutil.copy(photo, folder / f"{i:02d}.jpg")
    before = _created_total(server)
    rc = cli_main(["client", "--url", server.base, "--input", str(folder), "--api-key", API_KEY, "--out", str(tmp_path / "c.mp4")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert f"{folder} holds {max_images + 1} photos; this server takes 1 to {max_images}" in err[0], err
    assert _created_total(server) == before
