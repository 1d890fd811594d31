"""Avatar creation as a job (``server/jobs.py``): units of the decoder and the progress, and end to
end against real server processes (``server_process.py``: a 64 x 64 tiny model): ``Prefer:
respond-async`` -> 202, the status resource, server-sent events, a stream opened before the avatar
is ready, the bounded queue's 429 / 503 with ``Retry-After``, cancelling by DELETE, error messages
that name files by their filenames, the Python client's progress and ``ServerBusy``, and the
memory of the decompression-amplification attack (issue 18 item 1)."""

from __future__ import annotations

import concurrent.futures as cf
import io
import json
import os
import socket
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import torch
import pytest
from PIL import Image

from client_demo.client import CreationError, FastGHAClient, ServerBusy
from server.errors import ApiError
from server.jobs import STAGES, CreationRequest, Job, Photo, decode_photo, probe_request, safe_filename
from server_process import SAMPLE_NAME, ServerProcess, make_model_dir, make_sample_dir
from extras import needs_faces

pytestmark = pytest.mark.timeout(300)

KEYS = ("key-one", "key-two", "key-three")


def _png(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="PNG")
    return buf.getvalue()


def _jpeg(arr: np.ndarray, quality: int = 95) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()


def _smooth(h: int, w: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    return np.stack([128 + 100 * np.sin(xx / 37.0), 128 + 100 * np.cos(yy / 23.0), (xx + yy) % 256], -1).astype(np.uint8)


# ---------------------------------------------------------------- units
def test_decode_photo_downscales_while_decoding_like_a_full_decode_then_resize():
    arr = _smooth(600, 800)
    for data in (_png(arr), _jpeg(arr)):
        rgb, alpha = decode_photo(Photo("a.img", data), max_pixels=10**7, max_side=200)
        assert rgb.shape == (150, 200, 3) and rgb.dtype == np.uint8 and alpha is None
        ref = np.asarray(Image.open(io.BytesIO(data)).convert("RGB").resize((200, 150), Image.Resampling.LANCZOS), dtype=float)
        assert np.abs(rgb.astype(float) - ref).mean() < 4.0  # the same picture (JPEG: DCT-scaled decode)
    full, _ = decode_photo(Photo("a.png", _png(arr)), max_pixels=10**7, max_side=4096)
    np.testing.assert_array_equal(full, arr)  # no downscale below max_side: exact pixels


def test_decode_photo_alpha_and_masks():
    rgba = np.dstack([_smooth(40, 60), np.tile(np.arange(60, dtype=np.uint8) * 4, (40, 1))])
    rgb, alpha = decode_photo(Photo("p.png", _png(rgba)), max_pixels=10**6, max_side=1000)
    np.testing.assert_array_equal(rgb, rgba[..., :3])
    np.testing.assert_array_equal(alpha, rgba[..., 3])
    grey = np.tile(np.arange(60, dtype=np.uint8), (40, 1))
    m, _ = decode_photo(Photo("m.png", _png(grey)), max_pixels=10**6, max_side=1000, mask=True)
    np.testing.assert_array_equal(m, grey)
    m2, _ = decode_photo(Photo("m.png", _png(rgba)), max_pixels=10**6, max_side=1000, mask=True)
    np.testing.assert_array_equal(m2, rgba[..., 3])  # a mask with alpha: the alpha channel


def test_errors_name_files_by_their_filenames_never_an_index_or_a_repr():
    good = _png(_smooth(30, 40))
    cases = [
        (Photo("IMG_0042.jpg", good[:60]), "invalid_image"),
        (Photo("notes.png", b"this is not a picture"), "invalid_image"),
        (Photo("empty.png", b""), "invalid_image"),
    ]
    for photo, code in cases:
        with pytest.raises(ApiError) as ei:
            try:
                probe_request([photo], None, None, max_pixels=10**6, max_request_pixels=10**7)
                decode_photo(photo, max_pixels=10**6, max_side=100)
            except ApiError as e:
                assert e.code == code
                raise
        msg = ei.value.message
        assert photo.name in msg and "0x" not in msg and "BytesIO" not in msg and "image 0" not in msg, msg
    with pytest.raises(ApiError) as ei:
        probe_request([Photo("huge.png", _png(np.zeros((100, 100, 3), np.uint8)))], None, None, max_pixels=5000, max_request_pixels=10**7)
    assert ei.value.status == 413 and ei.value.code == "image_too_large" and "huge.png" in ei.value.message
    assert "FASTGHA_MAX_IMAGE_PIXELS" in ei.value.message and "downscaled" in ei.value.message  # what to change, either side
    from PIL import Image

    bomb = io.BytesIO()
    Image.new("1", (20000, 20000)).save(bomb, "PNG")  # past Pillow's own bomb check: the size and the limit, not only "too large"
    with pytest.raises(ApiError) as ei:
        probe_request([Photo("bomb.png", bomb.getvalue())], None, None, max_pixels=10**6, max_request_pixels=10**7)
    assert ei.value.status == 413 and ei.value.message == "bomb.png has 400000000 pixels; the limit is 1000000"
    photos = [Photo(f"p{i}.png", good) for i in range(3)]
    with pytest.raises(ApiError) as ei:
        probe_request(photos, None, None, max_pixels=10**6, max_request_pixels=2 * 30 * 40)
    assert ei.value.status == 413 and ei.value.code == "request_too_large" and "FASTGHA_MAX_REQUEST_PIXELS" in ei.value.message
    with pytest.raises(ApiError) as ei:
        probe_request([Photo("face.png", good)], [Photo("face_mask.png", _png(np.zeros((10, 10), np.uint8)))], None,
                      max_pixels=10**6, max_request_pixels=10**7)  # fmt: skip
    assert ei.value.code == "mask_size_mismatch" and "face.png" in ei.value.message and "face_mask.png" in ei.value.message
    assert safe_filename("../../etc/passwd", 0) == "passwd"
    assert safe_filename("C:\\Users\\me\\IMG 1.JPG", 0) == "IMG 1.JPG"
    assert safe_filename(None, 2) == "unnamed image 3" and safe_filename("", 0, "mask") == "unnamed mask 1"
    assert safe_filename("a\x00b.png", 0) == "a?b.png"


def test_exif_rotated_photo_is_probed_and_decoded_upright():
    """With the shared decoder (``fastgha_core.images``: EXIF orientation applied, cameras describe
    the upright image) the header probe and the decoder agree on the upright size."""
    from types import SimpleNamespace

    stored = _smooth(30, 40)  # stored 40 wide, 30 high; orientation 6: shown 30 wide, 40 high
    exif = Image.Exif()
    exif[0x0112] = 6
    buf = io.BytesIO()
    Image.fromarray(stored).save(buf, format="JPEG", quality=95, exif=exif.tobytes())
    photo = Photo("portrait.jpg", buf.getvalue())
    upright_cam = SimpleNamespace(width=30, height=40)
    probe_request([photo], None, [upright_cam], max_pixels=10**6, max_request_pixels=10**7)
    assert photo.size == (30, 40)
    rgb, _ = decode_photo(photo, max_pixels=10**6, max_side=1000)
    assert rgb.shape == (40, 30, 3)
    with pytest.raises(ApiError) as ei:  # a camera of the stored (sideways) grid is refused, naming the file
        probe_request([Photo("portrait.jpg", buf.getvalue())], None, [SimpleNamespace(width=40, height=30)],
                      max_pixels=10**6, max_request_pixels=10**7)  # fmt: skip
    assert ei.value.code == "camera_size_mismatch" and "portrait.jpg" in ei.value.message


def test_size_mismatch_of_a_sideways_stored_photo_says_the_server_turns_it_upright():
    """A file browser (or ``PIL.Image.open(...).size``) shows a phone photo's stored grid; the server
    measures the upright one. The refusal says both, so a camera of the stored grid is understood."""
    from types import SimpleNamespace

    exif = Image.Exif()
    exif[0x0112] = 6
    buf = io.BytesIO()
    Image.fromarray(_smooth(30, 40)).save(buf, format="JPEG", quality=95, exif=exif.tobytes())
    with pytest.raises(ApiError) as ei:
        probe_request([Photo("portrait.jpg", buf.getvalue())], None, [SimpleNamespace(width=40, height=30)],
                      max_pixels=10**6, max_request_pixels=10**7)  # fmt: skip
    assert "portrait.jpg is 30x40 upright (stored as 40x30 with EXIF orientation 6" in ei.value.message, ei.value.message
    plain = Photo("flat.png", _png(_smooth(30, 40)))
    with pytest.raises(ApiError) as ei:  # an unrotated photo keeps the short message
        probe_request([plain], None, [SimpleNamespace(width=30, height=40)], max_pixels=10**6, max_request_pixels=10**7)
    assert ei.value.message.endswith("but flat.png is 40x30"), ei.value.message


def test_job_progress_is_monotonic_over_its_stages():
    import asyncio

    async def run():
        req = CreationRequest([Photo("a.png", b"x")], None, None)
        stages = ["queued", "decoding", "tracking", "reconstructing", "refining", "saving"]
        assert set(stages) <= set(STAGES)
        job = Job("A" * 22, "h", "c", 1, req, stages)
        seen = [job.progress]
        for st in stages[1:]:
            for f in (0.0, 0.5, 1.0):
                job.update(st, f)
                seen.append(job.progress)
                assert job.status == "running" and job.snapshot()["stage"] == st
        job.finish({"avatar_id": job.id}, None)
        seen.append(job.progress)
        assert seen == sorted(seen) and seen[0] == 0.0 and seen[-1] == 1.0 and len(set(seen)) > 8
        assert job.snapshot()["status"] == "ready" and job.snapshot()["avatar"] == {"avatar_id": job.id}
        job2 = Job("B" * 22, "h", "c", 1, req, stages)
        job2.update("tracking", 0.0)
        before = job2.progress
        assert before > 0.0
        job2.finish(None, ApiError(422, "no_face", "no face in me.jpg"))
        snap = job2.snapshot()
        assert snap["status"] == "failed" and snap["error"] == {"status": 422, "code": "no_face", "message": "no face in me.jpg"}
        assert snap["progress"] == before  # a failed job keeps where it stopped (was 0.0: progress fell back)

    asyncio.run(run())


# ---------------------------------------------------------------- end to end




def _portrait() -> bytes:
    import matplotlib.cbook as cbook

    return Path(cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)).read_bytes()


