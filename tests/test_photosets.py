"""Synthetic photo sets laid out like the real sets (``fastgha_core/data/photosets.py``) and the
leave-one-out evaluation run on them end to end (``python -m fastgha_core.refine.realsets --synthetic``)."""

import json

import numpy as np
import pytest
from PIL import Image

from fastgha_core.data.photosets import PHOTOSET_VIEWS, photo_name, photoset_truth, write_photoset


def _pixels(path):
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"), dtype=np.int16)


def test_a_set_is_named_by_its_poses_and_a_pure_function_of_its_seed(tmp_path):
    views = ((0.0, 0.0), (40.0, 0.0))
    a = write_photoset(tmp_path / "a", 1_000_700, views, size=96)
    b = write_photoset(tmp_path / "b", 1_000_700, views, size=96)
    c = write_photoset(tmp_path / "c", 1_000_701, views, size=96)
    assert [p.name for p in a] == ["00_yaw+0_pitch+0.jpg", "01_yaw+40_pitch+0.jpg"]
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == [p.name for p in a]  # photos only: no cameras, no masks
    assert _pixels(a[0]).shape == (96, 96, 3)
    for p, q in zip(a, b):
        assert np.array_equal(_pixels(p), _pixels(q))
    assert np.abs(_pixels(a[0]) - _pixels(a[1])).mean() > 5  # another view
    assert np.abs(_pixels(a[0]) - _pixels(c[0])).mean() > 5  # another person


def test_the_name_carries_whole_signed_degrees_that_the_tracking_report_reads_back():
    from fastgha_core.tracking.realsets import annotated_pitch, annotated_yaw

    assert photo_name(3, -64.6, 25.2) == "03_yaw-65_pitch+25.jpg"
    assert photo_name(0, 0.0, -10.0) == "00_yaw+0_pitch-10.jpg"
    for yaw, pitch in ((-65.0, 25.0), (0.0, -10.0), (70.0, 0.0)):
        name = photo_name(1, yaw, pitch)
        assert (annotated_yaw(name), annotated_pitch(name)) == (yaw, pitch)
    assert annotated_pitch("03_yaw0_pitch-down.jpg") is None  # the real sets' names carry no pitch figure


@pytest.mark.parametrize("kwargs, match", [
    ({"seed": 5}, "held-out seeds"),
    ({"views": ()}, "at least one"),
    ({"views": ((95.0, 0.0),)}, r"\|yaw\| <= 90"),
    ({"size": 32}, ">= 64"),
    ({"jpeg_quality": 0}, "1-100"),
])  # fmt: skip
def test_bad_arguments_are_refused_before_anything_is_written(tmp_path, kwargs, match):
    args = {"folder": tmp_path / "s", "seed": 1_000_700, "views": PHOTOSET_VIEWS, "size": 64} | kwargs
    with pytest.raises(ValueError, match=match):
        write_photoset(**args)
    assert not (tmp_path / "s").exists()


def test_the_tracker_reads_the_yaw_the_names_carry(tmp_path):
    """The names follow the real sets' sign convention (+ = nose towards the image's right edge), which
    the tracker's yaw shares: a set with both signs and a pitched photo tracks to within 15 degrees of them."""
    pytest.importorskip("mediapipe", reason="needs the faces extra (MediaPipe Face Mesh)")
    from fastgha_core.tracking.realsets import evaluate_realsets

    write_photoset(tmp_path / "syn", 1_000_700, ((0.0, 0.0), (-45.0, 0.0), (40.0, 0.0), (0.0, 25.0)), size=384)
    rows = evaluate_realsets(tmp_path)
    assert [r["yaw_annotated"] for r in rows] == [0.0, -45.0, 40.0, 0.0]
    for r in rows:
        assert r["yaw_error"] <= 15.0, r
    assert rows[3]["pitch"] > rows[0]["pitch"] + 10.0  # the pitched-up photo reads nose up
    assert [r["pitch_annotated"] for r in rows] == [0.0, 0.0, 0.0, 25.0]
    assert max(r["pitch_error"] for r in rows) <= 10.0
    assert all(r["rotation_error"] is None for r in rows)  # not a syn<seed> folder of the default views: no truth


def test_the_tracking_report_measures_synthetic_sets_against_their_true_poses(tmp_path):
    """``tracking.realsets`` on a ``syn<seed>`` folder of the default views: each photo's rotation
    error against ``photoset_truth``'s cameras (a wrong convention, e.g. a transposed rotation,
    would put the turned photos at twice their yaw), and the summary lines per annotated yaw."""
    pytest.importorskip("mediapipe", reason="needs the faces extra (MediaPipe Face Mesh)")
    from fastgha_core.tracking.realsets import evaluate_realsets, rotation_summary

    write_photoset(tmp_path / "syn1000700", 1_000_700, size=384)
    rows = evaluate_realsets(tmp_path)
    errs = {r["yaw_annotated"]: r["rotation_error"] for r in rows if r["pitch_annotated"] == 0.0}
    assert set(errs) == {0.0, -65.0, 40.0, 70.0}
    assert errs[0.0] <= 6.0 and errs[40.0] <= 8.0 and max(errs.values()) <= 15.0, rows
    text = rotation_summary(rows)
    assert text.splitlines()[0].startswith("5 photos with a known pose: rotation error median")
    assert "annotated yaw 70: 1 photos" in text and rotation_summary([dict(r, rotation_error=None) for r in rows]) is None


