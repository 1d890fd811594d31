"""On-disk layout round trip, request folders, the synth CLI and the shipped samples."""

import json
from pathlib import Path

import pytest
import torch

from fastgha_core.cameras import Cameras, load_request_folder
from fastgha_core.cli import main
from fastgha_core.data.layout import DEPTH_UNIT_M, open_dataset, write_request_folder, write_sequence
from fastgha_core.data.sample import View
from fastgha_core.data.samples import list_samples, load_sample
from fastgha_core.data.synthetic import make_sequence


def _q(x):  # what an 8-bit file stores
    return torch.round(x.clamp(0, 1) * 255) / 255


class _MovingSource:
    """A tiny hand-made source whose cameras change per timestep (e.g. a tracked head pose)."""

    subject, sequence, expression_space = "toy", "take1", "flame120"
    num_timesteps, num_cameras = 2, 2

    def cameras(self, t):
        eye = torch.tensor([[0.0, 0.0, 1.0 + 0.1 * t], [0.5, 0.0, 0.8]])
        return Cameras.look_at(eye, fov_deg=30, width=24, height=16)

    def expression(self, t):
        return torch.arange(120, dtype=torch.float32) * (t + 1) / 1000

    def view(self, t, c):
        g = torch.Generator().manual_seed(10 * t + c)
        return View(image=torch.rand(3, 16, 24, generator=g), mask=torch.rand(1, 16, 24, generator=g), depth=None)


def test_round_trip_synthetic(tmp_path):
    src = make_sequence(5, timesteps=2, num_cameras=3, resolution=40)
    folder = write_sequence(tmp_path, src)
    assert folder == tmp_path / src.subject / src.sequence
    (seq,) = open_dataset(tmp_path)
    assert (seq.subject, seq.sequence, seq.expression_space) == (src.subject, src.sequence, "ict53")
    assert (seq.num_timesteps, seq.num_cameras) == (2, 3)
    for t in range(2):
        torch.testing.assert_close(seq.cameras(t).K, src.cameras(t).K)
        torch.testing.assert_close(seq.cameras(t).w2c, src.cameras(t).w2c)
        torch.testing.assert_close(seq.expression(t), src.expression(t), rtol=0, atol=0)
        for c in range(3):
            a, b = seq.view(t, c), src.view(t, c)
            torch.testing.assert_close(a.image, _q(b.image), atol=1e-6, rtol=0)
            torch.testing.assert_close(a.mask, _q(b.mask), atol=1e-6, rtol=0)
            torch.testing.assert_close(a.depth, b.depth, atol=DEPTH_UNIT_M / 2 + 1e-6, rtol=0)
    # the same dataset opened at the subject and the sequence level
    assert len(open_dataset(tmp_path / src.subject)) == 1 and len(open_dataset(folder)) == 1


def test_round_trip_moving_cameras_jpeg_no_depth(tmp_path):
    src = _MovingSource()
    write_sequence(tmp_path, src, image_format="jpg")
    (seq,) = open_dataset(tmp_path)
    assert json.loads((tmp_path / "toy/take1/meta.json").read_text())["cameras_per_timestep"] is True
    for t in range(2):
        torch.testing.assert_close(seq.cameras(t).w2c, src.cameras(t).w2c)
        assert seq.expression(t).shape == (120,)
        v = seq.view(t, 1)
        assert v.depth is None and v.image.shape == (3, 16, 24)
        torch.testing.assert_close(v.mask, _q(src.view(t, 1).mask), atol=1e-6, rtol=0)
        assert (v.image - src.view(t, 1).image).abs().mean() < 0.1  # JPEG of noise: lossy but close
    assert not torch.equal(seq.cameras(0).w2c, seq.cameras(1).w2c)


def test_open_dataset_errors(tmp_path):
    with pytest.raises(ValueError, match="no sequences"):
        open_dataset(tmp_path)
    with pytest.raises(ValueError, match="does not exist"):
        open_dataset(tmp_path / "missing")


def test_request_folder_round_trip(tmp_path):
    src = _MovingSource()
    views = [src.view(0, 0), src.view(1, 1), src.view(0, 1)]
    cams = [src.cameras(0)[0:1], src.cameras(1)[1:2], src.cameras(0)[1:2]]
    write_request_folder(tmp_path / "req", views, cams)
    paths, loaded = load_request_folder(tmp_path / "req")
    assert [p.name for p in paths] == ["00.png", "01.png", "02.png"]
    for c_in, c_out in zip(cams, loaded):
        torch.testing.assert_close(c_out.w2c, c_in.w2c)
    with pytest.raises(ValueError, match="one camera per view"):
        write_request_folder(tmp_path / "bad", views, cams[:2])


