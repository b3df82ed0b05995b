"""docs/reliability.md names a test for every promise: each file and test it names must exist."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "reliability.md"


def named_tests() -> list[tuple[str, str | None]]:
    """(file, test name or None) for every `tests/...py[::name]` and every `::name` that follows one in a row."""
    out: list[tuple[str, str | None]] = []
    for row in DOC.read_text().splitlines():
        if not row.startswith("|"):
            continue
        current: str | None = None
        for m in re.finditer(r"`(tests/[\w/]+\.py)?(?:::(\w+))?`", row):
            path, name = m.group(1), m.group(2)
            if path:
                current = path
            if current and (path or name):
                out.append((current, name))
    return out


def test_every_test_the_reliability_doc_names_exists() -> None:
    refs = named_tests()
    assert len(refs) >= 40 and len({p for p, _ in refs}) >= 10, refs
    for path, name in refs:
        source = ROOT / path
        assert source.is_file(), path
        if name is not None:
            assert re.search(rf"^\s*(async )?def {name}\(", source.read_text(), re.M), f"{path}::{name}"
