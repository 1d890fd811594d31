"""The leave-one-out report's table (``fastgha_core.refine.realsets.summary_table``): means per set and
step count, and the face counts of the renders beside those of the left-out photos themselves."""

from fastgha_core.refine.realsets import list_sets, summary_table


def _row(left_out, psnr, render, photo, ident=0.5, steps=0, s="a"):
    return {"set": s, "left_out": left_out, "steps": steps, "masked_psnr": psnr, "masked_ssim": 0.8,
            "identity_distance": ident, "faces_in_render": render, "faces_in_photo": photo, "refine_s": 0.0}


def test_summary_counts_faces_in_renders_and_in_the_left_out_photos():
    rows = [
        _row("00", 10.0, 1, 1),
        _row("01", 14.0, 0, 0, ident=None),  # a profile: dlib misses the photo too
        _row("02", 12.0, 2, 1),  # a doubled face
        _row("00", 20.0, 1, 1, s="b"),
    ]
    lines = summary_table(rows).strip().splitlines()
    assert lines[0].count("|") == lines[1].count("|") == 9
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
    assert cells[5:] == ["n/a", "n/a", "n/a"]


def test_list_sets_keeps_folders_with_two_photos(tmp_path):
    (tmp_path / "one").mkdir()
    (tmp_path / "one" / "a.jpg").write_bytes(b"x")
    (tmp_path / "two").mkdir()
    for n in ("a.jpg", "b.PNG", "notes.txt"):
        (tmp_path / "two" / n).write_bytes(b"x")
    assert [p.name for p in list_sets(tmp_path)] == ["two"]
    assert list_sets(tmp_path / "absent") == []