def test_leave_one_out_runs_end_to_end_on_a_synthetic_set(tmp_path, capsys):
    """The real sets' protocol (tracking, an avatar from the other photos, the left-out camera) on a
    held-out synthetic subject: one row per photo, each render scored inside its photo's mask."""
    pytest.importorskip("mediapipe", reason="needs the faces extra (MediaPipe Face Mesh)")
    from fastgha_core.refine.realsets import main

    out, grid = tmp_path / "rows.json", tmp_path / "grid.png"
    assert main(["--synthetic", "1", "--root", str(tmp_path / "sets"), "--refine-steps", "0", "--no-cnn-faces", "--own-cameras", "--json", str(out), "--grid", str(grid)]) == 0
    printed = capsys.readouterr().out
    assert "1 synthetic photo set(s) written to" in printed
    assert f"grid written to {grid} (rows: left-out photos; columns: left-out photo, 0 refine steps)" in printed
    # a band of column titles, then one row of two cells (photo, render) per photo at the tracker's 256²
    assert np.asarray(Image.open(grid)).shape == (22 + len(PHOTOSET_VIEWS) * 258 + 2, 2 * 258 + 2, 3)
    rows = json.loads(out.read_text())
    own = [r for r in rows if r.get("check") == "own_camera"]
    rows = [r for r in rows if r.get("check") != "own_camera"]
    # the input-view check: the avatar of all photos at each photo's own camera, scored as the leave-one-out renders
    assert sorted(r["photo"] for r in own) == sorted(photo_name(i, y, p) for i, (y, p) in enumerate(PHOTOSET_VIEWS))
    for r in own:
        assert r["uncovered_frac"] < 0.05 and 0.0 <= r["outline_error_share"] <= 1.0 and r["beyond_mask_frac"] >= 0.0, r
    assert "syn1000700: avatar of all photos at their own cameras" in printed and "error on the mask's outline" in printed
    assert sorted(r["left_out"] for r in rows) == sorted(photo_name(i, y, p) for i, (y, p) in enumerate(PHOTOSET_VIEWS))
    for r in rows:
        assert r["set"] == "syn1000700" and r["steps"] == 0
        assert r["uncovered_frac"] < 0.1, r  # the avatar is drawn where the left-out photo's head is
    # the set's mean: synthetic sets measure 17-20 dB (docs/model-card-log.md), a white render 3-7 dB
    assert 15.0 < np.mean([r["masked_psnr"] for r in rows]) < 40.0
    assert np.mean([r["masked_psnr"] for r in own]) > np.mean([r["masked_psnr"] for r in rows])  # its own photos are matched better than left-out ones
    from fastgha_core.train.faces import load_face_metrics

    if load_face_metrics() is not None:  # dlib's face descriptor: each scored render is the same person as its photo
        scored = [r["identity_distance"] for r in rows if r["identity_distance"] is not None]
        assert scored and max(scored) < 0.6, rows


def test_synthetic_sets_are_never_written_among_other_photo_sets(tmp_path, capsys):
    from fastgha_core.refine.realsets import main

    real = tmp_path / "phone-5"
    real.mkdir()
    for i in range(2):
        Image.new("RGB", (8, 8)).save(real / f"{i:02d}.jpg")
    with pytest.raises(SystemExit):
        main(["--synthetic", "1", "--root", str(tmp_path)])
    assert "holds other photo sets (phone-5)" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["phone-5"]
    with pytest.raises(SystemExit):
        main(["--first-seed", "1000700"])  # a seed without --synthetic
    assert "--first-seed needs --synthetic" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["--synthetic", "2", "--first-seed", "1009999"], "would use 1009999-1010000"),  # the range runs past the held-out seeds
    (["--synthetic", "1", "--sets", "phone-5"], "--sets picks among the real sets"),
    (["--synthetic", "1", "--root", "FILE"], "is a file"),
    (["--synthetic", "0", "--truth", "cameras"], "--truth needs --synthetic"),
])  # fmt: skip
def test_synthetic_arguments_that_cannot_work_are_refused_before_anything_is_written(tmp_path, capsys, argv, message):
    from fastgha_core.refine.realsets import main

    (tmp_path / "a_file").write_text("not a folder")
    argv = [str(tmp_path / "a_file") if a == "FILE" else a for a in argv]
    if "--root" not in argv:
        argv += ["--root", str(tmp_path / "sets")]
    with pytest.raises(SystemExit):
        main(argv)
    assert message in capsys.readouterr().err
    assert not (tmp_path / "sets").exists()


