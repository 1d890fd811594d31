"""The main job: ``fastgha demo`` on the shipped default model and a shipped held-out subject."""

import json
import math

import numpy as np
import pytest
from PIL import Image

from fastgha_core.cli import main
from fastgha_core.model.fastgha import ASSET_MODELS_DIR

SHIPPED = ASSET_MODELS_DIR / "tiny"


def test_shipped_tiny_model_is_packaged():
    assert (SHIPPED / "config.json").is_file() and (SHIPPED / "model.safetensors").is_file()
    cfg = json.loads((SHIPPED / "config.json").read_text())
    assert cfg["name"] == "tiny" and cfg["expression_space"] == "ict53"
    assert (SHIPPED / "model.safetensors").stat().st_size < 30 * 2**20  # the budget for shipped weights


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    assert main(["demo", "--frames", "6", "--out", str(out), "--json", str(out / "figures.json")]) == 0
    return out, json.loads((out / "figures.json").read_text())


def test_demo_writes_video_sheet_and_figures(demo_run):
    out, fig = demo_run
    for key in ("reconstruction_s", "refine_s", "fps", "psnr"):
        assert isinstance(fig[key], float) and math.isfinite(fig[key]), key
    assert fig["reconstruction_s"] > 0 and fig["fps"] > 0 and fig["frames"] == 6
    assert fig["refine_steps"] == 60 and fig["refine_s"] > 0  # refined by default
    assert (out / "demo.mp4").stat().st_size > 1000
    import imageio_ffmpeg

    frames, secs = imageio_ffmpeg.count_frames_and_secs(str(out / "demo.mp4"))
    assert frames == 2 * 6 - 2 and secs >= 6.0, (frames, secs)  # forward and back, long enough to watch
    assert fig["video_seconds"] == pytest.approx(secs, abs=0.2)
    sheet = np.asarray(Image.open(out / "contact_sheet.png"))
    assert sheet.ndim == 3 and sheet.shape[2] == 3 and sheet.std() > 5  # not a blank page


def test_demo_shipped_model_beats_an_untrained_one(demo_run):
    # An untrained tiny model scores about 7 dB here (a grey blob on white); the shipped model must
    # reconstruct the held-out subject far better than that.
    _, fig = demo_run
    assert fig["psnr"] > 15.0, fig


def test_demo_refinement_sharpens_the_orbit_and_can_be_skipped(demo_run, tmp_path):
    """The default refinement against the sample's 4 photos (with their info.json expressions) is
    what raises the orbit's PSNR over the feed-forward avatar's (18.0 -> 19.4 dB over all 48 frames);
    ``--refine-steps 0`` skips it."""
    from fastgha_core.data.samples import load_sample

    assert tuple(load_sample(gt=False).request_expressions.shape) == (4, 53)  # the inputs' own codes
    _, refined = demo_run
    assert main(["demo", "--frames", "6", "--refine-steps", "0", "--out", str(tmp_path), "--json", str(tmp_path / "f.json")]) == 0
    plain = json.loads((tmp_path / "f.json").read_text())
    assert plain["refine_steps"] == 0 and plain["refine_s"] == 0.0
    assert refined["psnr"] > plain["psnr"] + 0.5, (refined["psnr"], plain["psnr"])


def test_demo_rejects_negative_refine_steps(capsys):
    assert main(["demo", "--refine-steps", "-1"]) == 2
    assert "--refine-steps must be >= 0" in capsys.readouterr().err


def test_demo_rejects_unknown_sample(capsys):
    assert main(["demo", "--sample", "nobody"]) == 2
    assert "unknown sample 'nobody'" in capsys.readouterr().err


def test_demo_refuses_a_preset_without_shipped_weights_before_building_it(capsys, monkeypatch):
    """`--model paper` used to build a random 419M-parameter network, then fail on the sample's
    expression space; it is refused at once, naming what ships."""
    import fastgha_core.model.fastgha as fastgha_mod

    def no_build(*a, **k):
        raise AssertionError("the model must not be built")

    monkeypatch.setattr(fastgha_mod, "load_model", no_build)
    assert main(["demo", "--model", "paper"]) == 2
    err = capsys.readouterr().err
    assert "--model 'paper': no shipped weights" in err and "shipped: tiny" in err, err


def test_video_schedule_loops_and_lasts_long_enough():
    from fastgha_core.commands.demo import video_schedule

    order, fps = video_schedule(48)  # the shipped samples' sequence length
    assert order[:48] == list(range(48)) and order[48:] == list(range(46, 0, -1))
    assert len(order) / fps >= 6.0 and fps <= 25
    order, fps = video_schedule(400)
    assert fps == 25 and len(order) / fps > 6.0
    assert video_schedule(1) == ([0], 1 / 6.5)
    with pytest.raises(ValueError, match="at least one frame"):
        video_schedule(0)