def test_synth_cli_tiny_and_deterministic(tmp_path):
    args = ["synth", "--subjects", "2", "--timesteps", "2", "--cameras", "3", "--resolution", "32", "--seed", "40"]
    assert main(args + ["--out", str(tmp_path / "a")]) == 0
    assert main(args + ["--out", str(tmp_path / "b")]) == 0
    seqs = open_dataset(tmp_path / "a")
    assert [s.subject for s in seqs] == ["synth_0000040", "synth_0000041"]
    files_a = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(tmp_path / "b") for p in (tmp_path / "b").rglob("*") if p.is_file())
    assert files_a == files_b and len(files_a) > 20
    for f in files_a:
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    paths, cams = load_request_folder(tmp_path / "a" / "synth_0000040" / "request")
    assert len(paths) == 2  # min(4, timesteps, cameras)
    info = json.loads((tmp_path / "a/synth_0000040/request/info.json").read_text())
    assert len(set(info["timesteps"])) == 2 and len(set(info["cameras"])) == 2
    # the request photos are the dataset's views
    seq = seqs[0]
    for p, t, c in zip(paths, info["timesteps"], info["cameras"]):
        assert p.read_bytes() == (tmp_path / "a/synth_0000040/seq000/timesteps" / f"{t:05d}" / f"{c:02d}.png").read_bytes()
        torch.testing.assert_close(seq.cameras(t)[c : c + 1].w2c, cams[paths.index(p)].w2c)
    # held-out range is enforced
    assert main(["synth", "--out", str(tmp_path / "c"), "--subjects", "1", "--seed", "1000000"]) == 2
    assert main(["synth", "--out", str(tmp_path / "c"), "--subjects", "1", "--seed", "5", "--heldout"]) == 2


def test_shipped_samples_load():
    names = list_samples()
    assert len(names) == 3
    for name in names:
        s = load_sample(name)
        V, T = s.request_images.shape[0], s.expressions.shape[0]
        assert V == 4 and s.request_images.shape[1:] == (3, 256, 256)
        assert s.request_masks.shape == (4, 1, 256, 256) and len(s.request_cameras) == 4
        assert s.expressions.shape == (T, 53) and 40 <= T <= 64 and s.expression_space == "ict53"
        assert len(s.orbit_cameras) == T and s.gt_frames.shape == (T, 3, 256, 256)
        assert s.meta["seed"] >= 1_000_000  # held-out
        # the head is where the cameras look: the centre projects inside its photo's mask
        uv, _ = s.request_cameras.project(torch.zeros(1, 3))
        for i in range(4):
            u, v = uv[i, 0].long().tolist()
            assert s.request_masks[i, 0, v, u] > 0.5
        # ground-truth frames: white background at the corners, a head in the middle
        assert (s.gt_frames[:, :, :4, :4] > 0.95).all() and (s.gt_frames[:, :, 120:136, 120:136] < 0.9).any()
        size = sum(f.stat().st_size for f in Path(s.folder).rglob("*") if f.is_file())
        assert size < 1.5e6
    with pytest.raises(ValueError, match="unknown sample"):
        load_sample("nobody")


def test_synth_rerun_replaces_its_own_subjects_and_refuses_foreign_folders(tmp_path, capsys):
    """A second ``fastgha synth`` into the same folder with fewer timesteps / cameras left the first
    run's files beside the new ones: a request folder of 4 photos with 2 cameras. Now a subject
    folder synth wrote is replaced as a whole, and one it did not write is refused before anything
    is written."""
    base = ["synth", "--subjects", "1", "--seed", "40", "--out", str(tmp_path / "d")]
    assert main(base + ["--timesteps", "4", "--cameras", "5", "--resolution", "48"]) == 0
    assert main(base + ["--timesteps", "2", "--cameras", "2", "--resolution", "32"]) == 0
    expected = tmp_path / "e"
    assert main(["synth", "--subjects", "1", "--seed", "40", "--out", str(expected), "--timesteps", "2", "--cameras", "2", "--resolution", "32"]) == 0
    got = sorted(p.relative_to(tmp_path / "d") for p in (tmp_path / "d").rglob("*"))
    assert got == sorted(p.relative_to(expected) for p in expected.rglob("*"))  # nothing of the first run is left
    paths, cams = load_request_folder(tmp_path / "d" / "synth_0000040" / "request")
    assert len(paths) == len(cams) == 2
    foreign = tmp_path / "f" / "synth_0000041"
    foreign.mkdir(parents=True)
    (foreign / "notes.txt").write_text("mine")
    capsys.readouterr()
    assert main(["synth", "--subjects", "2", "--seed", "40", "--out", str(tmp_path / "f"), "--timesteps", "2", "--cameras", "2"]) == 2
    assert "was not written by fastgha synth" in capsys.readouterr().err
    assert sorted(p.name for p in (tmp_path / "f").iterdir()) == ["synth_0000041"]  # seed 40 not written either
    assert (foreign / "notes.txt").read_text() == "mine"


def test_a_broken_sequence_folder_is_named_in_the_error(tmp_path):
    """A hand-edited meta.json that does not parse, or a folder without its cameras.json, gave
    "Expecting property name ..." or a bare "[Errno 2]" without saying which file."""
    assert main(["synth", "--subjects", "1", "--timesteps", "2", "--cameras", "2", "--resolution", "32", "--out", str(tmp_path)]) == 0
    seq = tmp_path / "synth_0000000" / "seq000"
    (seq / "cameras.json").unlink()
    with pytest.raises(ValueError, match=r"seq000 has meta.json but no cameras.json"):
        open_dataset(tmp_path)
    (seq / "meta.json").write_text("{format: 1}")
    with pytest.raises(ValueError, match=r"seq000/meta.json does not parse as JSON: Expecting property name"):
        open_dataset(tmp_path)
