"""The repository stands alone: no doc, docstring, config or test points outside it.

Design notes, style guides and the maintainers' shared folder are not shipped, so a reference to
``DESIGN.md``, ``STYLE.md``, an absolute ``/work/...`` path or ``../shared`` leaves a reader with
a dead link. The one exception is the optional real-photo folder ``../shared/realsets`` (also
settable with ``FASTGHA_REALSETS``), which scripts read when present and skip cleanly without.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SUFFIXES = {".py", ".md", ".toml", ".cfg", ".txt", ".js", ".html", ".css", ".yml", ".yaml", ".sh", ".json"}
NAMES = {"Makefile", "Dockerfile", "run"}
SKIP_DIRS = {".git", ".venv", "node_modules", "__pycache__", "out", "runs", "data", ".pytest_cache", "build", "dist"}
FORBIDDEN = re.compile(r"DESIGN\.md|DESIGN axes|STYLE\.md|/work/|\.\./shared(?!/realsets)")
# this file names the patterns it forbids
SELF = Path(__file__).resolve()


def _files():
    for path in ROOT.rglob("*"):
        rel = path.relative_to(ROOT)
        if any(part in SKIP_DIRS or part.endswith(".egg-info") for part in rel.parts[:-1]):
            continue
        if path.is_file() and (path.suffix in SUFFIXES or path.name in NAMES) and path.resolve() != SELF:
            if path.stat().st_size < 2_000_000:
                yield path


def test_forbidden_pattern_catches_what_it_should():
    for bad in ("see DESIGN.md", "(metres, DESIGN axes)", "STYLE.md rule 3", "/work/shared/data/x.npz", "../shared/paper"):
        assert FORBIDDEN.search(bad), bad
    for ok in ("docs/conventions.md", "../shared/realsets", "shared test server"):
        assert not FORBIDDEN.search(ok), ok


def test_no_references_to_files_outside_the_repository():
    hits = []
    for path in _files():
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        for i, line in enumerate(text.splitlines(), 1):
            if FORBIDDEN.search(line):
                hits.append(f"{path.relative_to(ROOT)}:{i}: {line.strip()[:120]}")
    assert not hits, "references to files outside the repository:\n" + "\n".join(hits)


def test_docs_links_resolve():
    """Every `docs/<name>.md` named in README and docs exists."""
    missing = []
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for name in re.findall(r"docs/([\w.-]+\.md)", path.read_text(encoding="utf-8")):
            if not (ROOT / "docs" / name).exists():
                missing.append(f"{path.relative_to(ROOT)} -> docs/{name}")
    assert not missing, missing


# `docs/<name>.md`, "Section name" (a heading or a paragraph's bold title of that file); line breaks
# inside the name (comment markers included) read as spaces, a hyphen broken across lines as a hyphen.
CITATION = re.compile(r'docs/([\w.-]+\.md)`?\)?,?\s*(?:section\s*)?"([A-Za-z][^"(){}\[\]=]{2,150})"')


def _flatten(text: str) -> str:
    text = re.sub(r"-\n\s*(?:#|//|\*)?\s*", "-", text)
    return re.sub(r"\s+", " ", re.sub(r"\n\s*(?:#|//|\*)?\s*", " ", text))


def test_citation_pattern_reads_what_it_should():
    found = CITATION.findall(_flatten('see docs/model-card-log.md, "Hair beside\n    # the face") and `docs/tracking.md` "Pitched heads"'))
    assert found == [("model-card-log.md", "Hair beside the face"), ("tracking.md", "Pitched heads")]
    assert CITATION.findall(_flatten('docs/model-card-log.md, "Photo-\n# consistency depth"')) == [("model-card-log.md", "Photo-consistency depth")]
    assert not CITATION.findall('help="docs/model-card.md)", parser.add_argument("--x"')


def test_cited_sections_exist():
    """A section cited by name (`docs/X.md`, "Name") is found in that file: renaming or moving a
    section must move its citations with it (the model card's measurements moved to
    docs/model-card-log.md on 2026-12-06 under their old names)."""
    docs = {}
    stale = []
    for path in _files():
        try:
            text = _flatten(path.read_text(encoding="utf-8"))
        except UnicodeDecodeError:
            continue
        for name, section in CITATION.findall(text):
            doc = ROOT / "docs" / name
            if not doc.exists():
                continue  # test_docs_links_resolve reports missing files
            if name not in docs:
                docs[name] = _flatten(doc.read_text(encoding="utf-8"))
            if section.strip() not in docs[name]:
                stale.append(f'{path.relative_to(ROOT)} -> docs/{name} "{section}"')
    assert not stale, "cited sections not found in the cited file:\n" + "\n".join(stale)
