"""The tracker's crop padding is not background (``HeadSurface.frames`` / ``padding``; used by
``fit_hair_thickness``, ``hair_carve_fractions`` and ``FastGHA.reconstruct``'s shell carve; issue 17:
studio-4's -70 photo's frame cuts its hair at the back, and the crop's padding there, in the
background colour, read as "no head" carved the hair and the shell)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from fastgha_core.cameras import Cameras
from fastgha_core.data.headmodel import HeadModel
from fastgha_core.model.surface import HeadSurface, fit_hair_thickness, hair_carve_fractions, hair_vertex_weight
from test_mirror import _with  # the config-override context (one definition for the reconstruct tests)
from test_surface import _cameras  # head-centric cameras around the head (one definition for the surface tests)
from test_surface_coverage import _head_masks  # the fitted head's silhouette per view, as mattes


def _bald(views: int, frames=None) -> HeadSurface:
    return HeadSurface(np.zeros(100, np.float32), np.zeros((views, 53), np.float32), None, frames)


def test_frames_give_the_padding_at_any_size_and_follow_subset():
    s = _bald(2, [[0.0, 0.0, 1.0, 1.0], [0.25, -0.1, 1.2, 0.5]])
    pad = s.padding(8, 10)
    assert pad.shape == (2, 10, 8) and not bool(pad[0].any())
    assert bool(pad[1][:, :2].all()) and not bool(pad[1][:5, 2:].any())  # left quarter, bottom half
    assert bool(pad[1][5:].all())
    assert torch.equal(s.subset([1]).padding(8, 10)[0], pad[1])
    assert not bool(_bald(2).padding(4, 4).any())  # without frames: every pixel is the photo's
    with pytest.raises(ValueError, match="frames"):
        _bald(2, [[0.0, 0.0, 1.0, 1.0]])
    with pytest.raises(ValueError, match="frames"):
        _bald(1, [[0.5, 0.0, 0.4, 1.0]])


def test_from_tracking_reads_each_crops_frame_from_its_camera_and_its_photos():
    K = torch.tensor([[[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]]])
    photo = Cameras(K, torch.eye(4)[None], 100, 80)
    crop = photo.crop(-10, 30, 60, 60).resize(120, 120)  # 10 photo columns of padding left, 10 rows below
    fit = SimpleNamespace(identity=np.zeros(100, np.float32), expressions=np.zeros((1, 53), np.float32), head_to_world=None)
    s = HeadSurface.from_tracking(SimpleNamespace(fit=fit, cameras=crop, photo_cameras=[photo]))
    assert np.allclose(s.frames, [[10 / 60, -30 / 60, 110 / 60, 50 / 60]])  # the photo reaches beyond the crop on the right and the top
    pad = s.padding(120, 120)[0]
    assert int((~pad).sum()) == 100 * 100
    assert HeadSurface.from_tracking(fit).frames is None  # a fit alone has no crops


def _cut(fg: torch.Tensor, view: int, right: float):
    """The matte of ``view`` emptied beyond ``right`` (a fraction of the width), as a photo's frame would."""
    out = fg.clone()
    out[view, :, int(round(right * fg.shape[-1])) :] = 0.0
    return out


def test_the_padding_neither_carves_the_hair_nor_thins_its_fit():
    cams = _cameras([0.0, 70.0]).to(dtype=torch.float32)
    fg = _head_masks(_bald(2), cams, 0.02)  # the person's outline: 2 cm of hair all round
    cols = torch.nonzero(fg[1].any(0))[:, 0]
    right = (int(cols.min()) + int(cols.max())) / 2 / fg.shape[-1]  # the side view's frame cuts the head in half
    cut = _cut(fg, 1, right)
    framed = _bald(2, [[0.0, 0.0, 1.0, 1.0], [0.0, 0.0, right, 1.0]])
    w = hair_vertex_weight(HeadModel.load()) > 0
    plain = hair_carve_fractions(_bald(2), cams, cut, 0.02)
    kept = hair_carve_fractions(framed, cams, cut, 0.02)
    assert float((plain[w] < 1).mean()) > 0.1  # read as background, the cut carves the hair
    assert np.array_equal(kept, hair_carve_fractions(_bald(2), cams, fg, 0.02))  # as padding, as if uncut
    assert fit_hair_thickness(framed, cams, cut) == fit_hair_thickness(_bald(2), cams, fg)


