"""fastgha_core.images: one decoder for every ingest path (pixel modes, EXIF orientation, limits).

Fixtures (public domain, from field reports): ``fixtures/images/grace_gray16.png`` and
``sample00_gray16.png`` (16-bit greyscale PNGs that used to decode as all white),
``grace_hopper_exif6.jpg`` (stored sideways with EXIF orientation 6) and ``grace_hopper_upright.jpg``.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image, ImageOps

from fastgha_core.images import (
    ImageDecodeError,
    apply_orientation,
    decode_image_bytes,
    decode_mask_bytes,
    decode_pixels_bytes,
    read_image,
    read_mask,
)

FIX = Path(__file__).parent / "fixtures" / "images"
RNG = np.random.default_rng(7)


def _encode(im: Image.Image, fmt: str, **kw) -> bytes:
    buf = io.BytesIO()
    im.save(buf, format=fmt, **kw)
    return buf.getvalue()


def _u16(shape=(9, 13)) -> np.ndarray:
    a = RNG.integers(0, 65536, shape, dtype=np.uint16)
    a[0, 0], a[0, 1] = 0, 65535
    return a


def _expect16(a: np.ndarray) -> np.ndarray:  # the reference reading of 16-bit grey
    return np.round(a.astype(np.float64) / 65535.0 * 255.0).astype(np.uint8)


# ---------------------------------------------------------------- one test per mode
def test_mode_rgb_and_l_exact():
    rgb = RNG.integers(0, 256, (9, 13, 3), dtype=np.uint8)
    d = decode_image_bytes(_encode(Image.fromarray(rgb), "PNG"), "a.png")
    assert d.mode == "RGB" and d.alpha is None and d.orientation == 1 and d.scale == 1.0
    np.testing.assert_array_equal(d.rgb, rgb)
    g = rgb[..., 0]
    d = decode_image_bytes(_encode(Image.fromarray(g), "PNG"), "g.png")
    assert d.mode == "L"
    np.testing.assert_array_equal(d.rgb, np.repeat(g[..., None], 3, axis=2))


def test_mode_gray16_png_fixture_reads_grey_levels_not_white():
    src = np.asarray(Image.open(FIX / "sample00_gray16.png"))
    assert src.dtype == np.uint16
    d = read_image(FIX / "sample00_gray16.png")
    assert d.mode == "I;16"
    np.testing.assert_array_equal(d.rgb[..., 1], _expect16(src))
    assert abs(d.rgb.mean() / 255 - src.mean() / 65535) < 1e-3
    assert d.rgb.mean() / 255 < 0.9  # the bug: every pixel clipped to white
    g = read_image(FIX / "grace_gray16.png")
    assert abs(g.rgb.mean() / 255 - 0.302) < 0.005  # the portrait's mean grey level


@pytest.mark.parametrize("mode", ["I;16", "I;16L", "I;16B"])
def test_mode_16bit_variants(mode):
    a = _u16()
    raw = a.astype(">u2" if mode == "I;16B" else "<u2").tobytes()
    im = Image.frombytes(mode, (a.shape[1], a.shape[0]), raw)
    data = _encode(im, "TIFF")
    d = decode_image_bytes(data, "x.tif")
    assert d.mode.startswith("I;16")
    np.testing.assert_array_equal(d.rgb[..., 0], _expect16(a))


def test_mode_32bit_int_in_16bit_range_and_refused_outside():
    a = _u16().astype(np.int32)
    d = decode_image_bytes(_encode(Image.fromarray(a, mode="I"), "TIFF"), "i32.tif")
    assert d.mode == "I"
    np.testing.assert_array_equal(d.rgb[..., 2], _expect16(a))
    big = a.copy()
    big[3, 3] = 1_000_000
    with pytest.raises(ImageDecodeError) as e:
        decode_image_bytes(_encode(Image.fromarray(big, mode="I"), "TIFF"), "big.tif")
    assert e.value.code == "unsupported_image_mode" and "'I'" in str(e.value) and "big.tif" in str(e.value)


def test_mode_float_unit_range_and_refused_outside():
    f = RNG.random((9, 13)).astype(np.float32)
    d = decode_image_bytes(_encode(Image.fromarray(f, mode="F"), "TIFF"), "f.tif")
    assert d.mode == "F"
    np.testing.assert_array_equal(d.rgb[..., 0], np.round(f * 255).astype(np.uint8))
    for bad in (f * 300.0, np.where(f > 0.5, np.nan, f).astype(np.float32)):
        with pytest.raises(ImageDecodeError) as e:
            decode_image_bytes(_encode(Image.fromarray(bad, mode="F"), "TIFF"), "bad.tif")
        assert e.value.code == "unsupported_image_mode" and "'F'" in str(e.value)


def test_mode_palette_with_transparency():
    pal = Image.new("P", (6, 4))
    pal.putpalette([255, 0, 0, 0, 255, 0, 0, 0, 255] + [0] * (253 * 3))
    idx = np.array([[0, 1, 2, 0, 1, 2]] * 4, np.uint8)
    pal.putdata(idx.ravel().tolist())
    data = _encode(pal, "PNG", transparency=1)  # colour index 1 (green) is transparent
    d = decode_image_bytes(data, "p.png")
    assert d.mode == "P" and d.alpha is not None
    np.testing.assert_array_equal(d.alpha, np.where(idx == 1, 0, 255))
    np.testing.assert_array_equal(d.rgb[0, 0], [255, 0, 0])
    np.testing.assert_array_equal(d.rgb[0, 2], [0, 0, 255])
    # as a mask, the transparency is the matte
    np.testing.assert_array_equal(decode_mask_bytes(data, "p.png"), np.where(idx == 1, 0, 255))


def test_mode_la_and_rgba():
    la = RNG.integers(0, 256, (9, 13, 2), dtype=np.uint8)
    d = decode_image_bytes(_encode(Image.fromarray(la, mode="LA"), "PNG"), "la.png")
    assert d.mode == "LA"
    np.testing.assert_array_equal(d.rgb[..., 0], la[..., 0])
    np.testing.assert_array_equal(d.alpha, la[..., 1])
    rgba = RNG.integers(0, 256, (9, 13, 4), dtype=np.uint8)
    d = decode_image_bytes(_encode(Image.fromarray(rgba), "PNG"), "rgba.png")
    assert d.mode == "RGBA"
    np.testing.assert_array_equal(d.rgb, rgba[..., :3])
    np.testing.assert_array_equal(d.alpha, rgba[..., 3])


def test_mode_cmyk():
    rgb = RNG.integers(0, 256, (9, 13, 3), dtype=np.uint8)
    cmyk = np.concatenate([255 - rgb, np.zeros((9, 13, 1), np.uint8)], axis=2)  # K = 0: RGB = 255 - CMY
    d = decode_image_bytes(_encode(Image.fromarray(cmyk, mode="CMYK"), "TIFF"), "c.tif")
    assert d.mode == "CMYK"
    np.testing.assert_array_equal(d.rgb, rgb)
    smooth = np.zeros((32, 32, 4), np.uint8)
    smooth[..., 0] = 200  # cyan-ish: R = 55
    d = decode_image_bytes(_encode(Image.fromarray(smooth, mode="CMYK"), "JPEG", quality=95), "c.jpg")
    assert d.mode == "CMYK" and abs(float(d.rgb[..., 0].mean()) - 55) < 4 and d.rgb[..., 1].mean() > 248


def test_mode_bilevel():
    b = RNG.random((9, 16)) > 0.5
    d = decode_image_bytes(_encode(Image.fromarray(b), "PNG"), "b.png")
    assert d.mode == "1"
    np.testing.assert_array_equal(d.rgb[..., 0], np.where(b, 255, 0))


def test_mode_without_faithful_reading_is_refused():
    lab = Image.new("LAB", (4, 4), (50, 0, 0))
    with pytest.raises(ImageDecodeError) as e:
        decode_image_bytes(_encode(lab, "TIFF"), "lab.tif")
    assert e.value.code == "unsupported_image_mode" and "'LAB'" in str(e.value) and "lab.tif" in str(e.value)


# ---------------------------------------------------------------- masks
def test_mask_16bit_is_scaled_not_all_foreground():
    m = np.zeros((20, 30), np.uint16)
    m[5:15, 10:20] = 65535
    m[0, :] = 32768  # half intensity
    data = _encode(Image.fromarray(m), "PNG")
    got = decode_mask_bytes(data, "mask.png")
    assert got.dtype == np.uint8 and got.shape == (20, 30)
    assert (got > 127).mean() < 0.25  # was 99.99 % foreground
    np.testing.assert_array_equal(got, _expect16(m))


def test_mask_modes_rgb_and_la():
    g = RNG.integers(0, 256, (9, 13), dtype=np.uint8)
    rgb = np.repeat(g[..., None], 3, axis=2)
    np.testing.assert_array_equal(decode_mask_bytes(_encode(Image.fromarray(rgb), "PNG"), "m.png"), g)
    la = np.stack([np.full_like(g, 255), g], axis=2)
    np.testing.assert_array_equal(decode_mask_bytes(_encode(Image.fromarray(la, mode="LA"), "PNG"), "m.png"), g)


def test_pixels_keep_label_values():
    labels = RNG.integers(0, 12, (9, 13), dtype=np.uint8)
    out = decode_pixels_bytes(_encode(Image.fromarray(labels), "PNG"), "seg.png")
    assert out.shape == (9, 13, 1)
    np.testing.assert_array_equal(out[..., 0], labels)


# ---------------------------------------------------------------- orientation
def _stored_for(upright: Image.Image, orientation: int) -> Image.Image:
    """The stored pixels whose EXIF ``orientation`` displays as ``upright``."""
    T = Image.Transpose
    inverse = {1: None, 2: T.FLIP_LEFT_RIGHT, 3: T.ROTATE_180, 4: T.FLIP_TOP_BOTTOM, 5: T.TRANSPOSE,
               6: T.ROTATE_90, 7: T.TRANSVERSE, 8: T.ROTATE_270}[orientation]  # fmt: skip
    return upright.copy() if inverse is None else upright.transpose(inverse)


def _with_orientation(im: Image.Image, orientation: int, fmt: str, **kw) -> bytes:
    exif = Image.Exif()
    exif[0x0112] = orientation
    return _encode(im, fmt, exif=exif, **kw)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_orientation_matches_pillow_and_restores_upright(orientation):
    up = RNG.integers(0, 256, (6, 10, 3), dtype=np.uint8)
    stored = _stored_for(Image.fromarray(up), orientation)
    data = _with_orientation(stored, orientation, "PNG")
    ref = np.asarray(ImageOps.exif_transpose(Image.open(io.BytesIO(data))))
    d = decode_image_bytes(data, "o.png")
    assert d.orientation == orientation
    np.testing.assert_array_equal(d.rgb, up)
    np.testing.assert_array_equal(d.rgb, ref)
    np.testing.assert_array_equal(apply_orientation(np.asarray(stored), orientation), up)
    m = decode_mask_bytes(data, "o.png")
    assert m.shape == up.shape[:2]


def test_exif6_fixture_is_upright():
    up = read_image(FIX / "grace_hopper_upright.jpg")
    side = read_image(FIX / "grace_hopper_exif6.jpg")
    assert side.orientation == 6 and up.orientation == 1
    assert Image.open(FIX / "grace_hopper_exif6.jpg").size == (600, 512)  # stored sideways
    assert side.rgb.shape == up.rgb.shape == (600, 512, 3)
    assert np.abs(side.rgb.astype(int) - up.rgb).mean() < 2.0  # same picture (JPEG noise only)
    wrong = np.rot90(np.asarray(Image.open(FIX / "grace_hopper_exif6.jpg").convert("RGB")), k=1)  # the other way round
    assert np.abs(wrong.astype(int) - up.rgb).mean() > 20


# ---------------------------------------------------------------- limits, errors, downscale, focal
def test_errors_name_the_file_and_have_codes():
    jpeg = _encode(Image.new("RGB", (40, 40)), "JPEG")
    for blob in (b"", b"hello", jpeg[: len(jpeg) // 2]):
        with pytest.raises(ImageDecodeError) as e:
            decode_image_bytes(blob, "holiday.jpg")
        assert e.value.code == "invalid_image" and "holiday.jpg" in str(e.value)
        assert "BytesIO" not in str(e.value)  # never the repr of our buffer
    with pytest.raises(ImageDecodeError) as e:
        decode_image_bytes(b'[{"K": 1}]', "cameras.json")
    assert str(e.value) == "cameras.json is not an image file Pillow can read"
    with pytest.raises(ImageDecodeError) as e:
        decode_image_bytes(jpeg, "holiday.jpg", max_pixels=40 * 40 - 1)
    assert e.value.code == "image_too_large" and "holiday.jpg" in str(e.value)
    with pytest.raises(ImageDecodeError) as e:  # past Pillow's own bomb limit (89 M pixels): still the size and our limit
        decode_image_bytes(_encode(Image.new("1", (20000, 20000)), "PNG"), "bomb.png")
    assert e.value.code == "image_too_large" and str(e.value) == f"bomb.png has 400000000 pixels; the limit is {64 * 1024 * 1024}"
    with pytest.raises(ImageDecodeError) as e:
        decode_image_bytes(_encode(Image.new("RGB", (4, 4)), "BMP"), "x.bmp", formats=("JPEG", "PNG"))
    assert e.value.code == "invalid_image"
    with pytest.raises(ImageDecodeError) as e:
        read_image(FIX / "no-such-file.png")
    assert "no-such-file.png" in str(e.value)


@pytest.mark.parametrize("fmt", ["JPEG", "PNG"])
def test_max_side_downscales_while_decoding(fmt):
    y, x = np.mgrid[0:960, 0:1280]
    rgb = np.stack([x * 255 // 1279, y * 255 // 959, np.full_like(x, 128)], axis=2).astype(np.uint8)
    data = _encode(Image.fromarray(rgb), fmt, **({"quality": 95} if fmt == "JPEG" else {}))
    d = decode_image_bytes(data, "big", max_side=300)
    assert max(d.rgb.shape[:2]) == 300 and d.rgb.shape[:2] == (225, 300)
    assert d.scale == pytest.approx(300 / 1280)
    ref = np.asarray(Image.fromarray(rgb).resize((300, 225), Image.Resampling.BILINEAR)).astype(int)
    assert np.abs(d.rgb.astype(int) - ref).mean() < 3.0
    same = decode_image_bytes(data, "big", max_side=5000)  # > 1 MP: copied out of Pillow in bands of rows
    assert same.scale == 1.0 and same.rgb.shape == rgb.shape and same.rgb.flags.writeable
    np.testing.assert_array_equal(same.rgb, np.asarray(Image.open(io.BytesIO(data)).convert("RGB")))


def test_exif_focal_35mm():
    exif = Image.Exif()
    ifd = exif.get_ifd(0x8769)
    ifd[0xA405] = 26
    d = decode_image_bytes(_encode(Image.new("RGB", (40, 30)), "JPEG", exif=exif), "f.jpg")
    assert d.exif_focal_35mm == 26.0
    # FocalLength 4.25 mm on a 6.4 x 4.8 mm sensor (4000 px / 6.4 mm = 625 px/mm, unit mm)
    exif = Image.Exif()
    ifd = exif.get_ifd(0x8769)
    ifd[0x920A] = 4.25
    ifd[0xA20E] = 625.0
    ifd[0xA20F] = 625.0
    ifd[0xA210] = 4
    ifd[0xA002], ifd[0xA003] = 4000, 3000
    d = decode_image_bytes(_encode(Image.new("RGB", (40, 30)), "JPEG", exif=exif), "f.jpg")
    assert d.exif_focal_35mm == pytest.approx(4.25 * np.hypot(36, 24) / np.hypot(6.4, 4.8), rel=1e-3)
    assert decode_image_bytes(_encode(Image.new("RGB", (4, 3)), "PNG"), "n.png").exif_focal_35mm is None


# ---------------------------------------------------------------- server and CLI paths
def test_server_decoder_uses_modes_and_orientation():
    from server.errors import ApiError
    from server.imaging import decode_image, decode_mask

    img, alpha = decode_image((FIX / "sample00_gray16.png").read_bytes(), "sample00_gray16.png", 10**6)
    src = np.asarray(Image.open(FIX / "sample00_gray16.png")).astype(np.float64) / 65535
    assert alpha is None and abs(float(img.mean()) - src.mean()) < 2e-3
    side, _ = decode_image((FIX / "grace_hopper_exif6.jpg").read_bytes(), "p.jpg", 10**6)
    assert tuple(side.shape) == (3, 600, 512)
    m = np.zeros((8, 8), np.uint16)
    m[:4] = 65535
    mask = decode_mask(_encode(Image.fromarray(m), "PNG"), "m.png", 10**6)
    assert float(mask.mean()) == pytest.approx(0.5)
    f = Image.fromarray(np.ones((4, 4), np.float32), mode="F")
    with pytest.raises(ApiError) as e:  # TIFF is not accepted by the server at all
        decode_image(_encode(f, "TIFF"), "f.tif", 10**6)
    assert (e.value.status, e.value.code) == (400, "invalid_image")


def test_reconstruct_and_layout_readers_use_the_decoder(tmp_path):
    from fastgha_core.commands.reconstruct import _read_image, _read_mask
    from fastgha_core.data.layout import load_image, load_mask

    img = _read_image(FIX / "grace_hopper_exif6.jpg")
    assert img.dtype == torch.uint8 and tuple(img.shape) == (3, 600, 512)
    g = _read_image(FIX / "sample00_gray16.png")
    assert float(g.float().mean()) / 255 < 0.9
    m = np.zeros((8, 8), np.uint16)
    m[:2] = 65535
    Image.fromarray(m).save(tmp_path / "m.png")
    assert float(_read_mask(tmp_path / "m.png").float().mean()) / 255 == pytest.approx(0.25)
    assert float(load_mask(tmp_path / "m.png").mean()) == pytest.approx(0.25)
    upright = read_image(FIX / "grace_hopper_exif6.jpg").rgb.transpose(2, 0, 1) / 255.0
    np.testing.assert_allclose(load_image(FIX / "grace_hopper_exif6.jpg").numpy(), upright)
    assert read_mask(tmp_path / "m.png").shape == (8, 8)


# ---------------------------------------------------------------- tracking: the done-when of the EXIF field case
def _faces_available() -> bool:
    try:
        from fastgha_core.tracking.faces import load_face_detector

        load_face_detector()
        return True
    except Exception:
        return False


def _rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


@pytest.mark.skipif(not _faces_available(), reason="needs the 'faces' extra (dlib-bin, face-recognition-models)")
def test_eight_exif_orientations_track_to_the_upright_pose(tmp_path):
    """`fastgha track` on the portrait stored in each of the 8 EXIF orientations finds the same head
    pose as on the upright photo, within 1 degree.

    The stored pixels are written losslessly (PNG with an eXIf chunk) so that the test isolates the
    orientation handling: re-encoding the upright pixels as JPEG alone (orientation 1) moves the dlib
    tracker's pose by 2.4 degrees, which is the tracker's sensitivity to JPEG noise, not EXIF.
    """
    import json

    from fastgha_core.cli import main

    upright = Image.open(FIX / "grace_hopper_upright.jpg").convert("RGB")
    paths = [tmp_path / "upright.png"]
    upright.save(paths[0])
    for o in range(1, 9):
        p = tmp_path / f"o{o}.png"
        p.write_bytes(_with_orientation(_stored_for(upright, o), o, "PNG"))
        paths.append(p)
    report = tmp_path / "report.json"
    assert main(["track", "--images", *map(str, paths), "--out", str(tmp_path / "req"), "--json", str(report)]) == 0
    rots = [np.asarray(ph["head_rotation"]) for ph in json.loads(report.read_text())["photos"]]
    for o in range(1, 9):
        assert _rotation_angle_deg(rots[0], rots[o]) < 1.0, f"orientation {o}"
    # the field case itself (two JPEGs): orientation 6 tracks (it used to give "no face found")
    report6 = tmp_path / "report6.json"
    assert main(["track", "--images", str(FIX / "grace_hopper_upright.jpg"), str(FIX / "grace_hopper_exif6.jpg"),
                 "--out", str(tmp_path / "req6"), "--json", str(report6)]) == 0  # fmt: skip
    r6 = [np.asarray(ph["head_rotation"]) for ph in json.loads(report6.read_text())["photos"]]
    assert _rotation_angle_deg(r6[0], r6[1]) < 3.0  # JPEG noise between the two files, see above


@pytest.mark.skipif(not _faces_available(), reason="needs the 'faces' extra (dlib-bin, face-recognition-models)")
def test_server_without_cameras_tracks_the_exif6_portrait():
    """The server's no-camera path (server/imaging.py decode, then server/tracking.py) on the field case:
    the sideways-stored portrait used to give 422 no_face."""
    from server.imaging import decode_image
    from server.tracking import PhotoTracker

    img, _ = decode_image((FIX / "grace_hopper_exif6.jpg").read_bytes(), "grace_hopper_exif6.jpg", 10**7)
    crops, cams, masks, _, _ = PhotoTracker().track([img], None, 128)
    assert crops.shape[0] == 1 and len(cams) == 1 and masks.shape[0] == 1
