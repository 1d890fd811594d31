"""The leave-one-out report's table (``fastgha_core.refine.realsets.summary_table``): means per set and
step count, and the face counts of the renders beside those of the left-out photos themselves."""

import pytest
import torch

from fastgha_core.refine.realsets import beyond_mask, error_split, list_sets, summary_table


def _row(left_out, psnr, render, photo, ident=0.5, steps=0, s="a", cnn=(None, None), split=(None, None, None), beyond=None, outline=None):
    return {"set": s, "left_out": left_out, "steps": steps, "masked_psnr": psnr, "masked_ssim": 0.8,
            "identity_distance": ident, "faces_in_render": render, "faces_in_photo": photo, "refine_s": 0.0,
            "cnn_faces_in_render": cnn[0], "cnn_faces_in_photo": cnn[1],
            "uncovered_frac": split[0], "psnr_uncovered_only": split[1], "psnr_covered_only": split[2], "beyond_mask_frac": beyond,
            "outline_error_share": outline}


def test_summary_counts_faces_in_renders_and_in_the_left_out_photos():
    rows = [
        _row("00", 10.0, 1, 1),
        _row("01", 14.0, 0, 0, ident=None),  # a profile: dlib misses the photo too
        _row("02", 12.0, 2, 1),  # a doubled face
        _row("00", 20.0, 1, 1, s="b"),
    ]
    lines = summary_table(rows).strip().splitlines()
    assert lines[0].count("|") == lines[1].count("|") == 16
    a = [c.strip() for c in lines[2].strip("|").split("|")]
    assert a[0] == "a" and a[2] == "3"
    assert a[3] == "12.00"  # mean PSNR over the three left-out photos
    assert a[5] == "0.500"  # the photo without a descriptor is left out of the mean
    assert a[6] == "1/3" and a[7] == "2/3"
    b = [c.strip() for c in lines[3].strip("|").split("|")]
    assert b[0] == "b" and b[6] == "1/1" and b[7] == "1/1"


def test_summary_without_a_face_detector_says_n_a():
    rows = [_row("00", 10.0, None, None, ident=None)]
    cells = [c.strip() for c in summary_table(rows).strip().splitlines()[2].strip("|").split("|")]
    assert cells[5:] == ["n/a"] * 10


def test_summary_gives_the_cnn_counts_and_the_error_split():
    rows = [
        _row("00", 10.0, 0, 0, cnn=(1, 1), split=(0.10, 12.0, 20.0), beyond=0.25, outline=0.5),  # a profile HOG misses, the CNN finds
        _row("01", 14.0, 1, 1, cnn=(2, 1), split=(0.02, 24.0, 16.0), beyond=0.05, outline=0.2),  # a doubled face by the CNN
    ]
    cells = [c.strip() for c in summary_table(rows).strip().splitlines()[2].strip("|").split("|")]
    assert cells[6:10] == ["1/2", "1/2", "1/2", "2/2"]
    assert cells[10:] == ["6.0%", "18.00", "18.00", "35.0%", "15.0%"]


def test_error_split_adds_up_to_the_masked_error():
    g = torch.Generator().manual_seed(0)
    pred, target = torch.rand(3, 20, 20, generator=g), torch.rand(3, 20, 20, generator=g)
    mask = torch.zeros(1, 20, 20)
    mask[:, 2:18, 2:18] = 1
    alpha = torch.ones(1, 20, 20)
    alpha[:, 2:6] = 0.2  # the top rows of the mask are not covered by the render
    out = error_split(pred, target, mask, alpha)
    m = mask[0] > 0.5
    assert out["uncovered_frac"] == pytest.approx(4 * 16 / 256)
    se = ((pred - target) ** 2).sum(0)
    n3 = 3 * int(m.sum())
    assert out["psnr_uncovered_only"] == pytest.approx(float(-10 * torch.log10(se[2:6, 2:18].sum() / n3)), abs=1e-4)
    assert out["psnr_covered_only"] == pytest.approx(float(-10 * torch.log10(se[6:18, 2:18].sum() / n3)), abs=1e-4)
    total = 10 ** (-out["psnr_uncovered_only"] / 10) + 10 ** (-out["psnr_covered_only"] / 10)
    assert float(-10 * torch.log10(torch.tensor(total))) == pytest.approx(float(-10 * torch.log10(se[m].sum() / n3)), abs=1e-4)
    with pytest.raises(ValueError, match="mask is empty"):
        error_split(pred, target, torch.zeros(20, 20), alpha)


def test_error_split_gives_the_outlines_share_of_the_error():
    mask = torch.zeros(1, 20, 20)
    mask[:, 4:16, 4:16] = 1  # a 12 x 12 square: its outline is the outer ring of one pixel
    target = torch.zeros(3, 20, 20)
    alpha = torch.ones(1, 20, 20)
    ring = torch.zeros(20, 20, dtype=torch.bool)
    ring[4:16, 4:16] = True
    ring[5:15, 5:15] = False
    pred = target.clone()
    pred[:, ring] = 0.5  # error only on the outline
    assert error_split(pred, target, mask, alpha)["outline_error_share"] == pytest.approx(1.0)
    pred = target.clone()
    pred[:, 5:15, 5:15] = 0.5  # error only inside it
    assert error_split(pred, target, mask, alpha)["outline_error_share"] == pytest.approx(0.0)
    pred[:, ring] = 0.5  # equal error on every pixel: the ring's share of the pixels
    assert error_split(pred, target, mask, alpha)["outline_error_share"] == pytest.approx(44 / 144)
    assert error_split(target.clone(), target, mask, alpha)["outline_error_share"] is None  # no error at all


