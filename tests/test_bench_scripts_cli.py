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


@pytest.mark.parametrize("name", sorted(p.stem for p in (ROOT / "bench").glob("*.py") if not p.stem.startswith("_")))
def test_help_describes_the_script_in_whole_sentences(name):
    """``--help`` opens with the docstring's whole first paragraph, not its first line cut mid-sentence
    (``prior_frame_ab.py`` printed "... with and without it," until 2026-12-06)."""
    p = _bench_parser(name)
    if p is None:
        pytest.skip(f"bench/{name}.py has no main() with a parser")
    assert p.description, f"bench/{name}.py --help has no description"
    assert p.description.rstrip().endswith((".", ")")), p.description


def test_write_json_makes_the_folder_and_skips_without_a_path(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "bench"))
    sys.modules.pop("_bench_cli", None)
    from _bench_cli import write_json

    out = tmp_path / "new" / "dir" / "r.json"
    write_json(str(out), {"a": [1, 2]}, indent=1)
    assert json.loads(out.read_text()) == {"a": [1, 2]} and out.read_text().startswith('{\n "a"')
    write_json(None, {"a": 1})  # no --json: nothing written, no error
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["dir", "new", "r.json"]


def avx2_env() -> dict[str, str] | None:
    """``bench/_bench_cli.py``'s ``avx2_env()``, its module loaded by path (the bench folder stays off
    ``sys.path``); also used by ``test_kernel_codegen.py``."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("_bench_cli_isa", ROOT / "bench" / "_bench_cli.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.avx2_env()


@pytest.mark.skipif(avx2_env() is None, reason="needs an x86 CPU with AVX2")
def test_isa_avx2_reruns_the_script_with_avx512_off(tmp_path, monkeypatch):
    """``--isa avx2`` re-runs the script with its arguments in a process whose numba target has every
    AVX-512 feature off and AVX2 on, and torch / MKL / oneDNN told to dispatch AVX2; the re-run
    itself does not re-run again, and its exit status comes back."""
    monkeypatch.syspath_prepend(str(ROOT / "bench"))
    sys.modules.pop("_bench_cli", None)
    import _bench_cli

    script = tmp_path / "probe.py"
    script.write_text(
        "import json, os, sys\n"
        "sys.path.insert(0, %r)\n"
        "from _bench_cli import run_as_isa\n"
        "run_as_isa('avx2', __file__, sys.argv[1:])  # already the re-run: returns\n"
        "keys = ('NUMBA_CPU_NAME', 'NUMBA_CPU_FEATURES', 'ATEN_CPU_CAPABILITY', 'ONEDNN_MAX_CPU_ISA', 'FASTGHA_BENCH_ISA')\n"
        "json.dump({'argv': sys.argv[1:], **{k: os.environ.get(k) for k in keys}}, open(sys.argv[1], 'w'))\n"
        "sys.exit(3)\n" % str(ROOT / "bench")
    )
    out = tmp_path / "env.json"
    with pytest.raises(SystemExit) as done:
        _bench_cli.run_as_isa("avx2", script, [str(out), "--flag"])
    assert done.value.code == 3
    env = json.loads(out.read_text())
    assert env["argv"] == [str(out), "--flag"]
    feats = dict((f[1:], f[0]) for f in env["NUMBA_CPU_FEATURES"].split(","))
    assert feats["avx2"] == "+" and feats["fma"] == "+"
    assert feats.get("avx512f", "-") == "-" and all(v == "-" for k, v in feats.items() if k.startswith("avx512"))
    assert env["NUMBA_CPU_NAME"] == "x86-64-v3" and env["ATEN_CPU_CAPABILITY"] == "avx2" and env["ONEDNN_MAX_CPU_ISA"] == "AVX2"
    assert env["FASTGHA_BENCH_ISA"] == "avx2"
    assert _bench_cli.run_as_isa("host", script, []) is None  # host: nothing re-run