def test_reconstruct_does_not_carve_the_shell_into_the_padding():
    from fastgha_core.constants import BACKGROUND_RGB
    from fastgha_core.model.fastgha import load_model
    from fastgha_core.model.prior import back_shell_vertices
    from test_surface_hair_shell import _inputs

    tiny = load_model("tiny")
    imgs, cams, surface, fg = _inputs(tiny, [0.0, 70.0], hair_m=0.0)
    cols = torch.nonzero(fg[1].any(0))[:, 0]
    right = (int(cols.min()) + int(cols.max())) / 2 / fg.shape[-1]
    cut = _cut(fg, 1, right)
    bg = torch.tensor(BACKGROUND_RGB).view(1, 3, 1, 1)
    imgs_cut = imgs * cut[:, None] + bg * (1 - cut[:, None])
    framed = HeadSurface(surface.identity, surface.expressions, None, [[0.0, 0.0, 1.0, 1.0], [0.0, 0.0, right, 1.0]])
    k = len(back_shell_vertices(tiny.head_basis()))

    def shell(images, surf):
        with _with(tiny, mirror_views=False):
            av = tiny.reconstruct(images, cams, surface=surf)
        return av.gaussians.means[av.num_reconstructed : av.num_reconstructed + k]

    whole, cut_as_bg, cut_as_pad = shell(imgs, surface), shell(imgs_cut, surface), shell(imgs_cut, framed)
    moved = (whole - cut_as_bg).norm(dim=-1) > 1e-4
    assert int(moved.sum()) > 20  # the cut, read as background, pulls part of the shell in
    d_pad = (whole - cut_as_pad).norm(dim=-1) > 1e-4
    assert int(d_pad.sum()) <= int(moved.sum()) // 3  # read as padding, the shell is mostly as without the cut ...
    assert float((cut_as_pad.norm(dim=-1) - whole.norm(dim=-1)).min()) > -1e-6  # ... and nowhere pulled in further (the padding holds more than the uncut matte)


def test_head_json_frames_are_read_by_file_name():
    """head.json holds the frames by crop file name (``fastgha track``); ``fastgha reconstruct`` reads
    them for its images, in their order, and without a frame for every image uses none."""
    from fastgha_core.headfile import head_surface_from_json

    data = {"identity": [0.1] * 100, "frames": {"00_a.png": [0.0, 0.0, 1.0, 1.0], "01_b.png": [0.1, -0.2, 0.9, 1.0]}}
    expr = np.zeros((2, 53))
    s = head_surface_from_json(data, expr, names=["01_b.png", "00_a.png"])
    assert np.allclose(s.frames, [[0.1, -0.2, 0.9, 1.0], [0.0, 0.0, 1.0, 1.0]])
    assert head_surface_from_json(data, expr, names=["00_a.png", "02_new.png"]).frames is None  # a photo added after tracking
    assert head_surface_from_json({"identity": [0.1] * 100}, expr, names=["00_a.png", "01_b.png"]).frames is None  # a head.json from before frames
    with pytest.raises(ValueError, match="need the photos' names"):
        head_surface_from_json(data, expr)


def test_head_json_frame_errors_name_the_photo_and_what_came(caplog):
    """A wrong frame is refused naming its photo (by crop file name, as head.json keys it) and what
    came; values beyond [0, 1] are a photo reaching past the crop, and a photo without an entry
    gets a warning that names it (no frames are used then)."""
    import logging

    from fastgha_core.headfile import head_surface_from_json

    expr = np.zeros((2, 53))
    names = ["00_a.png", "01_b.png"]
    ok = [0.0, 0.0, 1.0, 1.0]
    with pytest.raises(ValueError, match=r"frames\['01_b.png'\] must be \[left, top, right, bottom\] \(4 numbers.*got 3 value"):
        head_surface_from_json({"identity": [0.1] * 100, "frames": {"00_a.png": ok, "01_b.png": [0.1, 0.2, 0.9]}}, expr, names=names)
    with pytest.raises(ValueError, match=r"frames\['00_a.png'\] = \[0.5, 0.0, 0.2, 1.0\] must have right > left"):
        head_surface_from_json({"identity": [0.1] * 100, "frames": {"00_a.png": [0.5, 0.0, 0.2, 1.0], "01_b.png": ok}}, expr, names=names)
    with pytest.raises(ValueError, match=r"frames\['01_b.png'\] must be a list of numbers, got str"):
        head_surface_from_json({"identity": [0.1] * 100, "frames": {"00_a.png": ok, "01_b.png": "0 0 1 1"}}, expr, names=names)
    with pytest.raises(ValueError, match=r"frames\[1\] must be \[left, top, right, bottom\] \(4 numbers.*got 5 value"):
        head_surface_from_json({"identity": [0.1] * 100, "frames": [ok, ok + [1.0]]}, expr)
    wide = head_surface_from_json({"identity": [0.1] * 100, "frames": {"00_a.png": [-0.47, 0.07, 1.73, 2.27], "01_b.png": ok}}, expr, names=names)
    pad = wide.padding(100, 100)[0]  # the photo starts 7 % down the crop and covers the rest of it
    assert np.allclose(wide.frames[0], [-0.47, 0.07, 1.73, 2.27]) and bool(pad[:7].all()) and not bool(pad[7:].any())
    with caplog.at_level(logging.WARNING, logger="fastgha_core.headfile"):
        s = head_surface_from_json({"identity": [0.1] * 100, "frames": {"00_a.png": ok, "01_typo.png": ok}}, expr, names=names)
    assert s.frames is None and "01_b.png" in caplog.text and "padding reads as background" in caplog.text
