"""``bench/mirror_frame.py`` (cost of the mirrored views, ``docs/model-card-log.md``): without the real
photo sets it skips cleanly, but a ``--set`` that is not among the sets present (a typo such as
``phone5``) is an error naming the sets, not a silent "nothing to measure" with exit status 0."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]


def _main():
    spec = importlib.util.spec_from_file_location("bench_mirror_frame", ROOT / "bench" / "mirror_frame.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.main


def test_unknown_set_is_an_error_naming_the_sets(tmp_path, monkeypatch, capsys):
    for name in ("phone-5", "studio-4"):
        (tmp_path / name).mkdir()
        for i in range(2):  # list_sets counts a folder with 2 photos as a set
            Image.fromarray(np.full((8, 8, 3), 128, np.uint8)).save(tmp_path / name / f"{i}.jpg")
    monkeypatch.setenv("FASTGHA_REALSETS", str(tmp_path))
    assert _main()(["--set", "phone5", "--frames", "1", "--rebuilds", "1"]) == 2
    err = capsys.readouterr().err
    assert "'phone5'" in err and "phone-5, studio-4" in err


def test_without_the_real_sets_it_skips_cleanly(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("FASTGHA_REALSETS", str(tmp_path / "absent"))
    assert _main()(["--set", "phone-5"]) == 0
    assert "nothing to measure" in capsys.readouterr().out
