"""The console script: help, version, and one-line errors with a non-zero exit."""

import subprocess
import sys
from pathlib import Path

import pytest

from fastgha_core import __version__
from fastgha_core.cli import CLIError, main


def test_help_lists_subcommands(capsys):
    assert main([]) == 0
    out = capsys.readouterr().out
    assert "usage: fastgha" in out
    assert "version" in out


def test_version_prints_package_version(capsys):
    assert main(["version"]) == 0
    assert capsys.readouterr().out.strip() == f"fastgha {__version__}"


def test_version_flag_as_most_tools_have_it(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"fastgha {__version__}"


def test_user_error_is_one_line_and_exit_2(capsys, monkeypatch):
    import fastgha_core.commands.version as version_cmd

    def boom(args):
        raise CLIError("no such avatar: x")

    monkeypatch.setattr(version_cmd, "run", boom)
    assert main(["version"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["fastgha version: error: no such avatar: x"]


def test_console_script_runs_in_a_subprocess():
    proc = subprocess.run([sys.executable, "-m", "fastgha_core.cli", "--help"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "COMMAND" in proc.stdout


def test_animate_help_says_the_default_camera_is_an_orbit(capsys):
    with pytest.raises(SystemExit):
        main(["animate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "default 'orbit'" in text


def test_every_option_with_a_default_says_it_in_its_help():
    """A user reads defaults in `--help`: an option whose default is a value (not None / off) names
    it in its help text, as "default ..." or the value itself."""
    import argparse

    from fastgha_core.cli import build_parser

    missing = []
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    for name, parser in sub.choices.items():
        for act in parser._actions:
            if not act.option_strings or isinstance(act, argparse._HelpAction) or act.default in (None, False, argparse.SUPPRESS):
                continue
            text = act.help or ""
            if "default" not in text.lower() and str(act.default) not in text:
                missing.append(f"{name} {act.option_strings[-1]} (default {act.default!r})")
    assert not missing, "options whose help does not give their default: " + ", ".join(missing)


def test_train_config_file_that_is_not_json_is_named(tmp_path, capsys):
    bad = tmp_path / "ft.json"
    bad.write_text('{"preset": "tiny",\n')
    assert main(["train", "--config", str(bad), "--data", "synthetic", "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert f"--config {bad} is not valid JSON" in err and "TrainConfig" in err, err
    assert not (tmp_path / "run").exists()


def test_face_metrics_load_without_a_deprecation_warning_on_every_run():
    """`fastgha eval` loads dlib's face models through face_recognition_models, whose
    pkg_resources import warned on every run."""
    import importlib.util

    if importlib.util.find_spec("face_recognition_models") is None or importlib.util.find_spec("dlib") is None:
        pytest.skip("needs the 'faces' extra (dlib-bin, face-recognition-models)")
    code = "from fastgha_core.train.faces import load_face_metrics; assert load_face_metrics() is not None"
    proc = subprocess.run([sys.executable, "-W", "always", "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "pkg_resources" not in proc.stderr, proc.stderr


def test_version_all_says_whether_photos_without_cameras_can_be_tracked(capsys, monkeypatch):
    """An operator checks the `faces` extra (server-side tracking) and CUDA/gsplat in one place."""
    import fastgha_core.commands.version as version_cmd

    assert main(["version", "--all"]) == 0
    out = capsys.readouterr().out
    assert "torch" in out and "faces extra:" in out and "gsplat:" in out
    monkeypatch.setattr(version_cmd, "_dist_version", lambda name: None)
    assert main(["version", "--all"]) == 0
    assert "faces extra: not installed" in (text := capsys.readouterr().out) and "422 cameras_required" in text
    present = {"dlib-bin": "20.0"}  # dlib without its landmark models is no tracker
    monkeypatch.setattr(version_cmd, "_dist_version", present.get)
    assert main(["version", "--all"]) == 0
    assert "faces extra: not installed" in capsys.readouterr().out


def test_clients_find_the_api_key_where_a_user_put_it(monkeypatch):
    """`fastgha client` / `loadtest`: --api-key, else FASTGHA_API_KEY, else the first key of the
    server's own FASTGHA_API_KEYS (client and server in one shell used to get 401); a 401 says how
    to send a key."""
    from fastgha_core.commands.client import api_key_from, key_hint

    monkeypatch.delenv("FASTGHA_API_KEY", raising=False)
    monkeypatch.delenv("FASTGHA_API_KEYS", raising=False)
    assert api_key_from(None) is None
    monkeypatch.setenv("FASTGHA_API_KEYS", " k1 , k2")
    assert api_key_from(None) == "k1"
    monkeypatch.setenv("FASTGHA_API_KEY", "mine")
    assert api_key_from(None) == "mine" and api_key_from("flag") == "flag"
    refused = "POST /v1/avatars -> HTTP 401 api_key_required: creating avatars needs an API key"
    assert key_hint(refused).endswith("(pass --api-key KEY, or set FASTGHA_API_KEY)")
    assert key_hint("POST /v1/avatars -> HTTP 422 no_face: no face") == "POST /v1/avatars -> HTTP 422 no_face: no face"


def test_device_flags_are_checked_with_a_one_line_answer(capsys, tmp_path):
    """`--device cuda` on a CPU-only torch (or `gpu`, a typo) used to end in a traceback from deep
    inside torch, for `serve` after loading the model."""
    import torch

    from fastgha_core.cli import check_device

    assert check_device("cpu") == "cpu"
    with pytest.raises(CLIError, match=r"--device 'gpu' is not a torch device; expected cpu, cuda or cuda:N"):
        check_device("gpu")
    with pytest.raises(CLIError, match=r"expected cpu, cuda or cuda:N"):
        check_device("meta")
    if torch.cuda.is_available():
        assert check_device("cuda") == "cuda"
        with pytest.raises(CLIError, match=r"only \d+ CUDA device"):
            check_device(f"cuda:{torch.cuda.device_count()}")
    else:
        with pytest.raises(CLIError, match=r"--device 'cuda': .*use cpu"):
            check_device("cuda")
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = str(s.getsockname()[1])
    assert main(["serve", "--port", port, "--data-dir", str(tmp_path / "data"), "--device", "gpu"]) == 2  # before the model loads
    err = capsys.readouterr().err
    assert err.strip() == "fastgha serve: error: --device 'gpu' is not a torch device; expected cpu, cuda or cuda:N", err


@pytest.mark.parametrize(
    "argv, said",
    [
        (["demo", "--frames", "0"], "--frames must be >= 1, got 0"),
        (["demo", "--frames", "-3"], "--frames must be >= 1, got -3"),
        (["animate", "--avatar", "missing.safetensors", "--expressions", "e.json", "--out", "o", "--radius", "-1"], "--radius must be > 0 metres, got -1.0"),
        (["animate", "--avatar", "missing.safetensors", "--expressions", "e.json", "--out", "o", "--fov", "0"], "--fov must be in (0, 180) degrees, got 0.0"),
        (["animate", "--avatar", "missing.safetensors", "--expressions", "e.json", "--out", "o", "--fov", "180"], "--fov must be in (0, 180) degrees, got 180.0"),
        (["eval", "--subjects", "0"], "--subjects must be >= 1, got 0"),
        (["eval", "--views", "0"], "--views must be >= 1, got 0"),
        (["eval", "--num-inputs", "0"], "--num-inputs must be >= 1, got 0"),
        (["eval", "--expressions", "-1"], "--expressions must be >= 1, got -1"),
        (["eval", "--refine-steps", "-5"], "--refine-steps must be >= 0, got -5"),
        (["reconstruct", "--input", "missing", "--out", "o.safetensors", "--refine-steps", "5", "--refine-preset", "nope"], "--refine-preset must be auto or one of"),
        (["track", "--images", "missing.jpg", "--out", "o", "--fov", "0"], "--fov must be in [1, 150] degrees, got 0.0"),
        (["train", "--data", "synthetic", "--out", "run", "--lr", "-1"], "--lr must be > 0 and --lr-deform >= 0"),
        (["train", "--data", "synthetic", "--out", "run", "--workers", "-1"], "--workers must be >= 0, got -1"),
        (["train", "--data", "synthetic", "--out", "run", "--warmup-steps", "-10"], "--warmup-steps must be >= 0, got -10"),
    ],
)
def test_out_of_range_numbers_are_refused_before_any_work(argv, said, capsys, monkeypatch, tmp_path):
    """A number no run can use is a one-line error naming the flag, before a model, avatar or photo is
    read: ``demo --frames 0`` used to animate all frames, ``animate --fov 0`` ended in a
    ZeroDivisionError traceback, ``animate --radius -1`` rendered from behind the head, ``eval
    --subjects 0`` evaluated the default 4, ``track --fov 0`` failed after finding the faces, and
    ``train --lr -1`` trained (uphill)."""
    import fastgha_core.model.fastgha as fastgha
    import fastgha_core.train.builders as builders

    def no_model(*a, **k):
        raise AssertionError("the model was loaded before the arguments were checked")

    monkeypatch.setattr(fastgha, "load_model", no_model)
    monkeypatch.setattr(builders, "build_model", no_model)
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and said in err[0], err


@pytest.mark.parametrize(
    "argv",
    [
        ["reconstruct", "--input", "req", "--out", "a.safetensors", "--model", "paper"],
        ["eval", "--model", "paper", "--subjects", "1"],
        ["demo", "--model", "paper"],
    ],
)
def test_a_preset_without_shipped_weights_is_refused_before_it_is_built(argv, capsys, monkeypatch, tmp_path):
    """``--model paper`` has no shipped weights: reconstruct and eval used to build a random
    419M-parameter network (minutes, gigabytes) and reconstruct noise with a warning; like the demo,
    they refuse it at once, naming the presets that ship."""
    import fastgha_core.model.fastgha as fastgha

    def no_model(*a, **k):
        raise AssertionError("the model must not be built")

    monkeypatch.setattr(fastgha, "load_model", no_model)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "req").mkdir()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--model 'paper': no shipped weights" in err[0] and "shipped: tiny" in err[0], err


@pytest.fixture()
def not_fastgha_http():
    """A plain HTTP server on loopback that answers 404 to everything (a server, but not FastGHA's
    API at the URL given): ``http://127.0.0.1:PORT``."""
    import http.server
    import threading

    class NotFound(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            self.send_error(404)

        def log_message(self, *a):
            pass

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), NotFound)
    t = threading.Thread(target=srv.serve_forever, daemon=True)
    t.start()
    yield f"http://127.0.0.1:{srv.server_address[1]}"
    srv.shutdown()
    srv.server_close()


def _closed_port() -> int:
    import socket

    with socket.socket() as s:  # a port nothing listens on (as while `fastgha serve` is still starting)
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("command", ["client", "loadtest"])
def test_an_unreachable_server_says_what_to_do(command, capsys, tmp_path, not_fastgha_http):
    """`fastgha serve` opens its port only after a start-up of 10-40 s: a client started at once got
    'Connection refused' and nothing more. Also https:// to the plain-HTTP server and a path in --url
    (http://host:port/v1) get the fix in the same line; all exit 2 before creating anything."""
    from pathlib import Path

    sample = Path(__file__).resolve().parents[1] / "fastgha_core" / "assets" / "samples" / "synth_1000000" / "request"
    extra = ["--out", str(tmp_path / "x.mp4")] if command == "client" else ["--clients", "1", "--duration", "1"]

    def run(url: str) -> str:
        assert main([command, "--url", url, "--input", str(sample), *extra]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"fastgha {command}: error: "), err
        return err[0]

    said = run(f"http://127.0.0.1:{_closed_port()}")
    assert "Connection refused" in said and "start one with `fastgha serve`" in said and "start-up done" in said
    said = run(not_fastgha_http.replace("http://", "https://"))
    assert "speaks plain HTTP: use http://" in said
    said = run(not_fastgha_http + "/v1")
    assert "answers, but not as a FastGHA server" in said and "without a path such as /v1" in said


def test_animate_names_the_frame_of_a_bad_expression(tmp_path):
    """`fastgha animate --expressions seq.json` with one bad frame among many said only 'expected a
    vector of 53 values, got shape [2]' (or 'unknown name(s)'), not which frame; `fastgha client`
    already said 'frame N'. Both formats, JSON and .npy, name the file and the frame."""
    import json

    import numpy as np

    from fastgha_core.commands.animate import load_expressions
    from fastgha_core.expressions import get_space

    space = get_space("ict53")
    seq = tmp_path / "seq.json"
    seq.write_text(json.dumps([{"jawOpen": 0.5}, {"jawOpen": 0.2}, [0.1, 0.2]]))
    with pytest.raises(ValueError, match=r"seq\.json'?: frame 2: .*expected a vector of 53 values, got shape \[2\]"):
        load_expressions(seq, space)
    seq.write_text(json.dumps({"frames": [{"jawOpen": 0.5}, {"jawOpne": 0.2}]}))
    with pytest.raises(ValueError, match=r"seq\.json'?: frame 1: .*unknown name\(s\) \['jawOpne'\]"):
        load_expressions(seq, space)
    arr = np.zeros((3, 53), dtype=np.float32)
    arr[1, 4] = np.nan
    np.save(tmp_path / "seq.npy", arr)
    with pytest.raises(ValueError, match=r"seq\.npy'?: frame 1: .*finite"):
        load_expressions(tmp_path / "seq.npy", space)
    seq.write_text(json.dumps([{"jawOpen": 0.5}, [0.0] * 53]))
    codes = load_expressions(seq, space)
    assert codes.shape == (2, 53) and codes[0, space.names.index("jawOpen")] == 0.5


def test_track_takes_a_photos_mask_listed_beside_it_as_its_mask(tmp_path, capsys, monkeypatch):
    """``fastgha track --images folder/*.png`` on a folder of photos with their ``<stem>_mask.png``
    (a tracked folder, say) lists the masks too: each is used as its photo's mask, not tracked as a
    photo (it used to fail with "no face found in ..._mask.png"); a ``*_mask.png`` whose photo is
    not listed is still a photo."""
    import numpy as np
    from PIL import Image

    import fastgha_core.tracking as tracking

    rgb = np.zeros((32, 32, 3), np.uint8)
    rgb[8:24, 8:24] = 200
    mask = np.zeros((32, 32), np.uint8)
    mask[4:28, 4:28] = 255
    Image.fromarray(rgb).save(tmp_path / "00_me.png")
    Image.fromarray(mask).save(tmp_path / "00_me_mask.png")
    Image.fromarray(rgb).save(tmp_path / "01_orphan_mask.png")
    seen = {}

    def fake_track(photos, config, masks=None, names=None, focal_35mm=None):
        seen.update(names=names, masks=masks)
        raise ValueError("stopped by the test")

    monkeypatch.setattr(tracking, "track_photos", fake_track)
    monkeypatch.setattr("fastgha_core.commands.track._same_person", lambda photos, names: None)
    argv = ["track", "--images", *sorted(str(p) for p in tmp_path.glob("*.png")), "--out", str(tmp_path / "out")]
    assert main(argv) == 2
    assert [Path(n).name for n in seen["names"]] == ["00_me.png", "01_orphan_mask.png"]
    assert seen["masks"][0] is not None and seen["masks"][1] is None
    assert np.array_equal(np.asarray(seen["masks"][0]) > 0.5, mask > 127)
    err = capsys.readouterr().err
    assert "not tracked" in err and "00_me_mask.png" in err and "stopped by the test" in err
