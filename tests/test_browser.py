"""End-to-end test of the browser demo in headless Chromium (Python playwright).

A real server process serves the demo at ``/`` (``server_process.py``: a 64 x 64 tiny model
whose deformation output layer is non-zero, and a synthetic sample subject). The page loads
the sample with one click, creates the avatar, receives frames, and the canvas must show a
picture that changes when an expression slider moves and when the camera is dragged. Other
tests create an avatar from one photo alone (the server tracks it) and watch the creation job's
progress, get the queue's 429 with its ``Retry-After``, check the page's small promises (issue
19 item 11), and move ``jawOpen`` on the shipped model to see the mouth region change.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import pytest

from server_process import API_KEY, SAMPLE_NAME, ServerProcess, make_model_dir, make_sample_dir
from extras import needs_faces

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--disable-quic"]  # fmt: skip

if not Path(CHROMIUM).exists():
    pytest.skip(f"needs Debian's chromium at {CHROMIUM} (not installed)", allow_module_level=True)
sync_api = pytest.importorskip("playwright.sync_api", reason="needs the Python package playwright")

pytestmark = pytest.mark.timeout(300)

# canvas statistics computed in the page: pixels (RGB, row-major) and their spread
_CANVAS_PIXELS = """() => {
  const c = document.getElementById('frame');
  const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
  const px = [];
  for (let i = 0; i < d.length; i += 4) px.push(d[i], d[i + 1], d[i + 2]);
  return {w: c.width, h: c.height, px};
}"""
# settled: a new frame was drawn, and it answers the last request sent (nothing in flight or pending)
_SETTLED = "() => { const s = window.fastghaDemo; return s.frames > %d && s.inFlight === null && !s.dirty && s.lastSeq === s.seq - 1; }"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    samples = tmp_path_factory.mktemp("samples")
    make_sample_dir(samples)
    model = make_model_dir(tmp_path_factory.mktemp("model"))
    srv = ServerProcess(model, tmp_path_factory.mktemp("data"), samples, tmp_path_factory.mktemp("logs") / "server.log",
                        FASTGHA_MAX_JOBS_PER_CLIENT="2")  # fmt: skip
    yield srv
    srv.stop()


@pytest.fixture()
def page(server):
    yield from _page_of(server)


def _page_of(server, viewport: dict | None = None, **context):
    profile = tempfile.mkdtemp(prefix="fastgha-chromium-")
    errors: list[str] = []
    with sync_api.sync_playwright() as p:
        ctx = p.chromium.launch_persistent_context(
            profile, executable_path=CHROMIUM, args=ARGS, headless=True, viewport=viewport or {"width": 1200, "height": 900}, accept_downloads=True,
            **context,
            bypass_csp=True,  # playwright's wait_for_function evals its predicate; the page under its CSP: test_server_hardening_e2e.py
        )
        try:
            pg = ctx.pages[0] if ctx.pages else ctx.new_page()
            pg.on("pageerror", lambda e: errors.append(str(e)))
            pg.goto(server.base + "/")
            yield pg
            assert not errors, f"JavaScript errors: {errors}"
        finally:
            ctx.close()
            shutil.rmtree(profile, ignore_errors=True)


def _pixels(page):
    import numpy as np

    r = page.evaluate(_CANVAS_PIXELS)
    return np.asarray(r["px"], dtype=np.int16).reshape(r["h"], r["w"], 3)


def _wait_settled(page, frames_before: int) -> None:
    page.wait_for_function(_SETTLED % frames_before, timeout=60_000)


def _load_sample(page, key: str = API_KEY) -> None:
    """Type ``key`` and load the shipped sample into the page, ready for "Create"."""
    page.wait_for_function("!document.getElementById('load-sample').disabled", timeout=30_000)
    page.fill("#api-key", key)
    page.click("#load-sample")
    page.wait_for_function("!document.getElementById('create').disabled", timeout=30_000)


def _stream_sample(page, timeout: int) -> None:
    """Load the sample, create its avatar and wait (``timeout`` ms) until its first frame settles."""
    _load_sample(page)
    page.click("#create")
    page.wait_for_function("window.fastghaDemo.frames >= 1", timeout=timeout)
    _wait_settled(page, 0)


def test_demo_streams_and_reacts_to_slider_and_camera(page, tmp_path):
    import numpy as np

    _load_sample(page)
    assert "4 photo(s), 4 camera(s), 4 mask(s)" in page.inner_text("#input-summary")
    assert page.locator("#thumbs img").count() == 4
    # sliders are named from GET /v1/model; the main ones first, the rest behind "more…"
    assert page.locator("#s-jawOpen").is_visible()
    assert not page.locator("#s-noseSneer_R").is_visible()
    page.click("#more-toggle")
    assert page.locator("#s-noseSneer_R").is_visible()

    page.click("#create")
    page.wait_for_function("window.fastghaDemo.frames >= 1", timeout=60_000)
    _wait_settled(page, 0)
    assert "reconstruction" in page.inner_text("#recon")
    assert "refinement" in page.inner_text("#recon")  # the shipped sample (photos with cameras) is refined by default
    # what the server reports about the avatar (docs/protocol.md): the sample comes with cameras, so no per-view data
    assert "view blending off (no per-view data" in page.inner_text("#recon") and "same person:" in page.inner_text("#recon")
    assert page.inner_text("#st-status") == "streaming"
    before = _pixels(page)
    assert before.shape == (256, 256, 3)
    assert before.std() > 3.0 and (np.abs(before - 255).sum(-1) > 30).mean() > 0.02  # a picture, not a blank canvas

    n = page.evaluate("window.fastghaDemo.frames")
    page.fill("#s-jawOpen", "1")
    page.fill("#s-mouthSmile_L", "1")
    _wait_settled(page, n)
    after = _pixels(page)
    assert np.abs(after - before).mean() > 0.5, "moving a slider did not change the picture"

    # drag on the canvas orbits the camera
    n = page.evaluate("window.fastghaDemo.frames")
    box = page.locator("#frame").bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(cx, cy)
    page.mouse.down()
    page.mouse.move(cx + 80, cy + 10, steps=4)
    page.mouse.up()
    _wait_settled(page, n)
    assert page.evaluate("window.fastghaDemo.cam.yaw") < 0
    orbited = _pixels(page)
    assert np.abs(orbited - after).mean() > 0.5, "dragging did not change the view"

    # latency and FPS are displayed; the PLY downloads with the bearer token
    assert page.inner_text("#st-lat") != "–"
    with page.expect_download() as dl:
        page.click("#download-ply")
    path = tmp_path / "avatar.ply"
    dl.value.save_as(path)
    assert path.read_bytes().startswith(b"ply")

    # a dropped connection (non-fatal close code) is reported and re-opened automatically
    page.evaluate("window.fastghaDemo.ws.close(4000, 'test drop')")
    page.wait_for_function("document.getElementById('messages').innerText.includes('reconnecting')", timeout=10_000)
    page.wait_for_function(
        "window.fastghaDemo.ws && window.fastghaDemo.reconnectAttempt === 0 && "
        "document.getElementById('st-status').innerText === 'streaming'",
        timeout=30_000,
    )
    n = page.evaluate("window.fastghaDemo.frames")
    page.fill("#s-jawOpen", "0.2")
    _wait_settled(page, n)
    assert np.abs(_pixels(page) - orbited).mean() > 0.5


def test_demo_reports_a_refused_api_key(page):
    _load_sample(page, key="wrong-key")
    page.click("#create")
    page.wait_for_function("document.getElementById('messages').innerText.includes('invalid_api_key')", timeout=30_000)
    assert page.evaluate("window.fastghaDemo.avatar") is None


# ---------------------------------------------------------------- photos alone, progress, the queue, page nits


def _portrait() -> bytes:
    import matplotlib.cbook as cbook

    return Path(cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)).read_bytes()


def _hold_places(server, n: int) -> list:
    """``n`` creation requests whose body never comes: each holds a place in the queue (admission
    happens before the body is read) until its socket closes."""
    import socket
    import time

    import httpx

    def waiting() -> float:
        for line in httpx.get(server.base + "/metrics").text.splitlines():
            if line.startswith('fastgha_creation_jobs{state="waiting"}'):
                return float(line.split()[-1])
        return -1.0

    base = waiting()
    socks = []
    for _ in range(n):
        s = socket.create_connection(("127.0.0.1", server.port))
        s.sendall(b"POST /v1/avatars HTTP/1.1\r\nHost: x\r\nX-API-Key: " + API_KEY.encode()
                  + b"\r\nContent-Type: multipart/form-data; boundary=b\r\nContent-Length: 100000\r\n\r\n--b\r\n")  # fmt: skip
        socks.append(s)
    deadline = time.monotonic() + 30
    while waiting() < base + n and time.monotonic() < deadline:
        time.sleep(0.05)
    assert waiting() == base + n
    return socks


@needs_faces
def test_demo_creates_an_avatar_from_one_photo_alone_and_shows_progress(page, server):
    import httpx

    page.wait_for_function("window.fastghaDemo.model !== null", timeout=30_000)
    page.fill("#api-key", API_KEY)
    page.set_input_files("#file-input", files=[{"name": "hopper.jpg", "mimeType": "image/jpeg", "buffer": _portrait()}])
    page.wait_for_function("!document.getElementById('create').disabled", timeout=10_000)
    assert "1 photo(s), no cameras" in page.inner_text("#input-summary")
    # a slower creation first (eight photos to track), so that the page's job waits in the queue
    files = [("images", (f"hopper{i}.jpg", _portrait(), "image/jpeg")) for i in range(8)]
    slow = httpx.post(server.base + "/v1/avatars", files=files, headers={"X-API-Key": API_KEY, "Prefer": "respond-async"}, timeout=60)
    assert slow.status_code == 202, slow.text
    page.click("#create")
    page.wait_for_function("document.getElementById('recon').innerText.includes('in the queue')", timeout=30_000)
    assert page.locator("#job-bar").is_visible()
    page.wait_for_function("window.fastghaDemo.frames >= 1", timeout=240_000)
    _wait_settled(page, 0)
    log = page.evaluate("window.fastghaDemo.progressLog")
    assert log[0]["status"] == "queued" and log[0]["queue_position"] == 1, log
    assert log[-1]["status"] == "ready" and log[-1]["progress"] == 1.0
    assert "tracking" in [e["stage"] for e in log] or "reconstructing" in [e["stage"] for e in log]
    assert [e["progress"] for e in log] == sorted(e["progress"] for e in log)
    assert "tracking" in page.inner_text("#recon") and "Gaussians" in page.inner_text("#recon")
    assert not page.locator("#job-bar").is_visible()
    assert _pixels(page).std() > 3.0


def test_demo_reports_a_full_queue_with_its_retry_time(page, server):
    _load_sample(page)
    socks = _hold_places(server, 2)  # this API key's share (FASTGHA_MAX_JOBS_PER_CLIENT=2)
    try:
        page.click("#create")
        page.wait_for_function("document.getElementById('messages').innerText.includes('too_many_jobs')", timeout=30_000)
        text = page.inner_text("#messages")
        assert "HTTP 429" in text and "try again in" in text
        assert page.evaluate("window.fastghaDemo.avatar") is None
        assert not page.locator("#create").is_disabled()  # one can try again
    finally:
        for s in socks:
            s.close()
    page.click("#create")
    page.wait_for_function("window.fastghaDemo.frames >= 1", timeout=60_000)


def test_demo_page_nits(page, server):
    page.wait_for_function("!document.getElementById('load-sample').disabled", timeout=30_000)
    # every paired slider is there (cheekPuff_L and cheekPuff_R)
    for name in ("cheekPuff_L", "cheekPuff_R", "eyeWide_L", "eyeWide_R"):
        assert page.locator(f"#s-{name}").is_visible(), name
    page.fill("#api-key", API_KEY)
    page.select_option("#size", "128")
    page.click("#load-sample")
    page.wait_for_function("!document.getElementById('create').disabled", timeout=30_000)
    assert page.input_value("#sample-select") == SAMPLE_NAME
    page.click("#create")
    page.wait_for_function("window.fastghaDemo.frames >= 1", timeout=60_000)
    _wait_settled(page, 0)
    # the log names the size actually streamed (the size box), not the server's default
    page.wait_for_function("document.getElementById('messages').innerText.includes('stream ready')", timeout=10_000)
    assert "128×128" in page.inner_text("#messages")
    # a still picture is "idle", not "0 fps"
    page.wait_for_timeout(1500)
    assert page.inner_text("#st-fps").startswith("idle")
    # the stats row stays one row
    tops = page.evaluate("[...document.querySelectorAll('#stats > div')].map((d) => d.offsetTop)")
    assert len(set(tops)) == 1, tops
    assert page.evaluate("(() => { const s = document.getElementById('stats'); return s.scrollWidth <= s.clientWidth; })()")  # nothing cut off
    # picking files: the sample list no longer names a sample; a broken cameras.json keeps the photos
    import httpx

    jpg = httpx.get(f"{server.base}/v1/samples/{SAMPLE_NAME}/00.jpg").content
    page.set_input_files("#file-input", files=[
        {"name": "me1.jpg", "mimeType": "image/jpeg", "buffer": jpg},
        {"name": "me2.jpg", "mimeType": "image/jpeg", "buffer": jpg},
        {"name": "cameras.json", "mimeType": "application/json", "buffer": b"[{not json"},
    ])  # fmt: skip
    page.wait_for_function("document.getElementById('messages').innerText.includes('ignored cameras.json')", timeout=10_000)
    assert page.input_value("#sample-select") == ""
    assert "2 photo(s), no cameras" in page.inner_text("#input-summary")
    assert page.locator("#thumbs img").count() == 2
    assert not page.locator("#create").is_disabled()
    # a cameras.json picked with photos stays for photos picked later only while it fits them: an
    # earlier one for two photos does not block "Create" for one new photo (it used to, until a reload)
    cams = httpx.get(f"{server.base}/v1/samples/{SAMPLE_NAME}/cameras.json").json()[:2]
    page.set_input_files("#file-input", files=[
        {"name": "me1.jpg", "mimeType": "image/jpeg", "buffer": jpg},
        {"name": "me2.jpg", "mimeType": "image/jpeg", "buffer": jpg},
        {"name": "cameras.json", "mimeType": "application/json", "buffer": json.dumps(cams).encode()},
    ])  # fmt: skip
    page.wait_for_function("document.getElementById('input-summary').innerText.startsWith('2 photo(s), 2 camera(s)')", timeout=10_000)
    page.set_input_files("#file-input", files=[{"name": "me3.jpg", "mimeType": "image/jpeg", "buffer": jpg}])
    page.wait_for_function("document.getElementById('input-summary').innerText.startsWith('1 photo(s), no cameras')", timeout=10_000)
    assert "dropped the earlier cameras.json (2 camera(s))" in page.inner_text("#messages")
    assert not page.locator("#create").is_disabled()
    page.set_input_files("#file-input", files=[  # photos alone that the cameras do fit keep them
        {"name": "me1.jpg", "mimeType": "image/jpeg", "buffer": jpg},
        {"name": "cameras.json", "mimeType": "application/json", "buffer": json.dumps(cams[:1]).encode()},
    ])  # fmt: skip
    page.wait_for_function("document.getElementById('input-summary').innerText.startsWith('1 photo(s), 1 camera(s)')", timeout=10_000)
    page.set_input_files("#file-input", files=[{"name": "me4.jpg", "mimeType": "image/jpeg", "buffer": jpg}])
    page.wait_for_timeout(500)
    assert page.inner_text("#input-summary").startswith("1 photo(s), 1 camera(s)")


def test_drop_hint_shows_the_underscore_of_mask_names(page):
    """The drop zone tells users to name masks ``*_mask.png``; at 14 px Debian's monospace lost the
    underscore's pixels, so the page read ``* mask.png``. The second character cell of that code
    element must hold ink (the underscore's, low in the cell)."""
    import io

    import numpy as np
    from PIL import Image

    code = page.locator("#drop code", has_text="mask.png")
    assert code.inner_text() == "*_mask.png"
    px = np.asarray(Image.open(io.BytesIO(code.screenshot())).convert("L"), dtype=np.int16)
    pad = page.evaluate("parseFloat(getComputedStyle(document.querySelector('#drop code')).paddingLeft)")
    cell = (px.shape[1] - 2 * pad) / 10  # ten monospace characters
    x0, x1 = int(round(pad + cell * 1.15)), int(round(pad + cell * 1.85))  # the "_" cell, without its neighbours' edges
    background = int(np.median(px))
    lower = px[px.shape[0] // 2 :, x0:x1]
    assert (lower - background).max() > 40, f"no underscore in '*_mask.png' (cell max {(lower - background).max()} over the background)"


def test_on_a_phone_the_avatar_stays_in_view_while_a_slider_moves(server):
    """At a phone's 390 x 844 the panel and the view stack: the view used to come last, ~1,100 px
    down, so "Create avatar" seemed to do nothing and no slider could be moved while watching the
    face. The view now comes first and stays at the top; its stats wrap instead of being cut off."""
    phone = {"width": 390, "height": 844}

    def inside(box) -> bool:
        return box["y"] >= -0.5 and box["y"] + box["height"] <= phone["height"] + 0.5

    pages = _page_of(server, viewport=phone, is_mobile=True, has_touch=True)
    page = next(pages)
    try:
        _stream_sample(page, timeout=60_000)
        assert inside(page.locator("#frame").bounding_box()), page.locator("#frame").bounding_box()
        assert page.evaluate("(() => { const s = document.getElementById('stats'); return s.scrollWidth <= s.clientWidth; })()")
        page.locator("#s-jawOpen").scroll_into_view_if_needed()
        n = page.evaluate("window.fastghaDemo.frames")
        page.fill("#s-jawOpen", "1")
        _wait_settled(page, n)
        slider, frame = page.locator("#s-jawOpen").bounding_box(), page.locator("#frame").bounding_box()
        assert inside(slider) and inside(frame), (slider, frame)
        assert slider["y"] >= frame["y"] + frame["height"], "the slider is hidden under the view"
        page.locator("#create").scroll_into_view_if_needed()  # the photos' controls are reachable too
        create, frame = page.locator("#create").bounding_box(), page.locator("#frame").bounding_box()
        assert inside(create) and create["y"] >= frame["y"] + frame["height"], (create, frame)
    finally:
        pages.close()


def test_demo_takes_a_whole_tracked_folder(page, server):
    """Dropping everything `fastgha track` wrote (crops, masks, cameras.json, expressions.json,
    head.json) loads the photos, cameras, masks and the tracked expressions as the sequence;
    head.json is not taken for a sequence."""
    import httpx

    page.wait_for_function("window.fastghaDemo.model !== null", timeout=30_000)
    jpg = httpx.get(f"{server.base}/v1/samples/{SAMPLE_NAME}/00.jpg").content
    cams = httpx.get(f"{server.base}/v1/samples/{SAMPLE_NAME}/cameras.json").json()[:2]
    names = page.evaluate("window.fastghaDemo.model.expression_names")
    tracked = {"space": "ict53", "names": names, "images": ["00_me.png", "01_me.png"], "expressions": [[0.0] * len(names)] * 2}
    frames = {"00_me.png": [0.0, -0.1, 1.0, 1.2], "01_me.png": [0.1, 0.0, 0.9, 1.0]}  # by crop file name, as `fastgha track` writes them
    head = {"model": "ict_facekit", "identity": [0.0] * 100, "frames": frames}
    page.set_input_files("#file-input", files=[  # head.json first: it must not be read as the sequence
        {"name": "head.json", "mimeType": "application/json", "buffer": json.dumps(head).encode()},
        {"name": "00_me.jpg", "mimeType": "image/jpeg", "buffer": jpg},
        {"name": "01_me.jpg", "mimeType": "image/jpeg", "buffer": jpg},
        {"name": "cameras.json", "mimeType": "application/json", "buffer": json.dumps(cams).encode()},
        {"name": "expressions.json", "mimeType": "application/json", "buffer": json.dumps(tracked).encode()},
    ])  # fmt: skip
    page.wait_for_function("document.getElementById('input-summary').innerText.startsWith('2 photo(s), 2 camera(s)')", timeout=10_000)
    assert "2-frame sequence" in page.inner_text("#input-summary")
    assert "ignored" not in page.inner_text("#messages")
    # head.json goes with the cameras as the `head` part, each photo's tracked expression added (by stem)
    assert "tracked head" in page.inner_text("#input-summary")
    page.fill("#api-key", API_KEY)
    page.evaluate("""() => { const f = window.fetch; window.fetch = (u, o) => {  // what the POST carries (no multipart body in CDP)
        if (o && o.body instanceof FormData) window.__sent = { head: o.body.get("head"), cameras: o.body.get("cameras") };
        return f(u, o); }; }""")
    page.click("#create")
    page.wait_for_function("window.__sent !== undefined", timeout=10_000)
    sent = page.evaluate("window.__sent")
    # ... and each photo's frame, in the photos' order (by stem: the crops were written as .png)
    assert json.loads(sent["head"]) == {**head, "expressions": tracked["expressions"], "frames": [frames["00_me.png"], frames["01_me.png"]]}
    assert len(json.loads(sent["cameras"])) == 2
    page.wait_for_function("window.fastghaDemo.frames >= 1", timeout=60_000)  # the server took it
    assert "creating the avatar failed" not in page.inner_text("#messages")


def test_demo_says_when_a_dropped_head_cannot_be_sent(page, server):
    """head.json without the expressions.json of its `fastgha track` run is not sent (named in the log)."""
    import httpx

    page.wait_for_function("window.fastghaDemo.model !== null", timeout=30_000)
    jpg = httpx.get(f"{server.base}/v1/samples/{SAMPLE_NAME}/00.jpg").content
    cams = httpx.get(f"{server.base}/v1/samples/{SAMPLE_NAME}/cameras.json").json()[:1]
    page.set_input_files("#file-input", files=[
        {"name": "head.json", "mimeType": "application/json", "buffer": json.dumps({"model": "ict_facekit", "identity": [0.0] * 100}).encode()},
        {"name": "00_me.jpg", "mimeType": "image/jpeg", "buffer": jpg},
        {"name": "cameras.json", "mimeType": "application/json", "buffer": json.dumps(cams).encode()},
    ])  # fmt: skip
    page.wait_for_function("document.getElementById('input-summary').innerText.startsWith('1 photo(s), 1 camera(s)')", timeout=10_000)
    assert "tracked head" not in page.inner_text("#input-summary")
    assert "ignored head.json: it needs the expressions.json" in page.inner_text("#messages")


def test_demo_stops_a_sequence_the_server_refuses_and_recovers(page, server):
    """A sequence file with a name the server does not know used to leave that name in every later
    request (each refused, one log line per frame, sliders dead until a reload): the player stops,
    the log says it once, and the sliders work again."""
    _stream_sample(page, timeout=60_000)
    bad = [{"jawOpenn": i / 10} for i in range(10)]
    page.set_input_files("#file-input", files=[{"name": "seq.json", "mimeType": "application/json", "buffer": json.dumps(bad).encode()}])
    page.wait_for_function("document.getElementById('input-summary').innerText.includes('10-frame sequence')", timeout=10_000)
    page.click("#play")
    page.wait_for_function("document.getElementById('messages').innerText.includes('stopped the sequence')", timeout=30_000)
    page.wait_for_timeout(800)
    assert not page.evaluate("window.fastghaDemo.playing")
    log = page.inner_text("#messages")
    assert log.count("unknown_expression_name") == 1 and "jawOpenn" in log, log
    frames = page.evaluate("window.fastghaDemo.frames")
    page.locator("#s-jawOpen").fill("0.6")  # a slider: rendered, not refused again
    page.wait_for_function(f"window.fastghaDemo.frames > {frames}", timeout=30_000)
    assert page.inner_text("#messages").count("unknown_expression_name") == 1


# ---------------------------------------------------------------- jawOpen on the shipped model
@pytest.fixture(scope="module")
def shipped_server(tmp_path_factory):
    """The shipped ``tiny`` model and the shipped sample subjects (``fastgha_core/assets``)."""
    srv = ServerProcess("tiny", tmp_path_factory.mktemp("data-shipped"), None, tmp_path_factory.mktemp("logs") / "shipped.log")
    yield srv
    srv.stop()


def test_jaw_open_changes_the_mouth_region(shipped_server):
    import numpy as np

    for pg in _page_of(shipped_server):
        _stream_sample(pg, timeout=120_000)
        neutral = _pixels(pg)
        n = pg.evaluate("window.fastghaDemo.frames")
        pg.fill("#s-jawOpen", "1")
        _wait_settled(pg, n)
        opened = _pixels(pg)
        assert neutral.shape == opened.shape == (256, 256, 3)
        d = np.abs(opened - neutral).sum(-1)  # [H, W] summed RGB change
        # default frontal camera, 1 m, 20 degrees: the head-centric mouth projects around row 185, column 128
        mouth = d[160:215, 98:158].mean()
        crown = d[20:80, 78:178].mean()  # top of the head: jawOpen should hardly touch it
        assert mouth > 2.0 and mouth > 2.0 * crown, (mouth, crown)
