"""The house rules a tool keeps (docs/architecture.md, "Rules the tools keep"): file sizes, and no stale sizes in
docstrings. The import rules are import-linter's and the types mypy's, both run by the test command."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hil", "firmware_stub")
MAX_LINES = 800  # past this a file usually holds two jobs
ONE_JOB = "One job:"  # a longer file's module docstring says why it is one job, in a sentence starting so


def source_files() -> list[Path]:
    return sorted(p for package in PACKAGES for p in (ROOT / package).rglob("*.py"))


def too_long(text: str) -> bool:
    """Past :data:`MAX_LINES` lines without a module docstring that says why it is one job."""
    return text.count("\n") > MAX_LINES and ONE_JOB not in (ast.get_docstring(ast.parse(text)) or "")


def test_no_file_is_past_800_lines_unless_its_docstring_says_why_it_is_one_job() -> None:
    named = [f"{p.relative_to(ROOT)}: {p.read_text().count(chr(10))} lines" for p in source_files()
             if too_long(p.read_text())]
    assert not named, ("split these along their own outline, or say in the module docstring why each is one job "
                          f"('{ONE_JOB} ...'): {named}")


def test_the_rule_names_a_long_file_without_its_reason(tmp_path: Path) -> None:
    body = "x = 1\n" * MAX_LINES
    assert too_long(f'"""A module."""\n{body}')
    assert not too_long(f'"""A module."""\n{body[6:]}')  # 800 lines exactly
    assert not too_long(f'"""A module.\n\n{ONE_JOB} the whole state machine of one thing."""\n{body}')
    assert too_long(f'"""A module."""\n# {ONE_JOB} said in a comment, not the docstring\n{body}')


def test_no_docstring_states_its_files_length() -> None:
    """A sentence like "about 820 lines" goes stale with the next change; the file-size rule says it instead."""
    stale = [f"{p.relative_to(ROOT)}: {m.group(0)!r}" for p in source_files()
             for m in [re.search(r"\b(about|some|~)\s*[0-9][0-9,]* lines\b", ast.get_docstring(ast.parse(p.read_text()))
                                 or "")] if m]
    assert not stale, stale