@pytest.fixture(scope="module")
def samples(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("samples")
    make_sample_dir(root)
    return root / SAMPLE_NAME / "request"


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    return make_model_dir(tmp_path_factory.mktemp("model"))


@pytest.fixture(scope="module")
def server(model_dir, tmp_path_factory):
    """One creation at a time, one more waiting, one per API key; no refinement stage (these tests
    are about the queue; the stage has its own tests below, and the slow job stays slow: it tracks
    eight photos)."""
    data = tmp_path_factory.mktemp("data")
    srv = ServerProcess(model_dir, data, None, tmp_path_factory.mktemp("logs") / "server.log",
                        FASTGHA_API_KEYS=",".join(KEYS), FASTGHA_MAX_CONCURRENT_RECONSTRUCTIONS="1",
                        FASTGHA_MAX_QUEUED_JOBS="1", FASTGHA_MAX_JOBS_PER_CLIENT="1", FASTGHA_REFINE_STEPS="0")  # fmt: skip
    srv.data = data
    yield srv
    srv.stop()


def _sample_parts(folder: Path):
    imgs = sorted(folder.glob("[0-9][0-9].jpg"))
    files = [("images", (p.name, p.read_bytes(), "image/jpeg")) for p in imgs]
    return files, (folder / "cameras.json").read_text()


def _post(srv, files, key, data=None, prefer_async=True) -> httpx.Response:
    h = {"X-API-Key": key, **({"Prefer": "respond-async"} if prefer_async else {})}
    return httpx.post(srv.base + "/v1/avatars", files=files, data=data or {}, headers=h, timeout=120)


def _status(srv, job) -> dict:
    r = httpx.get(f"{srv.base}/v1/avatars/{job['avatar_id']}/status", headers={"Authorization": f"Bearer {job['token']}"}, timeout=30)
    assert r.status_code == 200, r.text
    return r.json()


def _wait(srv, job, pred, timeout=240.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        st = _status(srv, job)
        if pred(st):
            return st
        time.sleep(0.05)
    raise AssertionError(f"job never reached the state: {st}")


def _sse(srv, job, out: list) -> None:
    url = f"{srv.base}/v1/avatars/{job['avatar_id']}/events"
    with httpx.stream("GET", url, params={"token": job["token"]}, timeout=240) as r:
        assert r.headers["content-type"].startswith("text/event-stream")
        event = None
        for line in r.iter_lines():
            if line.startswith("event: "):
                event = line[7:]
            elif line.startswith("data: "):
                out.append((event, json.loads(line[6:])))
                if event in ("ready", "failed"):
                    return


def _metric(srv, state: str) -> float:
    for line in httpx.get(srv.base + "/metrics").text.splitlines():
        if line.startswith(f'fastgha_creation_jobs{{state="{state}"}}'):
            return float(line.split()[-1])
    raise AssertionError("no fastgha_creation_jobs metric")


@needs_faces
def test_job_queue_progress_events_early_stream_and_limits(server, samples):
    from websockets.sync.client import connect

    from server.protocol import unpack_frame

    # a slow job first: eight photos without cameras, tracked one by one
    slow = _post(server, [("images", (f"hopper{i}.jpg", _portrait(), "image/jpeg")) for i in range(8)], KEYS[0])
    assert slow.status_code == 202, slow.text
    sj = slow.json()
    assert slow.headers["location"] == f"/v1/avatars/{sj['avatar_id']}/status" and sj["token"] and sj["status"] in ("queued", "running")
    _wait(server, sj, lambda st: st["status"] == "running")
    files, cams = _sample_parts(samples)
    fast = _post(server, files, KEYS[1], {"cameras": cams})
    assert fast.status_code == 202, fast.text
    fj = fast.json()
    assert fj["status"] == "queued" and fj["queue_position"] == 1 and fj["progress"] == 0.0
    assert fj["stream_url"] == f"/v1/avatars/{fj['avatar_id']}/stream"

    # the queue is full (one running, one waiting): 503 for anyone, 429 first for a client over its share
    busy = _post(server, files, KEYS[2], {"cameras": cams})
    assert busy.status_code == 503 and busy.json()["error"]["code"] == "queue_full", busy.text
    assert int(busy.headers["retry-after"]) >= 1
    mine = _post(server, files, KEYS[0], {"cameras": cams}, prefer_async=False)  # the synchronous form is refused alike
    assert mine.status_code == 429 and mine.json()["error"]["code"] == "too_many_jobs" and int(mine.headers["retry-after"]) >= 1
    with pytest.raises(ServerBusy) as ei:
        FastGHAClient(server.base, api_key=KEYS[2]).create_avatar([samples / "00.jpg"], [json.loads(cams)[0]])
    assert ei.value.status == 503 and ei.value.retry_after >= 1
    assert _metric(server, "running") == 1 and _metric(server, "waiting") == 1
    # the avatar is not there yet: its metadata says so, its status says where it is
    h = {"Authorization": f"Bearer {fj['token']}"}
    r = httpx.get(f"{server.base}/v1/avatars/{fj['avatar_id']}", headers=h)
    assert r.status_code == 409 and r.json()["error"]["code"] == "avatar_not_ready"
    assert httpx.get(f"{server.base}/v1/avatars/{fj['avatar_id']}/status", headers={"Authorization": "Bearer nope"}).status_code == 403

    # server-sent events and a stream opened now, before the avatar is ready
    events: list = []
    sse = threading.Thread(target=_sse, args=(server, fj, events))
    sse.start()
    try:
        with connect(f"{server.ws_base}/v1/avatars/{fj['avatar_id']}/stream?token={fj['token']}") as ws:
            msgs = [json.loads(ws.recv(timeout=30))]
            assert msgs[0]["type"] == "progress" and msgs[0]["status"] == "queued" and msgs[0]["queue_position"] == 1
            while msgs[-1]["type"] == "progress":
                msgs.append(json.loads(ws.recv(timeout=240)))
            assert msgs[-1]["type"] == "ready", msgs[-1]
            stages = [m["stage"] for m in msgs[:-1]]
            assert stages[0] == "queued" and all(s in STAGES for s in stages)
            prog = [m["progress"] for m in msgs[:-1]]
            assert prog == sorted(prog)
            sj_done = _status(server, sj)
            ws.send(json.dumps({"seq": 1, "expression": {"jawOpen": 0.5}}))
            while True:
                msg = ws.recv(timeout=60)
                if isinstance(msg, bytes):
                    break
            header, jpeg = unpack_frame(msg)
            assert header["seq"] == 1 and jpeg[:2] == b"\xff\xd8"
    finally:
        sse.join(timeout=240)
    assert sj_done is not None and sj_done["status"] in ("ready", "failed")  # the slow one ran first
    assert events and events[-1][0] == "ready" and events[0][1]["status"] == "queued"
    assert [e[1]["progress"] for e in events] == sorted(e[1]["progress"] for e in events)
    done = _status(server, fj)
    assert done["status"] == "ready" and done["progress"] == 1.0 and done["avatar"]["num_gaussians"] > 0
    assert done["elapsed_ms"] > 0 and done["queue_position"] is None  # every documented status field, also when ready
    meta = httpx.get(f"{server.base}/v1/avatars/{fj['avatar_id']}", headers=h).json()
    assert meta["num_gaussians"] == done["avatar"]["num_gaussians"] and meta["num_images"] == 4


@needs_faces
def test_delete_cancels_a_queued_job(server, samples):
    slow = _post(server, [("images", (f"hopper{i}.jpg", _portrait(), "image/jpeg")) for i in range(8)], KEYS[0]).json()
    _wait(server, slow, lambda st: st["status"] == "running")
    files, cams = _sample_parts(samples)
    q = _post(server, files, KEYS[1], {"cameras": cams}).json()
    assert q["status"] == "queued"
    r = httpx.delete(f"{server.base}/v1/avatars/{q['avatar_id']}", headers={"Authorization": f"Bearer {q['token']}"})
    assert r.status_code == 204
    st = _status(server, q)
    assert st["status"] == "failed" and st["error"]["code"] == "avatar_deleted"
    assert _status(server, slow)["status"] == "running"  # the running one goes on
    _wait(server, slow, lambda s: s["status"] in ("ready", "failed"))
    assert not list((server.data / "avatars").glob(f"{q['avatar_id']}*"))


def test_failed_job_reports_the_error_naming_the_file(server, samples, tmp_path):
    files, cams = _sample_parts(samples)
    files[2] = ("images", ("IMG_0042.jpg", files[2][1][1][: len(files[2][1][1]) // 3], "image/jpeg"))  # truncated: fails decoding
    r = _post(server, files, KEYS[2], {"cameras": cams})
    assert r.status_code == 202, r.text  # its header is intact: the request queues, decoding fails
    job = r.json()
    st = _wait(server, job, lambda s: s["status"] in ("ready", "failed"))
    assert st["status"] == "failed" and st["progress"] < 1.0, st
    err = st["error"]
    assert err["status"] == 400 and err["code"] == "invalid_image", err
    assert "IMG_0042.jpg" in err["message"] and "0x" not in err["message"] and "image 2" not in err["message"], err
    h = {"Authorization": f"Bearer {job['token']}"}
    assert httpx.get(f"{server.base}/v1/avatars/{job['avatar_id']}", headers=h).status_code == 404
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    with connect(f"{server.ws_base}/v1/avatars/{job['avatar_id']}/stream?token={job['token']}") as ws:
        last = json.loads(ws.recv(timeout=30))
        assert last["type"] == "progress" and last["status"] == "failed" and last["error"]["code"] == "invalid_image"
        with pytest.raises(ConnectionClosed) as ei:
            ws.recv(timeout=30)
    assert ei.value.rcvd.code == 4404 and ei.value.rcvd.reason == "creation_failed: invalid_image"
    # the Python client sends paths under their own names and raises the job's error as a CreationError
    broken = tmp_path / "IMG_0042.jpg"
    broken.write_bytes(files[2][1][1])
    paths = [samples / "00.jpg", samples / "01.jpg", broken, samples / "03.jpg"]
    with pytest.raises(CreationError, match="IMG_0042.jpg") as ei:
        FastGHAClient(server.base, api_key=KEYS[2]).create_avatar(paths, json.loads(cams))
    assert ei.value.code == "invalid_image"
    bad = [("images", ("IMG_0042.jpg", b"\x89PNG\r\n\x1a\n garbage", "image/png"))]
    r = _post(server, bad, KEYS[2], {"cameras": json.dumps(json.loads(cams)[:1])})
    assert r.status_code == 400 and "IMG_0042.jpg" in r.json()["error"]["message"] and "BytesIO" not in r.text


def test_python_client_shows_progress_and_sync_form_still_answers_201(server, samples):
    client = FastGHAClient(server.base, api_key=KEYS[1])
    seen: list[dict] = []
    av = client.create_avatar_from_dir(samples, progress=seen.append)
    assert av.num_gaussians > 0 and av.token
    assert seen and seen[-1]["status"] == "ready" and all(s["stage"] in STAGES for s in seen)
    assert [s["progress"] for s in seen] == sorted(s["progress"] for s in seen)
    client.delete(av)
    files, cams = _sample_parts(samples)
    r = _post(server, files, KEYS[1], {"cameras": cams}, prefer_async=False)
    assert r.status_code == 201 and set(r.json()) >= {"avatar_id", "token", "num_gaussians", "reconstruction_ms", "expression_space"}


def test_a_slow_upload_holds_its_place_and_a_vanished_one_gives_it_back(server, samples):
    """Admission happens before the body is read; a client that disconnects frees its place."""
    s = socket.create_connection(("127.0.0.1", server.port))
    s.sendall(b"POST /v1/avatars HTTP/1.1\r\nHost: x\r\nX-API-Key: " + KEYS[2].encode()
              + b"\r\nContent-Type: multipart/form-data; boundary=b\r\nContent-Length: 100000\r\n\r\n--b\r\n")  # fmt: skip
    deadline = time.monotonic() + 30
    while _metric(server, "waiting") < 1 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert _metric(server, "waiting") == 1
    files, cams = _sample_parts(samples)
    r = _post(server, files, KEYS[2], {"cameras": cams})
    assert r.status_code == 429 and r.json()["error"]["code"] == "too_many_jobs"
    s.close()
    while _metric(server, "waiting") > 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert _metric(server, "waiting") == 0
    assert _post(server, files, KEYS[2], {"cameras": cams}, prefer_async=False).status_code == 201
    assert server.alive()


def test_a_job_reported_ready_survives_kill_9(model_dir, samples, tmp_path):
    import signal

    from websockets.sync.client import connect

    data = tmp_path / "data"
    # no refinement: what is checked is the stored avatar's survival, and the 60 default steps (with the
    # expression fit before them) were most of this test's time; the default path is tested end to end
    # in test_server.py and test_clients.py
    srv = ServerProcess(model_dir, data, None, tmp_path / "a.log", FASTGHA_API_KEYS=",".join(KEYS), FASTGHA_WARMUP="false",
                        FASTGHA_REFINE_STEPS="0")  # fmt: skip
    try:
        files, cams = _sample_parts(samples)
        job = _post(srv, files, KEYS[0], {"cameras": cams}).json()
        st = _wait(srv, job, lambda s: s["status"] in ("ready", "failed"))
        assert st["status"] == "ready", st
    finally:
        srv.stop(signal.SIGKILL)  # the moment it said ready
    srv = ServerProcess(model_dir, data, None, tmp_path / "b.log", FASTGHA_API_KEYS=",".join(KEYS), FASTGHA_WARMUP="false")
    try:
        after = _status(srv, job)  # no job in memory any more: the status comes from the stored avatar
        assert after["status"] == "ready" and after["avatar"]["num_gaussians"] == st["avatar"]["num_gaussians"]
        assert set(after) == set(st) and after["elapsed_ms"] is None  # same fields; the job's clock died with it
        assert after["avatar"] == st["avatar"]  # the 201 body without the token, from the stored metadata
        with connect(f"{srv.ws_base}/v1/avatars/{job['avatar_id']}/stream?token={job['token']}") as ws:
            assert json.loads(ws.recv(timeout=60))["type"] == "ready"
    finally:
        srv.stop()


def test_created_fields_keep_every_stage_time_of_the_stored_metadata():
    """The ready status rebuilt from an avatar's stored metadata (the job gone from memory) carries
    what the 201 body carried: every stage's time, refining_ms included, and same_person; not the
    token's hash or the storage-only keys."""
    from server.jobs import created_fields

    meta = {"avatar_id": "a", "token_sha256": "x", "model": "tiny", "expression_space": "ict53", "num_gaussians": 10,
            "num_images": 4, "reconstruction_ms": 1.5, "created_at": 0.0, "tracking_ms": 2.5, "refining_ms": 3547.9,
            "same_person": {"checked": False}, "view_blend_views": 4}  # fmt: skip
    assert created_fields(meta) == {"avatar_id": "a", "num_gaussians": 10, "reconstruction_ms": 1.5, "expression_space": "ict53",
                                    "tracking_ms": 2.5, "refining_ms": 3547.9, "same_person": {"checked": False}}  # fmt: skip


# ---------------------------------------------------------------- memory (issue 18 item 1)
def bomb_png(side: int = 4096, level: int = 200) -> bytes:
    """A greyscale PNG of one grey level, ``side`` x ``side``: 22.5 KB at 4096 (deflate at its limit)."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    raw = (b"\x00" + bytes([level]) * side) * side  # filter byte 0 + one row
    ihdr = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)  # 8-bit greyscale
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b"")


def _rss_peak_growth(pid: int, fn) -> float:
    def field(name: str) -> int:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(name + ":"):
                return int(line.split()[1]) * 1024
        raise KeyError(name)

    before = field("VmRSS")
    Path(f"/proc/{pid}/clear_refs").write_text("5")  # reset the peak (VmHWM) to the current RSS
    fn()
    return (field("VmHWM") - before) / 2**20


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="needs Linux /proc peak-RSS reset")
def test_decompression_amplification_is_bounded(model_dir, tmp_path):
    """Eight 22 KB PNGs decoding to 4096 x 4096 per request, three requests at once (default limits)."""
    from fastgha_core.cameras import cameras_to_json, orbit_cameras

    png = bomb_png()
    assert len(png) < 25_000 and Image.open(io.BytesIO(png)).size == (4096, 4096)
    files = [("images", (f"bomb{i}.png", png, "image/png")) for i in range(8)]
    cams = json.dumps(cameras_to_json(orbit_cameras(8, width=4096, height=4096)))
    srv = ServerProcess(model_dir, tmp_path / "data", None, tmp_path / "server.log", FASTGHA_API_KEYS=",".join(KEYS))
    try:
        codes: list[int] = []

        def three():
            with cf.ThreadPoolExecutor(3) as ex:
                codes.extend(ex.map(lambda k: _post(srv, files, k, {"cameras": cams}, prefer_async=False).status_code, KEYS))

        growth = _rss_peak_growth(srv.proc.pid, three)
        assert codes == [201, 201, 201], codes
        assert growth < 600, f"peak RSS grew by {growth:.0f} MB"  # was 4.5 GB before decoding moved into the queue
    finally:
        srv.stop()


# ---------------------------------------------------------------- the extra-stage hook (test-time refinement plugs in here)
def _sample_request(samples: Path) -> CreationRequest:
    """The sample folder's photos, masks and cameras as a checked ``CreationRequest``."""
    from fastgha_core.cameras import cameras_from_json

    imgs = sorted(samples.glob("[0-9][0-9].jpg"))
    photos = [Photo(p.name, p.read_bytes()) for p in imgs]
    masks = [Photo(f"{p.stem}_mask.png", (samples / f"{p.stem}_mask.png").read_bytes()) for p in imgs]
    cams = cameras_from_json(json.loads((samples / "cameras.json").read_text()))
    probe_request(photos, masks, cams, max_pixels=10**7, max_request_pixels=10**8)
    return CreationRequest(photos, masks, cams)


def _run_job(ctx, request, extra_stages, tracker=None) -> tuple:
    """Run one creation through an in-process ``JobQueue``; ``(job, [(stage, fraction, progress)]`` of
    every update (watchers may see them coalesced)."""
    import asyncio

    from server.jobs import JobQueue

    async def run():
        q = JobQueue(ctx, tracker=tracker, extra_stages=extra_stages)
        await q.start()
        try:
            job, _ = q.submit(q.reserve("test", 1), request)
            seen = []
            update = job.update
            job.update = lambda st, f: (update(st, f), seen.append((job.stage, job.stage_fraction, job.progress)))
            await q.wait(job)
            return job, seen
        finally:
            await q.stop()

    return asyncio.run(run())


def test_an_extra_stage_sees_the_prepared_inputs_reports_progress_and_replaces_the_avatar(model_dir, samples, tmp_path):
    """``JobQueue(extra_stages=[("refining", fn)])`` in-process with a real model and store."""
    import dataclasses

    from fastgha_core import load_model
    from fastgha_core.model.avatar import CanonicalAvatar
    from server.context import ServerContext
    from server.settings import Settings
    from server.store import AvatarStore

    ctx = ServerContext(settings=Settings(data_dir=tmp_path, warmup=False))
    ctx.model = load_model(str(model_dir), device="cpu")
    ctx.store = AvatarStore(tmp_path, 10**9, 0, load_fn=CanonicalAvatar.load)
    seen: dict = {}

    def refine(state, fraction) -> None:
        seen.update(images=tuple(state.images.shape), masks=tuple(state.masks.shape), views=len(state.cameras.K),
                    size=(state.cameras.width, state.cameras.height), names=list(state.names), n=len(state.avatar.gaussians))  # fmt: skip
        fraction(0.5)
        g = state.avatar.gaussians
        state.avatar = dataclasses.replace(state.avatar, gaussians=dataclasses.replace(g, colors=torch.full_like(g.colors, 0.25)))

    request = _sample_request(samples)
    job, updates = _run_job(ctx, request, [("refining", refine)])
    stages = [(st, p) for st, _, p in updates]
    assert job.status == "ready", job.error and job.error.message
    s = ctx.model.config.input_size
    assert seen["images"] == (4, 3, s, s) and seen["masks"] == (4, 1, s, s) and seen["views"] == 4 and seen["size"] == (s, s)
    assert seen["names"] == [p.name for p in request.images]
    assert job.stages == ["queued", "decoding", "reconstructing", "refining", "saving"]
    assert "refining" in [st for st, _ in stages] and [p for _, p in stages] == sorted(p for _, p in stages)
    meta = ctx.store.get_meta(job.id)
    assert meta["num_gaussians"] == seen["n"] == job.result["num_gaussians"] and "refining_ms" in meta
    stored = ctx.store.get(job.id).avatar.gaussians
    assert torch.all(stored.colors == 0.25)  # the stage's avatar is what was saved


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="SCHED_IDLE and per-thread nice values are Linux's")
@pytest.mark.parametrize("sched_idle", [True, False])
def test_creation_threads_give_the_cpu_to_render_threads(model_dir, samples, tmp_path, sched_idle):
    """A job's work runs under SCHED_IDLE (default) or at ``creation_nice``; the threads it starts
    (torch's OpenMP team) inherit it, and the server's other threads keep the normal policy."""
    from fastgha_core import load_model
    from fastgha_core.model.avatar import CanonicalAvatar
    from server.context import ServerContext
    from server.settings import Settings
    from server.store import AvatarStore

    ctx = ServerContext(settings=Settings(data_dir=tmp_path, warmup=False, creation_sched_idle=sched_idle, creation_nice=7))
    ctx.model = load_model(str(model_dir), device="cpu")
    ctx.store = AvatarStore(tmp_path, 10**9, 0, load_fn=CanonicalAvatar.load)
    seen: dict = {}

    def policy(tid: int) -> tuple[int, int]:
        return os.sched_getscheduler(tid), os.getpriority(os.PRIO_PROCESS, tid)

    def stage(state, fraction) -> None:
        torch.randn(512, 512) @ torch.randn(512, 512)  # a parallel region: this thread's OpenMP team exists
        seen["job"] = policy(0)
        seen["all"] = [policy(int(t)) for t in os.listdir("/proc/self/task")]

    base = policy(0)  # the test process's own (CI may run it niced)
    job, _ = _run_job(ctx, _sample_request(samples), [("refining", stage)])
    assert job.status == "ready", job.error and job.error.message
    want = (os.SCHED_IDLE, base[1]) if sched_idle else (os.SCHED_OTHER, max(base[1], 7))
    assert base[0] == os.SCHED_OTHER and seen["job"] == want
    if torch.get_num_threads() > 1:  # the job thread's OpenMP workers, started by it, inherit its policy
        assert seen["all"].count(want) >= torch.get_num_threads(), seen["all"]
    assert policy(0) == base  # this thread, like the server's render threads, untouched


def test_refine_steps_setting_plugs_test_time_refinement_into_the_job(model_dir, samples, tmp_path):
    """``FASTGHA_REFINE_STEPS`` > 0: the job runs ``fastgha_core.refine`` as its ``refining`` stage,
    reporting its steps, and stores the refined avatar; 0 adds no stage."""

    from fastgha_core import load_model
    from fastgha_core.cameras import cameras_from_json
    from fastgha_core.model.avatar import CanonicalAvatar
    from server.context import ServerContext
    from server.jobs import extra_stages_for
    from server.settings import Settings
    from server.store import AvatarStore

    assert extra_stages_for(ServerContext(settings=Settings(data_dir=tmp_path, warmup=False, refine_steps=0))) == []
    imgs = sorted(samples.glob("[0-9][0-9].jpg"))
    cams = cameras_from_json(json.loads((samples / "cameras.json").read_text()))
    model = load_model(str(model_dir), device="cpu")

    def create(steps: int, sub: str):
        ctx = ServerContext(settings=Settings(data_dir=tmp_path / sub, warmup=False, refine_steps=steps))
        ctx.model = model
        ctx.store = AvatarStore(tmp_path / sub, 10**9, 0, load_fn=CanonicalAvatar.load)
        photos = [Photo(p.name, p.read_bytes()) for p in imgs]
        masks = [Photo(f"{p.stem}_mask.png", (samples / f"{p.stem}_mask.png").read_bytes()) for p in imgs]

        job, updates = _run_job(ctx, CreationRequest(photos, masks, cams), extra_stages_for(ctx))
        seen = [(st, f) for st, f, _ in updates]
        assert job.status == "ready", job.error and job.error.message
        return ctx.store.get(job.id).avatar.gaussians, ctx.store.get_meta(job.id), job, seen

    g0, meta0, job0, _ = create(0, "plain")
    g2, meta2, job2, seen = create(2, "refined")
    assert "refining" not in job0.stages and "refining_ms" not in meta0
    assert "refining" in job2.stages and "refining_ms" in meta2
    fractions = [f for st, f in seen if st == "refining"]
    assert 0.5 in fractions and fractions == sorted(fractions)  # one update per step of the two
    from fastgha_core.model.prior import cheek_shell_vertices, load_basis

    k = len(cheek_shell_vertices(load_basis("ict53")))  # the refinement backs the cheeks it thinned (RefineConfig.cheek_shell)
    assert len(g2) == len(g0) + k and not torch.allclose(g2.colors[:1000], g0.colors[:1000])  # the refined avatar is the one stored


def test_refine_steps_auto_refines_every_avatar_with_the_preset_that_fits_it(model_dir, samples, tmp_path, monkeypatch):
    """``FASTGHA_REFINE_STEPS=auto`` (the default): photos the server tracks (an avatar on the tracked
    head) are refined with ``REFINE_PRESETS["photos"]`` and their tracked expressions: colours change,
    opacities and the Gaussian count do not. Photos with cameras (the network's depth) are refined
    with ``REFINE_PRESETS["default"]`` and the expressions fitted through their cameras, fitted only
    then (once) and only for them."""
    import numpy as np

    import fastgha_core.refine as refine_module
    from fastgha_core import load_model
    from fastgha_core.refine import REFINE_PRESETS
    from fastgha_core.cameras import Cameras, cameras_from_json
    from fastgha_core.model.avatar import CanonicalAvatar
    from fastgha_core.model.surface import HeadSurface
    from server.context import ServerContext
    from server.jobs import extra_stages_for
    from server.settings import Settings
    from server.store import AvatarStore

    monkeypatch.delenv("FASTGHA_REFINE_STEPS", raising=False)
    assert Settings(data_dir=tmp_path, warmup=False).refine_steps == "auto"
    assert Settings(data_dir=tmp_path, warmup=False, refine_steps="7").refine_steps == 7
    with pytest.raises(ValueError, match="refine_steps must be auto or a number of steps 0-1000"):
        Settings(data_dir=tmp_path, warmup=False, refine_steps="many")
    imgs = sorted(samples.glob("[0-9][0-9].jpg"))
    cams = cameras_from_json(json.loads((samples / "cameras.json").read_text()))
    expr = np.zeros((len(imgs), 53))
    expr[:, 0] = 0.2
    fitted = np.zeros((len(imgs), 53))
    fitted[:, 1] = 0.3
    fits = []

    class Tracker:  # stands in for server.tracking.PhotoTracker: the sample's own cameras, a generic head
        def track(self, images, masks, size, names=None):
            crops = torch.stack([im for im in images])
            ones = torch.ones(len(imgs), 1, *crops.shape[-2:])
            return crops, Cameras.stack([cams[i] for i in range(len(imgs))]), ones, torch.from_numpy(expr).float(), HeadSurface(np.zeros(100), expr)

        def fit_known_cameras(self, images, cameras, names=None, masks=None):
            fits.append((len(images), len(cameras), names))
            return HeadSurface(np.zeros(100), fitted)

    calls = []  # (preset steps, lr_opacity, expressions) of every refinement
    real_refine = refine_module.refine_avatar

    def spy(model, avatar, images, cameras, masks=None, *, config, expressions=None, **kw):
        calls.append((config.steps, config.lr_opacity, None if expressions is None else expressions.numpy().copy()))
        return real_refine(model, avatar, images, cameras, masks, config=config, expressions=expressions, **kw)

    monkeypatch.setattr(refine_module, "refine_avatar", spy)
    model = load_model(str(model_dir), device="cpu")
    photos = [Photo(p.name, p.read_bytes()) for p in imgs]
    masks = [Photo(f"{p.stem}_mask.png", (samples / f"{p.stem}_mask.png").read_bytes()) for p in imgs]
    stored = {}
    for refine in (0, "auto"):
        for kind, req in (("tracked", CreationRequest(photos, None, None)), ("cameras", CreationRequest(photos, masks, cams))):
            ctx = ServerContext(settings=Settings(data_dir=tmp_path / f"{kind}{refine}", warmup=False, refine_steps=refine))
            ctx.model = model
            ctx.store = AvatarStore(tmp_path / f"{kind}{refine}", 10**9, 0, load_fn=CanonicalAvatar.load)
            fits.clear()
            calls.clear()
            job, _ = _run_job(ctx, req, extra_stages_for(ctx), tracker=Tracker())
            assert job.status == "ready", job.error and job.error.message
            assert ("refining" in job.stages) == (refine == "auto"), (kind, refine, job.stages)
            assert ("refining_ms" in job.result) == ("refining" in job.stages)
            assert len(fits) == int(refine == "auto" and kind == "cameras"), (kind, refine, fits)
            if refine == "auto":
                (steps, lr_opacity, used), = calls
                preset = REFINE_PRESETS["photos" if kind == "tracked" else "default"]
                assert (steps, lr_opacity) == (preset.steps, preset.lr_opacity)
                np.testing.assert_allclose(used, expr if kind == "tracked" else fitted, atol=1e-6)
            stored[kind, refine] = ctx.store.get(job.id).avatar
    assert fits[0][:2] == (len(imgs), len(imgs))  # the last creation's fit (cameras, auto): every photo with its camera
    plain, refined = stored["tracked", 0], stored["tracked", "auto"]
    assert plain.view_blend is not None and len(refined.gaussians) == len(plain.gaussians)
    assert torch.equal(refined.gaussians.opacities, plain.gaussians.opacities)
    assert float((refined.gaussians.colors - plain.gaussians.colors).abs().max()) > 1e-3
    assert stored["cameras", 0].view_blend is None
    a, b = stored["cameras", "auto"].gaussians, stored["cameras", 0].gaussians
    assert len(a) != len(b) or float((a.colors - b.colors).abs().max()) > 1e-3  # the refined avatar is the one stored


@pytest.mark.parametrize("surface_depth", [True, False])
def test_tracked_photos_are_reconstructed_on_the_tracked_head(model_dir, samples, tmp_path, surface_depth):
    """Photos without cameras: the job hands the tracker's head surface to ``reconstruct`` (unless
    ``FASTGHA_SURFACE_DEPTH=0``), and the avatar's Gaussians then lie on that head."""
    import numpy as np

    from fastgha_core import load_model
    from fastgha_core.cameras import cameras_from_json
    from fastgha_core.model.avatar import CanonicalAvatar
    from fastgha_core.model.surface import HeadSurface
    from server.context import ServerContext
    from server.settings import Settings
    from server.store import AvatarStore

    imgs = sorted(samples.glob("[0-9][0-9].jpg"))
    cams = cameras_from_json(json.loads((samples / "cameras.json").read_text()))
    surface = HeadSurface(np.zeros(100), np.zeros((len(imgs), 53)))

    class Tracker:  # stands in for server.tracking.PhotoTracker: the sample's own cameras, a generic head
        def track(self, images, masks, size, names=None):
            crops = torch.stack([im for im in images])
            return crops, Cameras.stack([cams[i] for i in range(len(imgs))]), torch.ones(len(imgs), 1, *crops.shape[-2:]), torch.zeros(len(imgs), 53), surface

    from fastgha_core.cameras import Cameras

    ctx = ServerContext(settings=Settings(data_dir=tmp_path, warmup=False, surface_depth=surface_depth))
    ctx.model = load_model(str(model_dir), device="cpu")
    ctx.store = AvatarStore(tmp_path, 10**9, 0, load_fn=CanonicalAvatar.load)
    got = []
    recon = ctx.model.reconstruct
    ctx.model.reconstruct = lambda *a, **k: (got.append(k.get("surface")), recon(*a, **k))[1]
    photos = [Photo(p.name, p.read_bytes()) for p in imgs]
    job, _ = _run_job(ctx, CreationRequest(photos, None, None), [], tracker=Tracker())
    assert job.status == "ready", job.error and job.error.message
    assert job.stages[:3] == ["queued", "decoding", "tracking"]
    assert got == [surface if surface_depth else None]
    if surface_depth:  # the stored avatar's prior is bound to the tracked (generic) head, not an ICP fit
        stored = ctx.store.get(job.id).avatar
        assert stored.prior is not None and torch.allclose(stored.prior.transform, torch.eye(4))
        assert float(stored.prior.identity.abs().max()) == 0.0


@pytest.mark.parametrize("mode", ["off", "blend"])
def test_photos_with_cameras_use_the_head_fitted_through_them(model_dir, samples, tmp_path, mode):
    """Photos WITH cameras: with ``FASTGHA_SURFACE_DEPTH_CAMERAS`` on, the job fits the head through
    the given cameras (``PhotoTracker.fit_known_cameras``) and reconstructs on it in that mode, its
    prior bound to the fitted head -> world transform; off, nothing is fitted."""
    import numpy as np

    from fastgha_core import load_model
    from fastgha_core.cameras import cameras_from_json
    from fastgha_core.model.avatar import CanonicalAvatar
    from fastgha_core.model.surface import HeadSurface
    from server.context import ServerContext
    from server.settings import Settings
    from server.store import AvatarStore

    imgs = sorted(samples.glob("[0-9][0-9].jpg"))
    cams = cameras_from_json(json.loads((samples / "cameras.json").read_text()))
    G = np.eye(4)
    G[:3, 3] = [0.0, 0.004, -0.003]
    surface = HeadSurface(np.zeros(100), np.zeros((len(imgs), 53)), G)
    calls = []

    class Tracker:  # stands in for server.tracking.PhotoTracker
        def fit_known_cameras(self, images, cameras, names=None, masks=None):
            calls.append((len(images), [(c.width, c.height) for c in cameras], [tuple(im.shape[-2:]) for im in images]))
            assert masks is not None and [tuple(m.shape[-2:]) for m in masks] == [tuple(im.shape[-2:]) for im in images]
            return surface

    ctx = ServerContext(settings=Settings(data_dir=tmp_path, warmup=False, surface_depth_cameras=mode))
    ctx.model = load_model(str(model_dir), device="cpu")
    ctx.store = AvatarStore(tmp_path, 10**9, 0, load_fn=CanonicalAvatar.load)
    got = []
    recon = ctx.model.reconstruct
    ctx.model.reconstruct = lambda *a, **k: (got.append((k.get("surface"), k.get("surface_mode"))), recon(*a, **k))[1]
    photos = [Photo(p.name, p.read_bytes()) for p in imgs]
    masks = [Photo(f"{p.stem}_mask.png", (samples / f"{p.stem}_mask.png").read_bytes()) for p in imgs]
    job, _ = _run_job(ctx, CreationRequest(photos, masks, cams), [], tracker=Tracker())
    assert job.status == "ready", job.error and job.error.message
    assert "tracking" not in job.stages
    if mode == "off":
        assert calls == [] and got == [(None, "replace")]
    else:
        # the full-size photos with their own cameras, one per photo
        assert len(calls) == 1 and calls[0][0] == len(imgs) and all((w, h) == (hh[1], hh[0]) for (w, h), hh in zip(calls[0][1], calls[0][2]))
        assert got == [(surface, "blend")]
        stored = ctx.store.get(job.id).avatar
        assert stored.prior is not None and torch.allclose(stored.prior.transform.double(), torch.from_numpy(G), atol=1e-6)


# ---------------------------------------------------------------- a tracked head sent with the cameras (the `head` part)
def _head_folder(samples: Path, dst: Path, seed: int = 3) -> tuple[Path, dict]:
    """A copy of the sample request folder as `fastgha track` leaves one: photos, masks, cameras.json,
    expressions.json and head.json (a small random identity, mild expressions); ``(folder, the head part)``."""
    import shutil

    from fastgha_core.expressions import ICT53_NAMES

    shutil.copytree(samples, dst)
    imgs = sorted(p.name for p in dst.glob("[0-9][0-9].jpg"))
    rng = np.random.default_rng(seed)
    ident = np.zeros(100)
    ident[:20] = rng.standard_normal(20) * 0.5
    expr = (rng.uniform(0.0, 0.3, (len(imgs), 53))).round(4)
    frames = [[0.0, 0.0, 1.0, 1.0] if i % 2 else [0.0, -0.1, 0.85, 1.0] for i in range(len(imgs))]  # each photo's frame: some padding right and top
    (dst / "head.json").write_text(json.dumps({"model": "ict_facekit", "identity": ident.round(5).tolist(), "frames": dict(zip(imgs, frames))}))
    (dst / "expressions.json").write_text(json.dumps({"space": "ict53", "names": list(ICT53_NAMES), "images": imgs, "expressions": expr.tolist()}))
    return dst, {"model": "ict_facekit", "identity": ident.round(5).tolist(), "frames": frames, "expressions": expr.tolist()}


def _head_distance(avatar, head_part: dict) -> float:
    """Median distance (m) of the avatar's reconstructed Gaussians to the head mesh of the first view."""
    from scipy.spatial import cKDTree

    from fastgha_core.model.surface import HeadSurface

    surf = HeadSurface(np.asarray(head_part["identity"]), np.asarray(head_part["expressions"]))
    means = avatar.gaussians.means[: avatar.num_reconstructed].numpy()
    d, _ = cKDTree(surf.vertices(0)).query(means)
    return float(np.median(d))


def test_a_sent_head_is_reconstructed_on_exactly_as_fastgha_reconstruct_does(model_dir, samples, tmp_path):
    """``CreationRequest(head=...)`` (the ``head`` part): the job reconstructs on the sent head with
    the photos' expressions, giving the avatar `fastgha reconstruct` makes of the same tracked folder
    (same Gaussians, prior bound to the head); without it (cameras only) the Gaussians follow the
    network's depth, off the head."""
    from fastgha_core import load_model
    from fastgha_core.cameras import cameras_from_json
    from fastgha_core.cli import main
    from fastgha_core.model.avatar import CanonicalAvatar
    from server.context import ServerContext
    from server.protocol import parse_head_json
    from server.settings import Settings
    from server.store import AvatarStore

    folder, head_part = _head_folder(samples, tmp_path / "tracked")
    imgs = sorted(folder.glob("[0-9][0-9].jpg"))
    model = load_model(str(model_dir), device="cpu")

    def create(head):
        data = tmp_path / ("head" if head is not None else "cams")
        ctx = ServerContext(settings=Settings(data_dir=data, warmup=False))
        ctx.model = model
        ctx.store = AvatarStore(data, 10**9, 0, load_fn=CanonicalAvatar.load)
        photos = [Photo(p.name, p.read_bytes()) for p in imgs]
        masks = [Photo(f"{p.stem}_mask.png", (folder / f"{p.stem}_mask.png").read_bytes()) for p in imgs]
        cams = cameras_from_json(json.loads((folder / "cameras.json").read_text()))
        probe_request(photos, masks, cams, max_pixels=10**7, max_request_pixels=10**8)
        job, _ = _run_job(ctx, CreationRequest(photos, masks, cams, head), [])
        assert job.status == "ready", job.error and job.error.message
        assert "tracking" not in job.stages
        return ctx.store.get(job.id).avatar

    with_head = create(parse_head_json(json.dumps(head_part), len(imgs)))
    cams_only = create(None)
    assert main(["reconstruct", "--input", str(folder), "--model", str(model_dir), "--out", str(tmp_path / "cli.safetensors")]) == 0
    cli = CanonicalAvatar.load(tmp_path / "cli.safetensors")
    n = with_head.num_reconstructed
    assert n == cli.num_reconstructed and len(with_head.gaussians) == len(cli.gaussians)
    torch.testing.assert_close(with_head.gaussians.means, cli.gaussians.means, atol=1e-5, rtol=0)
    torch.testing.assert_close(with_head.gaussians.colors, cli.gaussians.colors, atol=1e-5, rtol=0)
    k = with_head.prior.identity.shape[0]
    np.testing.assert_allclose(with_head.prior.identity.numpy(), np.asarray(head_part["identity"][:k]), atol=1e-5)
    on, off = _head_distance(with_head, head_part), _head_distance(cams_only, head_part)
    assert on < 0.01 and off > 2 * on, (on, off)  # on the sent head; the network's depth lies elsewhere


def test_head_part_validation_names_the_part_and_what_was_expected():
    from server.protocol import ProtocolError, parse_head_json

    good = {"model": "ict_facekit", "identity": [0.1] * 100, "expressions": [[0.0] * 53, [0.2] * 53]}
    assert len(parse_head_json(json.dumps(good), 2)) == 2 and parse_head_json(json.dumps(good), 2).frames is None
    framed = parse_head_json(json.dumps({**good, "frames": [[0.0, -0.1, 1.0, 1.0], [0.1, 0.0, 0.9, 1.2]]}), 2)
    assert np.allclose(framed.frames, [[0.0, -0.1, 1.0, 1.0], [0.1, 0.0, 0.9, 1.2]])
    cases = [
        ("{not json", "invalid_json", "head is not valid JSON"),
        (json.dumps([1, 2]), "invalid_head", "expected a JSON object"),
        (json.dumps({**good, "model": "flame"}), "invalid_head", "expected \"model\": \"ict_facekit\""),
        (json.dumps({"expressions": good["expressions"]}), "invalid_head", "expected an 'identity' list"),
        (json.dumps({**good, "identity": [0.0] * 101}), "invalid_head", "1 to 100"),
        (json.dumps({**good, "identity": [50.0] * 100}), "invalid_head", "must lie in [-10, 10]"),
        (json.dumps({**good, "identity": ["a"] * 100}), "invalid_head", "list of numbers, got a list holding str"),
        (json.dumps({k: v for k, v in good.items() if k != "expressions"}), "invalid_head", "expected an 'expressions' list"),
        (json.dumps({**good, "expressions": [[0.0] * 52, [0.0] * 53]}), "invalid_head", "expressions[0] must be a list of 53 ict53 weights, got 52"),
        (json.dumps({**good, "expressions": [[2.0] * 53, [0.0] * 53]}), "invalid_head", "must lie in [0, 1]"),
        (json.dumps({**good, "expressions": [[0.0] * 53]}), "head_count_mismatch", "head: expressions for 1 photo(s) but 2 images came"),
        (json.dumps({**good, "frames": [[0.0, 0.0, 1.0, 1.0]]}), "invalid_head", "frames must hold one [left, top, right, bottom] per photo (2), got 1 entries"),
        (json.dumps({**good, "frames": [[0.0, 0.0, 1.0, 1.0], [0.5, 0.0, 0.4, 1.0]]}), "invalid_head", "right > left and bottom > top"),
        (json.dumps({**good, "frames": [[0.0, 0.0, 1.0, 1.0], [0.0, 0.0, 1.0]]}), "invalid_head", "frames[1] must be [left, top, right, bottom] (4 numbers, fractions of the crop), got 3 value(s)"),
        (json.dumps({**good, "frames": {"a.png": [0.0, 0.0, 1.0, 1.0]}}), "invalid_head", "frames by file name need the photos' names"),
        ('{"identity": [NaN], "expressions": [[0.0]]}', "non_finite_number", "head: JSON numbers must be finite"),
    ]
    for text, code, words in cases:
        with pytest.raises(ProtocolError) as e:
            parse_head_json(text, 2)
        assert e.value.code == code and words in e.value.message, (text[:40], e.value.code, e.value.message)
        assert e.value.message.startswith("head"), e.value.message


def test_server_takes_a_head_with_the_cameras_and_refuses_malformed_ones(server, samples, tmp_path):
    """``POST /v1/avatars`` with a ``head`` part: 201 and the stored avatar's prior is bound to the
    sent head; documented 400s for a head without cameras, malformed heads and a wrong count."""
    from fastgha_core.model.avatar import CanonicalAvatar

    folder, head_part = _head_folder(samples, tmp_path / "tracked")
    files, cams = _sample_parts(folder)
    files += [("masks", (p.name, p.read_bytes(), "image/png")) for p in sorted(folder.glob("[0-9][0-9]_mask.png"))]  # as a tracked folder has
    r = _post(server, files, KEYS[0], data={"cameras": cams, "head": json.dumps(head_part)}, prefer_async=False)
    assert r.status_code == 201, r.text
    stored = CanonicalAvatar.load(server.data / "avatars" / f"{r.json()['avatar_id']}.safetensors")
    k = stored.prior.identity.shape[0]
    np.testing.assert_allclose(stored.prior.identity.numpy(), np.asarray(head_part["identity"][:k]), atol=1e-5)
    assert _head_distance(stored, head_part) < 0.01
    bad = [
        ({"head": json.dumps(head_part)}, "head_without_cameras", "send the 'cameras' part too"),
        ({"cameras": cams, "head": "{"}, "invalid_head", "head is not valid JSON (Expecting property name"),
        ({"cameras": cams, "head": json.dumps({**head_part, "model": "flame"})}, "invalid_head", "ict_facekit"),
        ({"cameras": cams, "head": json.dumps({**head_part, "expressions": head_part["expressions"][:2], "frames": head_part["frames"][:2]})}, "head_count_mismatch", "but 4 images came"),
        ({"cameras": cams, "head": json.dumps({**head_part, "frames": head_part["frames"][:3]})}, "invalid_head", "frames must hold one [left, top, right, bottom] per photo (4), got 3"),
    ]
    for data, code, words in bad:
        r = _post(server, files, KEYS[1], data=data)
        assert r.status_code == 400 and r.json()["error"]["code"] == code and words in r.json()["error"]["message"], r.text


def test_python_client_sends_a_tracked_folders_head(server, samples, tmp_path, monkeypatch):
    """``create_avatar_from_dir`` / ``fastgha client --input`` send head.json with each photo's tracked
    expression, in the photos' order; a head.json without expressions.json is refused before any upload."""
    from client_demo.client import load_head, load_request_dir

    folder, head_part = _head_folder(samples, tmp_path / "tracked")
    images, cams, _ = load_request_dir(folder)
    assert load_head(folder, images) == head_part
    assert load_head(samples, images) is None  # no head.json: cameras only, as before
    sent = []
    post = httpx.post
    monkeypatch.setattr(httpx, "post", lambda url, **kw: (sent.append(kw.get("data")), post(url, **kw))[1])
    client = FastGHAClient(server.base, api_key=KEYS[2])
    avatar = client.create_avatar_from_dir(folder)
    assert json.loads(sent[-1]["head"]) == head_part and len(json.loads(sent[-1]["cameras"])) == 4
    from fastgha_core.model.avatar import CanonicalAvatar

    stored = CanonicalAvatar.load(server.data / "avatars" / f"{avatar.avatar_id}.safetensors")
    assert _head_distance(stored, head_part) < 0.01
    client.delete(avatar)
    (folder / "expressions.json").unlink()
    with pytest.raises(ValueError, match="head.json needs expressions.json"):
        load_head(folder, images)


def test_python_client_warns_and_sends_no_frames_when_a_photo_has_none(samples, tmp_path, caplog):
    """A photo added to a tracked folder after `fastgha track` has no frame in head.json: the client
    sends no frames (the server then reads every crop's border as the photo's) and says which photo."""
    import logging

    from client_demo.client import load_head, load_request_dir

    folder, head_part = _head_folder(samples, tmp_path / "tracked")
    images, _, _ = load_request_dir(folder)
    head = json.loads((folder / "head.json").read_text())
    del head["frames"][images[1].name]
    (folder / "head.json").write_text(json.dumps(head))
    with caplog.at_level(logging.WARNING, logger="client_demo.client"):
        part = load_head(folder, images)
    assert "frames" not in part and part["expressions"] == head_part["expressions"]
    assert images[1].name in caplog.text and images[0].name not in caplog.text


@needs_faces
def test_fastgha_client_sends_the_head_of_a_folder_fastgha_track_wrote(server, tmp_path, capsys):
    """The fresh-user path: `fastgha track` a photo, then `fastgha client --input` that folder: the
    server gets the tracked head with the cameras and the avatar lies on it (its prior bound to it)."""
    from fastgha_core.cli import main
    from fastgha_core.model.avatar import CanonicalAvatar

    photo = tmp_path / "gh.jpg"
    photo.write_bytes(_portrait())
    req = tmp_path / "me"
    assert main(["track", "--images", str(photo), "--out", str(req), "--size", "128"]) == 0
    tracked = json.loads((req / "expressions.json").read_text())
    head_part = {**json.loads((req / "head.json").read_text()), "expressions": tracked["expressions"]}
    out = tmp_path / "me.mp4"
    assert main(["client", "--url", server.base, "--input", str(req), "--out", str(out), "--frames", "2", "--size", "64",
                 "--api-key", KEYS[2], "--keep"]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert "sending the tracked head" in printed and out.is_file()
    aid = printed.split("avatar ", 1)[1].split(":", 1)[0]
    stored = CanonicalAvatar.load(server.data / "avatars" / f"{aid}.safetensors")
    k = stored.prior.identity.shape[0]
    np.testing.assert_allclose(stored.prior.identity.numpy(), np.asarray(head_part["identity"][:k]), atol=1e-4)
    from client_demo.client import load_request_dir

    images, cams, masks = load_request_dir(req)  # the same folder with its cameras only: the network's depth
    plain = FastGHAClient(server.base, api_key=KEYS[2]).create_avatar(images, cams, masks)
    off = CanonicalAvatar.load(server.data / "avatars" / f"{plain.avatar_id}.safetensors")
    on_d, off_d = _head_distance(stored, head_part), _head_distance(off, head_part)
    assert on_d < 0.5 * off_d, (on_d, off_d)


def test_events_of_a_ready_job_still_in_memory_match_its_status(server, samples):
    """docs/protocol.md: elapsed_ms is null only once the job is no longer in memory; the events of an
    avatar whose job finished moments ago carried the stored status (elapsed_ms null) while /status
    gave the job's own snapshot."""
    files, cams = _sample_parts(samples)
    deadline = time.monotonic() + 240
    while True:  # earlier tests may still hold this key's one job slot
        r = _post(server, files, KEYS[2], {"cameras": cams})
        if r.status_code not in (429, 503) or time.monotonic() > deadline:
            break
        time.sleep(0.5)
    assert r.status_code == 202, r.text
    job = r.json()
    st = _wait(server, job, lambda s: s["status"] in ("ready", "failed"))
    assert st["status"] == "ready" and st["elapsed_ms"] is not None and st["elapsed_ms"] > 0, st
    events: list = []
    _sse(server, job, events)
    assert [e[0] for e in events] == ["ready"]
    assert events[0][1] == _status(server, job) == st