def test_the_truth_is_what_the_photos_were_drawn_from(tmp_path):
    """``photoset_truth`` recomputed from the seed renders the written photos again (JPEG error only)."""
    from fastgha_core.data.synthetic import SyntheticSubject

    views = ((0.0, 0.0), (-65.0, 0.0), (0.0, 25.0))
    paths = write_photoset(tmp_path, 1_000_701, views, size=96)
    truth = photoset_truth(1_000_701, views, size=96)
    assert truth.expressions.shape == (3, 53) and len(truth.cameras.flatten().K) == 3
    assert ((truth.expressions > 0).sum(1) >= 2).all() and truth.expressions.max() <= 0.5
    subject = SyntheticSubject(1_000_701)
    np.testing.assert_array_equal(truth.identity, subject.identity)
    for i, path in enumerate(paths):
        rgb = subject.render(subject.frame(truth.expressions[i]), truth.cameras[i : i + 1])[0].image.permute(1, 2, 0).numpy()
        mse = np.mean((rgb - _pixels(path) / 255.0) ** 2)
        assert -10 * np.log10(mse) > 30.0, (path.name, mse)
    other = photoset_truth(1_000_702, views, size=96)
    assert not np.allclose(other.expressions, truth.expressions)


def test_the_truth_replaces_what_tracking_found(tmp_path):
    """``--truth``'s remake of a tracking result: the photos' cameras are the true ones, the identity
    and expressions too with ``all``; the crops are cut around the true head."""
    pytest.importorskip("mediapipe", reason="needs the faces extra (MediaPipe Face Mesh)")
    from fastgha_core.refine.realsets import _with_truth
    from fastgha_core.tracking import track_photos
    from fastgha_core.tracking.pipeline import TrackConfig

    views = ((0.0, 0.0), (40.0, 0.0), (0.0, 25.0))
    paths = write_photoset(tmp_path, 1_000_700, views, size=384)
    photos = [_pixels(p) for p in paths]
    names = [p.name for p in paths]
    truth = photoset_truth(1_000_700, views, size=384)
    idx = [2, 0]  # a subset in another order (as after a dropped photo): the truth's rows follow idx
    photos, names = [photos[i] for i in idx], [names[i] for i in idx]
    tr = track_photos(photos, TrackConfig(size=128), names=names)
    for parts in ("cameras", "all"):
        got = _with_truth(tr, photos, names, truth, idx, parts, 128)
        cams = got.photo_cameras.flatten()
        np.testing.assert_allclose(cams.w2c.numpy(), truth.cameras.flatten().w2c[idx].numpy(), atol=1e-5)
        np.testing.assert_allclose(cams.K.numpy(), truth.cameras.flatten().K[idx].numpy(), rtol=1e-6)
        head = got.cameras.flatten()  # the crops' cameras put the true head centre (the origin) mid-crop
        for v in range(2):
            c = head.K[v].double() @ head.w2c[v, :3, 3].double()
            assert np.allclose((c[:2] / c[2]).numpy(), 64.0, atol=8.0), (parts, v, c)
        if parts == "all":
            np.testing.assert_array_equal(got.expressions, truth.expressions[idx])
            np.testing.assert_allclose(got.fit.identity, truth.identity, atol=1e-6)
        else:
            np.testing.assert_array_equal(got.expressions, tr.expressions)
    with pytest.raises(ValueError, match="truth_parts must be one of"):
        from fastgha_core.refine.realsets import evaluate_set

        evaluate_set(None, tmp_path, [0], truth=truth, truth_parts="poses")


def test_grid_labels_follow_the_rows_to_their_columns():
    """Each left-out photo's row of the ``--grid`` picture: its set and name over the photo, then each
    render's masked PSNR and identity distance, under the column key its render is filed under."""
    from fastgha_core.refine.realsets import grid_labels, grid_titles

    rows = [{"set": "s", "left_out": f"{n}.jpg", "steps": st, "mirror": mv, "masked_psnr": 17.0 + st / 10 + n, "identity_distance": None if n else 0.456,
             "aligned_masked_psnr": 30.0, "aligned_identity_distance": 0.1} for n in (0, 1) for mv in ("off", "on") for st in (0, 30)]
    cols = [(("on", 30), "aligned"), ("off", 0), ("on", 30)]
    assert grid_labels(rows, cols) == [["s 0", "30.0 dB, id 0.10", "17.0 dB, id 0.46", "20.0 dB, id 0.46"],
                                       ["s 1", "30.0 dB, id 0.10", "18.0 dB, id -", "21.0 dB, id -"]]
    assert grid_titles([0, 30, ("off", 0), ((("on", 30)), "aligned")]) == [
        "left-out photo", "0 refine steps", "30 refine steps", "mirror off, 0 steps", "mirror on, 30 steps, aligned"]
