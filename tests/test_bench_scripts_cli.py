"""The bench scripts that share ``bench/_bench_cli.py`` keep their command lines: the same options
with the same defaults as when each built its own parser (``--help`` and the docs' commands quote
them), and ``--json`` writes into a folder that does not exist yet."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from test_docs_commands import _bench_parser

ROOT = Path(__file__).resolve().parents[1]

# script -> {option: default}, as each script's own parser had them before the shared module
EXPECTED = {
    "interior_colors": {"--subjects": 30, "--json": None},
    "lid_colors": {"--subjects": 30, "--json": None},
    "prior_frame_ab": {"--model": "tiny", "--rounds": 40, "--sizes": "256,512", "--json": None, "--rev": None},
    "prior_frame_groups": {"--model": "tiny", "--rounds": 20, "--size": 256, "--mode": "random", "--threads": 0, "--clock": "wall", "--json": None},
    "prior_frame_profile": {"--model": "tiny", "--rounds": 40, "--size": 256, "--threads": 0, "--clock": "wall", "--json": None},
}


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_shared_parser_keeps_each_command_line(name):
    p = _bench_parser(name)  # the script loaded by file path, as the docs test loads it
    got = {a.option_strings[-1]: a.default for a in p._actions if a.option_strings and a.option_strings[-1] != "--help"}
    assert got == EXPECTED[name]
    assert list(got) == list(EXPECTED[name])  # same order in --help
    assert p.description and "\n" not in p.description  # the first line of the script's docstring


def test_write_json_makes_the_folder_and_skips_without_a_path(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "bench"))
    sys.modules.pop("_bench_cli", None)
    from _bench_cli import write_json

    out = tmp_path / "new" / "dir" / "r.json"
    write_json(str(out), {"a": [1, 2]}, indent=1)
    assert json.loads(out.read_text()) == {"a": [1, 2]} and out.read_text().startswith('{\n "a"')
    write_json(None, {"a": 1})  # no --json: nothing written, no error
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["dir", "new", "r.json"]
