"""The view-blending benchmark scripts (bench/realset_resolution.py, bench/view_blend_frame.py,
bench/view_blend_synthetic.py, bench/expr_blend_synthetic.py) explain every option in --help and refuse a bad value at once,
before tracking real photos or rendering synthetic subjects for minutes (a misspelt ``--variants
blnd20`` used to fail after the first set was tracked)."""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ("realset_resolution", "view_blend_frame", "view_blend_synthetic", "expr_blend_synthetic")


def _load(name):
    spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / "bench" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


class _Parsed(Exception):
    pass


@pytest.mark.parametrize("name", SCRIPTS)
def test_every_option_has_help(name, monkeypatch):
    seen = {}

    def grab(self, *a, **k):
        seen["parser"] = self
        raise _Parsed

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", grab)
    with pytest.raises(_Parsed):
        _load(name).main([])
    bare = [a.option_strings[0] for a in seen["parser"]._actions if a.option_strings and not a.help]
    assert not bare, f"bench/{name}.py options without help: {bare}"


@pytest.mark.parametrize(
    "name, argv, said",
    [
        ("realset_resolution", ["--variants", "shipped,blnd20"], "blnd20"),
        ("realset_resolution", ["--variants", "blendx"], "blendx"),
        ("view_blend_frame", ["--frames", "0", "--views", "1"], "--frames >= 1"),
        ("view_blend_frame", ["--views", "9"], "1..8"),
        ("view_blend_synthetic", ["--taus", "0,twenty", "--subjects", "1", "--resolution", "32"], "--taus"),
        ("view_blend_frame", ["--expr-mm", "0"], "--expr-mm > 0"),
        ("expr_blend_synthetic", ["--sigmas", "0,eight"], "--sigmas"),
        ("expr_blend_synthetic", ["--sigmas", "-1"], "--sigmas >= 0"),
    ],
)
def test_a_bad_value_is_refused_before_any_work(name, argv, said, capsys, monkeypatch, tmp_path):
    monkeypatch.setenv("FASTGHA_REALSETS", str(tmp_path))  # no sets: without the check the script would skip and exit 0
    with pytest.raises(SystemExit) as e:
        _load(name).main(argv)
    assert e.value.code == 2 and said in capsys.readouterr().err


def test_the_variants_the_docs_quote_are_accepted():
    mod = _load("realset_resolution")
    for n in ("shipped", "g128_photo", "g256_photo", "g256face_photo", "view20", "blend10", "blend20", "blend30", "blend0"):
        assert mod._valid_variant(n), n
    for n in ("blend", "view-5", "blnd20", "Shipped", ""):
        assert not mod._valid_variant(n), n
