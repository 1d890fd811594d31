"""Output paths are checked before a command does its work (``fastgha_core/commands/_paths.py``):
a path under an existing *file* used to end minutes of tracking, refinement or timing in a
``FileExistsError`` traceback; now every writing command refuses it first, as one line, exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fastgha_core.cli import CLIError, main
from fastgha_core.commands._paths import output_dir, output_file

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "fastgha_core" / "assets" / "samples" / "synth_1000000" / "request"


def test_output_file_and_dir_rules(tmp_path):
    f = tmp_path / "a_file"
    f.write_text("x")
    assert output_file(tmp_path / "new" / "deeper" / "x.json", "--json") == tmp_path / "new" / "deeper" / "x.json"
    assert output_dir(tmp_path / "new" / "deeper", "--out") == tmp_path / "new" / "deeper"
    assert not (tmp_path / "new").exists()  # checking creates nothing
    with pytest.raises(CLIError, match=r"--json .*a_file is a file, not a folder"):
        output_file(f / "x.json", "--json")
    with pytest.raises(CLIError, match=r"--out .*a_file is a file, not a folder"):
        output_dir(f, "--out")
    with pytest.raises(CLIError, match=r"--out .*a_file is a file, not a folder"):
        output_dir(f / "sub" / "sub", "--out")
    with pytest.raises(CLIError, match="is a folder; expected a file path"):
        output_file(tmp_path, "--ply")


# one argv per writing command; "F" is replaced by a path under an existing file
COMMANDS = [
    ["reconstruct", "--input", str(SAMPLE), "--out", "F/a.safetensors"],
    ["reconstruct", "--input", str(SAMPLE), "--out", "ok.safetensors", "--ply", "F/a.ply"],
    ["export", "--avatar", "AVATAR", "--ply", "F/a.ply"],
    ["animate", "--avatar", "AVATAR", "--expressions", "E", "--out", "F/x.mp4"],
    ["animate", "--avatar", "AVATAR", "--expressions", "E", "--out", "F"],
    ["track", "--images", "IMG", "--out", "F"],
    ["track", "--images", "IMG", "--out", "req", "--json", "F/r.json"],
    ["demo", "--out", "F"],
    ["synth", "--out", "F", "--subjects", "1", "--timesteps", "2", "--cameras", "2"],
    ["eval", "--subjects", "1", "--out", "F"],
    ["bench", "mlp", "--quick", "--json", "F/b.json"],
    ["train", "--data", "synthetic", "--steps", "1", "--out", "F"],
]


@pytest.mark.parametrize("argv", COMMANDS, ids=[f"{a[0]}-{i}" for i, a in enumerate(COMMANDS)])
def test_every_writing_command_refuses_a_path_under_a_file_before_its_work(argv, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "F").write_text("not a folder")
    (tmp_path / "AVATAR").write_text("")  # exists (export checks that first); never read
    (tmp_path / "E").write_text(json.dumps({"space": "ict53", "expressions": [[0.0] * 53]}))
    (tmp_path / "IMG").write_text("")
    rc = main([a if a != "F" and not a.startswith("F/") else str(tmp_path / a) for a in argv])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "is a file, not a folder" in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["AVATAR", "E", "F", "IMG"]  # nothing written


def test_reconstruct_makes_the_cameras_out_folder(tmp_path, capsys):
    """``--cameras-out`` into a folder that does not exist yet is created like ``--out``'s (it failed
    after the whole refinement)."""
    out = tmp_path / "new" / "cams.json"
    rc = main(["reconstruct", "--input", str(SAMPLE), "--out", str(tmp_path / "a.safetensors"), "--refine-steps", "1",
               "--refine-cameras", "--cameras-out", str(out)])
    assert rc == 0, capsys.readouterr().err
    cams = json.loads(out.read_text())
    assert len(cams) == 4 and {"K", "w2c"} <= set(cams[0])


def test_reconstruct_and_animate_bound_their_sizes(tmp_path, capsys):
    assert main(["reconstruct", "--input", str(SAMPLE), "--out", str(tmp_path / "a.safetensors"), "--refine-steps", "100000"]) == 2
    assert "--refine-steps must be in 0..1000" in capsys.readouterr().err
    assert main(["animate", "--avatar", "x", "--expressions", "e", "--out", str(tmp_path / "x.mp4"), "--size", "100000"]) == 2
    assert "--size must be in 16..4096" in capsys.readouterr().err


def test_ctrl_c_ends_a_command_with_status_130(tmp_path):
    """SIGINT during a long command: "interrupted" and status 130 from the console script's exit
    path (``cli.console_main``: ``os._exit`` after the streams are flushed; interpreter shutdown with
    the thread pools mid-work segfaulted ``fastgha train`` in about half of the interrupts tried)."""
    import signal
    import subprocess
    import sys
    import time

    proc = subprocess.Popen([sys.executable, "-m", "fastgha_core.cli", "bench", "mlp", "--json", str(tmp_path / "b.json")],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            # a test run started in the background (nohup, CI) ignores SIGINT, and a
                            # child inherits that: Python then installs no handler and never sees it
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    line = ""
    while "MLP benchmark" not in line and time.monotonic() < deadline:  # wait until it is working
        line = proc.stdout.readline()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "fastgha bench: interrupted" in err and "Traceback" not in err
    assert not (tmp_path / "b.json").exists()


def test_train_refuses_an_old_runs_folder_before_building_anything(tmp_path, capsys):
    ck = tmp_path / "run" / "checkpoints" / "step_00000003"
    ck.mkdir(parents=True)
    (ck / "trainer_state.pt").write_bytes(b"")
    (ck / "model.safetensors").write_bytes(b"")
    assert main(["train", "--data", "synthetic", "--steps", "1", "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert "already holds a training run (checkpoint step_00000003): add --resume" in err
    assert "perceptual" not in err  # refused before the model and the losses were built
