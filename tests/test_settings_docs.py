"""docs/protocol.md's Settings table is the operator's reference: every ``FASTGHA_*`` setting of
``server.settings.Settings`` is in it, with the default the code has (no undocumented setting, no
stale figure), and every variable the table names exists."""

from __future__ import annotations

import re
from pathlib import Path

from server.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
_UNITS = {"KiB": 1024, "MiB": 1024**2, "GiB": 1024**3}


def _table(doc: str = "protocol.md", section: str | None = "## Settings") -> dict[str, str]:
    """``FASTGHA_NAME`` -> the default cell of the tables in ``docs/<doc>`` (under ``section``)."""
    text = (ROOT / "docs" / doc).read_text(encoding="utf-8")
    if section is not None:
        text = text.split(section, 1)[1].split("\n## ", 1)[0]
    out = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 3 or not cells[0].startswith("`FASTGHA_"):
            continue
        names = re.findall(r"`(FASTGHA_\w+)`", cells[0])
        values = [v.strip() for v in cells[1].split(",")] if len(names) > 1 else [cells[1]]
        assert len(values) == len(names), line
        out.update(zip(names, values))
    return out


def _matches(doc: str, value) -> bool:
    doc = doc.strip().strip("`")
    if value is None or value == "":
        return doc in ("empty", "none", "") or "/" in doc  # a path the server falls back to
    if isinstance(value, bool):
        return doc == str(value).lower()
    if isinstance(value, (int, float)):
        m = re.fullmatch(r"([\d.]+)\s*(KiB|MiB|GiB)?", doc)
        return m is not None and float(m.group(1)) * _UNITS.get(m.group(2), 1) == float(value)
    return doc == str(value)


def test_matcher_reads_the_table_forms():
    assert _matches("2 GiB", 2 * 1024**3) and _matches("524288", 512 * 1024) and _matches("1.0", 1.0)
    assert _matches("true", True) and not _matches("false", True)
    assert _matches("`fastgha-data`", Path("fastgha-data")) and _matches("empty", "")
    assert not _matches("8", 16) and not _matches("tiny", "paper")


def test_every_setting_is_documented_with_its_default():
    table = _table()
    fields = {f"FASTGHA_{name.upper()}": f.default for name, f in Settings.model_fields.items()}
    assert not sorted(set(fields) - set(table)), f"settings missing from docs/protocol.md: {sorted(set(fields) - set(table))}"
    assert not sorted(set(table) - set(fields)), f"docs/protocol.md names settings that do not exist: {sorted(set(table) - set(fields))}"
    wrong = [f"{k}: docs say {table[k]!r}, code has {v!r}" for k, v in fields.items() if not _matches(table[k], v)]
    assert not wrong, "\n".join(wrong)


def test_deploy_tables_give_the_code_defaults():
    """docs/deploy.md repeats some limits (connection deadlines and sizes): same figures."""
    table = _table("deploy.md", None)
    fields = {f"FASTGHA_{name.upper()}": f.default for name, f in Settings.model_fields.items()}
    assert len(table) >= 5 and set(table) <= set(fields), sorted(set(table) - set(fields))
    wrong = [f"{k}: deploy.md says {table[k]!r}, code has {fields[k]!r}" for k in table if not _matches(table[k], fields[k])]
    assert not wrong, "\n".join(wrong)
