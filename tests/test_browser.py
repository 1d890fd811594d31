"""End-to-end test of the browser demo in headless Chromium (Python playwright).

A real server process serves the demo at ``/`` (``server_process.py``: a 64 x 64 tiny model
whose deformation output layer is non-zero, and a synthetic sample subject). The page loads
the sample with one click, creates the avatar, receives frames, and the canvas must show a
picture that changes when an expression slider moves and when the camera is dragged.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import pytest

from server_process import API_KEY, ServerProcess, make_model_dir, make_sample_dir

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
    srv = ServerProcess(model, tmp_path_factory.mktemp("data"), samples, tmp_path_factory.mktemp("logs") / "server.log")
    yield srv
    srv.stop()


@pytest.fixture()
def page(server):
    profile = tempfile.mkdtemp(prefix="fastgha-chromium-")
    errors: list[str] = []
    with sync_api.sync_playwright() as p:
        ctx = p.chromium.launch_persistent_context(
            profile, executable_path=CHROMIUM, args=ARGS, headless=True, viewport={"width": 1200, "height": 900}, accept_downloads=True,
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


def test_demo_streams_and_reacts_to_slider_and_camera(page, tmp_path):
    import numpy as np

    page.wait_for_function("!document.getElementById('load-sample').disabled", timeout=30_000)
    page.fill("#api-key", API_KEY)
    page.click("#load-sample")
    page.wait_for_function("!document.getElementById('create').disabled", timeout=30_000)
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
    page.wait_for_function("!document.getElementById('load-sample').disabled", timeout=30_000)
    page.fill("#api-key", "wrong-key")
    page.click("#load-sample")
    page.wait_for_function("!document.getElementById('create').disabled", timeout=30_000)
    page.click("#create")
    page.wait_for_function("document.getElementById('messages').innerText.includes('invalid_api_key')", timeout=30_000)
    assert page.evaluate("window.fastghaDemo.avatar") is None
