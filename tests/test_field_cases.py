"""The field cases (real inputs the product got wrong; public domain, copied into ``fixtures/images``)
through the server's creation path as it is now: ``server.jobs.decode_photo`` and a creation job.

- ``sample00_gray16.png`` (a view of the shipped sample as 16-bit grey, 256 x 256) and
  ``grace_gray16.png``: decoded to their grey levels (means 0.555 and 0.302; the cases README gives
  ~0.30 as the sample view's and 128 x 128 as its size, but 0.30 is the portrait's), not white; an
  avatar from the sample view with the sample's camera holds a head (it used to have 36-66 Gaussians).
- ``grace_hopper_exif6.jpg`` (stored sideways, EXIF orientation 6): decoded upright, the same picture
  as ``grace_hopper_upright.jpg``; posted without cameras it is tracked (it used to be 422 no_face).

``test_images.py`` covers the shared decoder and ``fastgha track`` on the same files.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from extras import needs_faces
from server.jobs import CreationRequest, Photo, decode_photo
from server_process import make_model_dir
from test_server_avatar_info import _ctx, _run_job

pytestmark = pytest.mark.timeout(300)

FIX = Path(__file__).resolve().parent / "fixtures" / "images"
SAMPLE = Path(__file__).resolve().parents[1] / "fastgha_core" / "assets" / "samples" / "synth_1000000" / "request"


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    return make_model_dir(tmp_path_factory.mktemp("model"))


def test_gray16_decodes_to_its_grey_levels_on_the_creation_path():
    src = np.asarray(Image.open(FIX / "sample00_gray16.png")).astype(np.float64) / 65535.0
    rgb, alpha = decode_photo(Photo("sample00_gray16.png", (FIX / "sample00_gray16.png").read_bytes()), max_pixels=10**7, max_side=4096)
    assert alpha is None and rgb.shape == (*src.shape, 3)
    got = rgb.astype(np.float64) / 255.0
    assert abs(got.mean() - src.mean()) < 2e-3 and got.mean() < 0.9  # its grey levels (0.555), not white
    assert np.abs(got[..., 0] - src).max() <= 1.0 / 255 + 1e-9 and np.array_equal(rgb[..., 0], rgb[..., 2])
    grace, _ = decode_photo(Photo("grace_gray16.png", (FIX / "grace_gray16.png").read_bytes()), max_pixels=10**7, max_side=4096)
    # the field report's "mean ~0.30" is this portrait's grey level (the sample view's is 0.555)
    assert abs(grace.mean() / 255 - 0.302) < 0.005


def test_exif6_decodes_upright_on_the_creation_path():
    side, _ = decode_photo(Photo("s.jpg", (FIX / "grace_hopper_exif6.jpg").read_bytes()), max_pixels=10**7, max_side=4096)
    up, _ = decode_photo(Photo("u.jpg", (FIX / "grace_hopper_upright.jpg").read_bytes()), max_pixels=10**7, max_side=4096)
    assert side.shape == up.shape and side.shape[0] > side.shape[1]  # portrait: taller than wide
    assert np.abs(side.astype(int) - up.astype(int)).mean() < 4.0  # the same picture (two JPEG encodings)


@pytest.mark.skipif(not SAMPLE.is_dir(), reason="needs the shipped sample synth_1000000")
def test_gray16_view_with_its_camera_gives_a_head(model_dir, tmp_path):
    from fastgha_core.cameras import cameras_from_json

    cam = cameras_from_json(json.loads((SAMPLE / "cameras.json").read_text()))[0]
    w, h = Image.open(FIX / "sample00_gray16.png").size
    photo = Photo("sample00_gray16.png", (FIX / "sample00_gray16.png").read_bytes())
    job = _run_job(_ctx(model_dir, tmp_path), CreationRequest([photo], None, [cam if (cam.width, cam.height) == (w, h) else cam.resize(w, h)]))
    assert job.status == "ready", job.error and job.error.message
    assert job.result["num_gaussians"] > 1000  # was 36-66 when the photo decoded as white


@needs_faces
def test_exif6_portrait_without_cameras_is_tracked_by_a_creation_job(model_dir, tmp_path):
    from server.tracking import PhotoTracker

    photos = [Photo("grace_hopper_exif6.jpg", (FIX / "grace_hopper_exif6.jpg").read_bytes())]
    job = _run_job(_ctx(model_dir, tmp_path), CreationRequest(photos, None, None), tracker=PhotoTracker())
    assert job.status == "ready", job.error and f"{job.error.code}: {job.error.message}"
    assert job.stages[:3] == ["queued", "decoding", "tracking"] and job.result["tracking_ms"] > 0


def _cut_out_png(rgb: Image.Image, margin: float) -> bytes:
    """``rgb`` as an RGBA PNG cut out by its alpha: opaque below the top eighth and between
    ``margin`` of the width from either side, transparent elsewhere."""
    import io

    cut = rgb.convert("RGBA")
    alpha = np.zeros((cut.height, cut.width), np.uint8)
    alpha[cut.height // 8 :, int(cut.width * margin) : int(cut.width * (1 - margin))] = 255
    cut.putalpha(Image.fromarray(alpha))
    buf = io.BytesIO()
    cut.save(buf, format="PNG")
    return buf.getvalue()


@needs_faces
def test_opaque_rgba_png_is_matted_like_the_same_photo_without_alpha(model_dir, tmp_path):
    """A PNG saved with an alpha channel that is opaque everywhere (editors, screenshots, conversions)
    carries no matte: posted without cameras it is matted by the tracked head like the same pixels
    without alpha. It used to be taken as an all-foreground mask, so the whole background (the flag
    behind the portrait) stayed in the avatar as a flat card, with ~60% more Gaussians."""
    import io

    from server.tracking import PhotoTracker

    rgb = Image.open(FIX / "grace_hopper_upright.jpg").convert("RGB")
    results = {}
    for mode in ("RGB", "RGBA"):
        buf = io.BytesIO()
        rgb.convert(mode).save(buf, format="PNG")
        job = _run_job(_ctx(model_dir, tmp_path / mode), CreationRequest([Photo(f"grace_{mode}.png", buf.getvalue())], None, None), tracker=PhotoTracker())
        assert job.status == "ready", job.error and f"{job.error.code}: {job.error.message}"
        results[mode] = job.result["num_gaussians"]
    assert results["RGBA"] == results["RGB"], results
    # a real matte (transparent background) still wins over the tracked silhouette
    cut = _cut_out_png(rgb, 1 / 4)
    job = _run_job(_ctx(model_dir, tmp_path / "cut"), CreationRequest([Photo("grace_cut.png", cut)], None, None), tracker=PhotoTracker())
    assert job.status == "ready" and job.result["num_gaussians"] != results["RGB"], job.result


@needs_faces
def test_a_photo_without_matte_beside_one_with_is_matted_by_the_tracked_head(model_dir, tmp_path):
    """Photos of one person, one a PNG cut out with transparency and one a JPEG: the JPEG has no
    matte of its own, so the tracker makes one from the fitted head. It used to be handed an
    all-foreground mask (the request had "masks"), keeping that photo's whole background."""
    from server.tracking import PhotoTracker

    rgb = Image.open(FIX / "grace_hopper_upright.jpg").convert("RGB")
    photos = [Photo("cut.png", _cut_out_png(rgb, 1 / 6)), Photo("plain.jpg", (FIX / "grace_hopper_upright.jpg").read_bytes())]
    seen = {}

    class Spy(PhotoTracker):
        def track(self, images, masks, size, names=None):
            out = super().track(images, masks, size, names=names)
            seen["given"], seen["crop_masks"] = masks, out[2]
            return out

    job = _run_job(_ctx(model_dir, tmp_path), CreationRequest(photos, None, None), tracker=Spy())
    assert job.status == "ready", job.error and f"{job.error.code}: {job.error.message}"
    assert seen["given"][0] is not None and seen["given"][1] is None
    plain = seen["crop_masks"][1, 0]
    assert 0.05 < float(plain.mean()) < 0.9, float(plain.mean())  # the head's silhouette, not the whole crop
