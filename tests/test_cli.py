"""The console script: help, version, and one-line errors with a non-zero exit."""

import subprocess
import sys

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
