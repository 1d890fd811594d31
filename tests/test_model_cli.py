"""`fastgha reconstruct` and `fastgha animate` end to end with a toy model folder."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from fastgha_core.cameras import cameras_to_json, orbit_cameras
from fastgha_core.cli import main
from fastgha_core.config import DecoderConfig, DeformConfig, DinoConfig, FastGHAConfig, GaussianHeadConfig, TransformerConfig, VAEConfig
from fastgha_core.model.avatar import CanonicalAvatar
from fastgha_core.model.fastgha import FastGHA


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    cfg = FastGHAConfig(
        name="toy", expression_space="ict53", expression_dim=53, input_size=32, render_size=32,
        dino=DinoConfig(hidden_size=32, num_layers=2, num_heads=2, intermediate_size=64, feature_layers=(1, 2), out_channels=8, frozen=False),
        vae=VAEConfig(block_out_channels=(8, 8, 8, 8), layers_per_block=1, norm_num_groups=4, frozen=False),
        transformer=TransformerConfig(hidden_size=32, num_layers=1, num_heads=2),
        decoder=DecoderConfig(block_out_channels=(8, 8, 8, 8), layers_per_block=1, norm_num_groups=4),
        gaussians=GaussianHeadConfig(feature_dim=8, prune_opacity=0.2),
        deform=DeformConfig(hidden_size=16, num_layers=2, pe_freqs=2),
    )
    torch.manual_seed(0)
    folder = tmp_path_factory.mktemp("model") / "toy"
    FastGHA(cfg).save_pretrained(folder)
    return folder


def _request(folder, masks: bool, n: int = 3):
    folder.mkdir()
    cams = orbit_cameras(n, width=40, height=36)
    rng = np.random.default_rng(0)
    for i in range(n):
        Image.fromarray(rng.integers(0, 255, (36, 40, 3), dtype=np.uint8)).save(folder / f"view{i}.png")
        if masks:
            Image.fromarray(np.full((36, 40), 255, np.uint8)).save(folder / f"view{i}_mask.png")
    (folder / "cameras.json").write_text(json.dumps(cameras_to_json(cams)))
    return folder


def test_one_photo_and_one_frame_are_said_in_the_singular(tmp_path, model_dir, capsys):
    """The README's one-photo example (the astronaut) printed "from 1 views"; animate with its one
    tracked expression, "rendered 1 frames"."""
    req = _request(tmp_path / "req", masks=True, n=1)
    out = tmp_path / "avatar.safetensors"
    assert main(["reconstruct", "--input", str(req), "--model", str(model_dir), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"reconstructed {len(CanonicalAvatar.load(out))} Gaussians from 1 view at " in printed, printed
    (tmp_path / "one.json").write_text(json.dumps([{"jawOpen": 0.5}]))  # and animate's "rendered 1 frames"
    args = ["animate", "--avatar", str(out), "--model", str(model_dir), "--expressions", str(tmp_path / "one.json"),
            "--size", "24", "--out", str(tmp_path / "frames")]
    assert main(args) == 0
    assert "rendered 1 frame at 24^2 in " in capsys.readouterr().out


def test_reconstruct_then_animate(tmp_path, model_dir, capsys):
    req = _request(tmp_path / "req", masks=True)
    out, ply = tmp_path / "avatar.safetensors", tmp_path / "avatar.ply"
    assert main(["reconstruct", "--input", str(req), "--model", str(model_dir), "--out", str(out), "--ply", str(ply)]) == 0
    said = capsys.readouterr()
    printed = said.out
    assert f"loading model {str(model_dir)!r} ..." in said.err  # shown before the seconds of loading, not after
    avatar = CanonicalAvatar.load(out)
    assert f"reconstructed {len(avatar)} Gaussians from 3 views" in printed and " ms " in printed
    assert 0 < len(avatar) <= 3 * 32 * 32 and ply.exists()
    assert f"wrote the canonical Gaussians as a 3DGS PLY (static: unweighted opacities, no view blending) -> {ply}" in printed
    assert "view blending: off for this avatar (built on the network's depth" in printed  # no head.json here

    np.save(tmp_path / "seq.npy", np.random.default_rng(1).random((3, 53)).astype(np.float32))
    frames = tmp_path / "frames"
    args = ["animate", "--avatar", str(out), "--model", str(model_dir), "--expressions", str(tmp_path / "seq.npy"), "--size", "24"]
    assert main(args + ["--out", str(frames)]) == 0
    assert "loading model" in capsys.readouterr().err
    pngs = sorted(frames.glob("*.png"))
    assert len(pngs) == 3 and Image.open(pngs[0]).size == (24, 24)

    (tmp_path / "seq.json").write_text(json.dumps([{"jawOpen": 0.5}, {"eyeBlink_L": 1.0}]))
    (tmp_path / "cams.json").write_text(json.dumps(cameras_to_json(orbit_cameras(1, width=64, height=64))))
    video = tmp_path / "out.mp4"
    args = ["animate", "--avatar", str(out), "--model", str(model_dir), "--expressions", str(tmp_path / "seq.json"),
            "--cameras", str(tmp_path / "cams.json"), "--size", "32", "--out", str(video)]
    assert main(args) == 0
    import imageio.v3 as iio

    assert iio.imread(video, index=None).shape[0] == 2  # two frames


def test_animate_view_blend_tau_flag(tmp_path, model_dir, capsys):
    """``animate --view-blend-tau-deg``: the tau the frames use (as the server's setting), said in the
    summary; bad values are refused in one line before anything loads."""
    import dataclasses

    from fastgha_core.model.viewblend import ViewBlend

    req = _request(tmp_path / "req", masks=True)
    out = tmp_path / "avatar.safetensors"
    assert main(["reconstruct", "--input", str(req), "--model", str(model_dir), "--out", str(out)]) == 0
    avatar = CanonicalAvatar.load(out)
    n = avatar.num_reconstructed
    dirs = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    vb = ViewBlend((torch.arange(n) % 2).to(torch.int8), torch.full((n,), 3, dtype=torch.uint8), dirs)
    dataclasses.replace(avatar, view_blend=vb).save(tmp_path / "blended.safetensors")
    np.save(tmp_path / "seq.npy", np.zeros((2, 53), np.float32))
    args = ["animate", "--avatar", str(tmp_path / "blended.safetensors"), "--model", str(model_dir), "--expressions", str(tmp_path / "seq.npy"),
            "--size", "24", "--out", str(tmp_path / "frames")]  # fmt: skip
    capsys.readouterr()
    assert main(args + ["--view-blend-tau-deg", "35"]) == 0
    assert "views blended by angle (tau 35 deg)" in capsys.readouterr().out
    assert main(args + ["--view-blend-tau-deg", "0"]) == 0
    assert "views unweighted (tau 0: --view-blend-tau-deg 0" in capsys.readouterr().out
    for bad in ("-1", "nan", "1e9"):
        assert main(args + ["--view-blend-tau-deg", bad]) == 2
        err = capsys.readouterr().err
        assert "--view-blend-tau-deg: view_blend_tau_deg must be 0 (off)" in err and "loading model" not in err, err


def test_reconstruct_of_untracked_photos_suggests_a_track_command_that_works(tmp_path, model_dir, capsys, monkeypatch):
    """A folder of photos without cameras.json: the message suggests tracking them into a new folder
    (track refuses an --out that holds the photos), and that exact command's --out check passes."""
    photos = tmp_path / "me"
    photos.mkdir()
    for n in ("a.jpg", "b.JPG"):
        Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(photos / n, format="JPEG")
    assert main(["reconstruct", "--input", str(photos), "--model", str(model_dir), "--out", str(tmp_path / "a.safetensors")]) == 2
    err = capsys.readouterr().err
    assert f"`fastgha track --images {photos}/*.JPG {photos}/*.jpg --out out/me-tracked`" in err, err
    assert "then use --input out/me-tracked" in err
    from fastgha_core.commands.track import _earlier_run_files

    from fastgha_core.cli import CLIError

    monkeypatch.chdir(tmp_path)  # out/ of the working directory, not beside the photos (their folder may be read-only)
    assert not _earlier_run_files(Path("out/me-tracked"), sorted(photos.iterdir()))  # no refusal of that --out
    with pytest.raises(CLIError, match="already holds photos"):  # what the old advice (--out the photos' folder) ran into
        _earlier_run_files(photos, sorted(photos.iterdir()))


def test_cli_errors_are_one_line(tmp_path, model_dir, capsys):
    req = _request(tmp_path / "req", masks=False)
    (req / "view0_mask.png").write_bytes((req / "view0.png").read_bytes())  # a mask for one image only
    assert main(["reconstruct", "--input", str(req), "--model", str(model_dir), "--out", str(tmp_path / "a.safetensors")]) == 2
    assert "missing masks" in capsys.readouterr().err
    assert main(["reconstruct", "--input", str(tmp_path / "nope"), "--out", str(tmp_path / "a.safetensors")]) == 2
    capsys.readouterr()
    # --out a.ply used to write a safetensors file under a .ply name
    assert main(["reconstruct", "--input", str(req), "--model", str(model_dir), "--out", str(tmp_path / "a.ply")]) == 2
    err = capsys.readouterr().err
    assert "--out is the avatar file (.safetensors" in err and "add --ply FILE" in err and not (tmp_path / "a.ply").exists()
    assert main(["reconstruct", "--input", str(req), "--model", str(model_dir), "--out", str(tmp_path / "a.safetensors"), "--ply", str(tmp_path / "a.splat")]) == 2
    assert "--ply must name a .ply file" in capsys.readouterr().err


def test_reconstruct_with_refinement_writes_avatar_and_corrected_cameras(tmp_path, model_dir, capsys):
    req = _request(tmp_path / "req", masks=True)
    info = {"expressions": np.random.default_rng(2).random((3, 53)).round(3).tolist()}
    (req / "info.json").write_text(json.dumps(info))
    out, cams_out = tmp_path / "avatar.safetensors", tmp_path / "cams.json"
    args = ["reconstruct", "--input", str(req), "--model", str(model_dir), "--out", str(out), "--refine-steps", "2", "--cameras-out", str(cams_out)]
    assert main(args) == 2  # without --refine-cameras the cameras are not refined: refused, not written unchanged
    assert "--refine-cameras" in capsys.readouterr().err and not cams_out.exists()
    assert main(args + ["--refine-cameras"]) == 0
    printed = capsys.readouterr().out
    assert "refined in" in printed and "(2 steps, preset 'default')" in printed  # the network's depth: the default preset
    assert len(CanonicalAvatar.load(out)) > 0
    cams = json.loads(cams_out.read_text())
    given = json.loads((req / "cameras.json").read_text())
    assert len(cams) == 3 and (cams[0]["width"], cams[0]["height"]) == (40, 36)
    assert max(np.abs(np.array(c["w2c"]) - np.array(g["w2c"])).max() for c, g in zip(cams, given)) > 1e-5  # corrected
    assert main(["reconstruct", "--input", str(req), "--model", str(model_dir), "--out", str(out), "--refine-steps", "-1"]) != 0


def test_animate_refuses_an_out_file_type_it_does_not_write(tmp_path, model_dir, capsys):
    """``--out clip.gif`` used to make a folder named clip.gif full of PNGs; it is refused at once,
    naming what is written. A folder whose name has another dot still works."""
    req = _request(tmp_path / "req", masks=True)
    out = tmp_path / "avatar.safetensors"
    assert main(["reconstruct", "--input", str(req), "--model", str(model_dir), "--out", str(out)]) == 0
    np.save(tmp_path / "seq.npy", np.zeros((2, 53), np.float32))
    args = ["animate", "--avatar", str(out), "--model", str(model_dir), "--expressions", str(tmp_path / "seq.npy"), "--size", "16"]
    capsys.readouterr()
    assert main(args + ["--out", str(tmp_path / "clip.gif")]) == 2
    err = capsys.readouterr().err
    assert "--out must be a video file (.mp4" in err and "clip.gif" in err and not (tmp_path / "clip.gif").exists()
    assert main(args + ["--out", str(tmp_path / "frames.v2")]) == 0
    assert len(list((tmp_path / "frames.v2").glob("frame_*.png"))) == 2


def test_animate_refuses_a_model_other_than_the_avatars(tmp_path, model_dir, capsys):
    """An avatar's Gaussians carry its model's features, which only that model's deformation MLP
    reads (the server closes such a stream with 4409). ``animate --model`` of another model is
    refused in one line naming both, instead of frames of garbage or an expression-name error."""
    req = _request(tmp_path / "req", masks=True)
    out = tmp_path / "avatar.safetensors"
    assert main(["reconstruct", "--input", str(req), "--model", str(model_dir), "--out", str(out)]) == 0
    other = tmp_path / "other"
    model = FastGHA.from_pretrained(model_dir)
    model.config.name = "toy2"
    model.save_pretrained(other)
    np.save(tmp_path / "seq.npy", np.zeros((2, 53), np.float32))
    capsys.readouterr()
    args = ["animate", "--avatar", str(out), "--expressions", str(tmp_path / "seq.npy"), "--size", "16", "--out", str(tmp_path / "f")]
    assert main(args + ["--model", str(other)]) == 2
    err = [x for x in capsys.readouterr().err.strip().splitlines() if "error" in x]
    assert len(err) == 1 and "is model 'toy2' (ict53)" in err[0] and "reconstructed by model 'toy' (ict53)" in err[0], err
    assert not (tmp_path / "f").exists()
    assert main(args + ["--model", str(model_dir)]) == 0


def test_expression_files_of_every_shipped_json_form_load_in_animate_and_client(tmp_path):
    """The JSON forms FastGHA itself writes are read by both `animate` and `client`: a list,
    {"frames": [...]} (GET /v1/samples/{name}/expressions.json) and `fastgha track`'s
    expressions.json ({"space", "names", "images", "expressions"})."""
    from fastgha_core.cli import CLIError
    from fastgha_core.commands.animate import load_expressions
    from fastgha_core.commands.client import _load_sequence
    from fastgha_core.expressions import get_space

    space = get_space("ict53")
    codes = np.random.default_rng(3).random((2, 53)).round(4).tolist()
    forms = {"list.json": codes, "frames.json": {"frames": codes, "num_frames": 2, "dim": 53},
             "track.json": {"space": "ict53", "names": space.names, "images": ["a.png", "b.png"], "expressions": codes}}  # fmt: skip
    for name, obj in forms.items():
        path = tmp_path / name
        path.write_text(json.dumps(obj))
        got = load_expressions(path, space)
        assert got.shape == (2, 53) and np.allclose(got.numpy(), codes, atol=1e-6), name
        assert _load_sequence(path, 53, "ict53") == codes, name
    (tmp_path / "other.json").write_text(json.dumps({"weights": codes}))
    with pytest.raises(ValueError, match=r"an object with 'expressions' or 'frames', got an object with keys \['weights'\]"):
        load_expressions(tmp_path / "other.json", space)
    with pytest.raises(CLIError, match="expected a non-empty list"):
        _load_sequence(tmp_path / "other.json", 53, "ict53")


def test_animate_keeps_the_aspect_of_a_non_square_camera():
    """A 64 x 32 camera rendered into the square --size frame used to be stretched (x scaled by 0.5,
    y by 1); it is scaled uniformly and padded: square pixels stay square and the view's centre
    stays the frame's centre."""
    from fastgha_core.cameras import Cameras
    from fastgha_core.commands.animate import frame_cameras

    cam = Cameras.look_at(torch.tensor([0.0, 0.0, 1.0]), torch.zeros(3), torch.tensor([0.0, 1.0, 0.0]), fov_deg=20.0, width=64, height=32)
    spec = json.dumps(cameras_to_json(cam))
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "cams.json"
        path.write_text(spec)
        (out,) = frame_cameras(str(path), 1, 32, 1.0, 20.0)
    K, K0 = out.K.reshape(3, 3), cam.K.reshape(3, 3)
    assert (out.width, out.height) == (32, 32)
    assert float(K[0, 0] / K[1, 1]) == pytest.approx(float(K0[0, 0] / K0[1, 1]))  # aspect kept
    assert float(K[0, 0]) == pytest.approx(float(K0[0, 0]) * 0.5)  # uniform scale 32 / 64
    assert (float(K[0, 2]), float(K[1, 2])) == pytest.approx((16.0, 16.0))  # centred, padded above and below


def test_first_run_says_the_rasterizer_kernels_compile(tmp_path, model_dir, capsys, monkeypatch):
    """A cold numba cache (the first run after installing) makes animate say why it pauses; a filled
    cache (after any render) keeps it silent, and so does a CUDA device."""
    from fastgha_core.commands import note_first_compilation, rasterizer_cache_cold
    from fastgha_core.render import cpu_kernels

    req = _request(tmp_path / "req", masks=True)
    out = tmp_path / "avatar.safetensors"
    assert main(["reconstruct", "--input", str(req), "--model", str(model_dir), "--out", str(out)]) == 0
    np.save(tmp_path / "seq.npy", np.zeros((1, 53), np.float32))
    args = ["animate", "--avatar", str(out), "--model", str(model_dir), "--expressions", str(tmp_path / "seq.npy"),
            "--size", "24", "--out", str(tmp_path / "frames")]
    assert main(args) == 0  # renders: numba has compiled (or loaded) the kernels and keeps them on disk
    capsys.readouterr()
    assert not rasterizer_cache_cold()
    assert main(args) == 0
    assert "numba compiles" not in capsys.readouterr().err
    monkeypatch.setattr(cpu_kernels.raster_forward_fast._cache._cache_file, "_index_path", str(tmp_path / "none.nbi"))
    assert rasterizer_cache_cold()
    assert main(args) == 0
    assert "first run: numba compiles the CPU rasterizer's kernels once" in capsys.readouterr().err
    note_first_compilation("cuda:0")
    assert capsys.readouterr().err == ""