def test_error_split_gives_the_gain_matched_psnr_and_the_bottom_rows_share():
    g = torch.Generator().manual_seed(1)
    target = 0.2 + 0.6 * torch.rand(3, 20, 20, generator=g)
    mask = torch.ones(1, 20, 20)
    alpha = torch.ones(1, 20, 20)
    darker = target * torch.tensor([0.8, 0.9, 1.1]).view(3, 1, 1)  # the photo under another exposure and white balance
    out = error_split(darker, target, mask, alpha)
    assert out["psnr_gain_matched"] > 80  # one gain per channel undoes it: no error left (float rounding only)
    noisy = darker + 0.05 * torch.randn(3, 20, 20, generator=g)
    out = error_split(noisy, target, mask, alpha)
    se = ((noisy - target) ** 2).sum(0)
    assert out["psnr_gain_matched"] > float(-10 * torch.log10(se.sum() / (3 * 400))) + 3
    pred = target.clone()
    pred[:, 14:] += 0.1  # error only in the bottom 30 % of the rows (rows 14-19 of 20)
    assert error_split(pred, target, mask, alpha)["bottom_error_share"] == pytest.approx(1.0)
    pred = target.clone()
    pred[:, :14] += 0.1
    assert error_split(pred, target, mask, alpha)["bottom_error_share"] == pytest.approx(0.0)


def test_list_sets_keeps_folders_with_two_photos(tmp_path):
    (tmp_path / "one").mkdir()
    (tmp_path / "one" / "a.jpg").write_bytes(b"x")
    (tmp_path / "two").mkdir()
    for n in ("a.jpg", "b.PNG", "notes.txt"):
        (tmp_path / "two" / n).write_bytes(b"x")
    assert [p.name for p in list_sets(tmp_path)] == ["two"]
    assert list_sets(tmp_path / "absent") == []


def test_mirror_variant_sets_the_named_fields_and_restores_every_one():
    """``--mirror`` variants (``refine.realsets.mirror_variant``): the given fields are set, the empty or
    left-out ones keep the config's value, and all are restored after the block, even on an error."""
    from fastgha_core.config import GaussianHeadConfig
    from fastgha_core.refine.realsets import MIRROR_FIELDS, mirror_variant

    g = GaussianHeadConfig()
    before = {f: getattr(g, f) for f in MIRROR_FIELDS}
    with mirror_variant(g, "25//5"):
        assert g.mirror_views and g.mirror_min_yaw_deg == 25.0 and g.mirror_midline_m == 0.005
        assert g.mirror_drop_seen_deg == before["mirror_drop_seen_deg"] and g.mirror_blend_offset_deg == before["mirror_blend_offset_deg"]
    assert {f: getattr(g, f) for f in MIRROR_FIELDS} == before
    with mirror_variant(g, "30///0"):
        assert g.mirror_blend_offset_deg == 0.0 and g.mirror_min_yaw_deg == 30.0
    with pytest.raises(RuntimeError):
        with mirror_variant(g, "off"):
            assert not g.mirror_views
            raise RuntimeError("inside")
    assert {f: getattr(g, f) for f in MIRROR_FIELDS} == before
    with mirror_variant(g, None):
        assert {f: getattr(g, f) for f in MIRROR_FIELDS} == before


def test_beyond_mask_counts_what_the_render_draws_outside_the_photos_outline():
    mask = torch.zeros(1, 40, 40)
    mask[:, 10:30, 10:30] = 1  # 400 pixels
    alpha = torch.zeros(1, 40, 40)
    alpha[:, 10:30, 10:30] = 1.0
    assert beyond_mask(alpha, mask) == 0.0  # the render fills the outline and stops there
    alpha[:, 5:10, 10:30] = 0.9  # 5 rows above the outline: the 2 rows beyond the 3-pixel margin count
    assert beyond_mask(alpha, mask) == pytest.approx(2 * 20 / 400)
    assert beyond_mask(alpha, mask, dilate_px=0) == pytest.approx(5 * 20 / 400)
    alpha[:, 30:40, 10:30] = 0.3  # faint: below the 0.5 threshold, not drawn
    assert beyond_mask(alpha, mask) == pytest.approx(2 * 20 / 400)
    frame = torch.ones(40, 40, dtype=torch.bool)
    frame[:8] = False  # the photo ends 8 rows from the crop's top: the padding above is not the photo's background
    assert beyond_mask(alpha, mask, frame) == 0.0
    with pytest.raises(ValueError, match="mask is empty"):
        beyond_mask(alpha, torch.zeros(40, 40))
    with pytest.raises(ValueError, match="one size"):
        beyond_mask(alpha, mask, torch.ones(20, 20, dtype=torch.bool))
