"""The library names its own parameters; the command line shows them as its options (hil.cli._common.as_flags), and
no other module spells out a `hil` option (docs/architecture.md, "Faces")."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from hil import api
from hil.cli._common import as_flags, option_names

REPO = Path(__file__).resolve().parents[2]
FLAG = re.compile(r"--[a-z][a-z0-9-]+")
# a module with a command line of its own (``python -m hil.log.docgen --write``): its flags are not `hil`'s
OWN_COMMAND_LINE = {"hil/log/docgen.py"}


@pytest.mark.parametrize(("message", "shown"), [
    ("jobs=0: need at least 1", "--jobs 0: need at least 1"),
    ("study='tiny': already in sqlite:///t.db; pass resume=True to continue it",
     "--study tiny: already in sqlite:///t.db; pass --resume to continue it"),
    ("clock='sim': runs the emulated lab in this process; needs loopback=True",
     "--clock sim: runs the emulated lab in this process; needs --loopback"),
    ("scheduler='tcp://10.0.0.1:8786': cannot connect", "--scheduler tcp://10.0.0.1:8786: cannot connect"),
    ("f_start_hz=nan: not a finite number", "--f-start-hz nan: not a finite number"),
    ("settle_s=-1: not a finite number of seconds >= 0", "--settle -1: not a finite number of seconds >= 0"),
    ("params='kp=1..5': not name=low..high", "--params kp=1..5: not name=low..high"),
    ("empty; cannot tell which kind of config it is (pass kind=)", "empty; cannot tell which kind of config it is "
     "(pass --kind)"),
    # not options: a config field, a plant parameter, a value inside a path
    ("safety.watchdog_ms=5: too short", "safety.watchdog_ms=5: too short"),
    ("k_m_el=0.3: outside the plausible range", "k_m_el=0.3: outside the plausible range"),
    ("/data/run-seed=3/log.h5: no such file", "/data/run-seed=3/log.h5: no such file"),
])
def test_a_library_error_is_shown_in_the_command_s_words(message: str, shown: str) -> None:
    assert as_flags(message) == shown


def argv_strings(tree: ast.AST) -> set[int]:
    """ids of the string constants that are a command line's words: items of a list or tuple, or a call's whole
    argument (``cmd.append("--loopback")``, ``add_argument("--write")``)."""
    out: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.List | ast.Tuple):
            out.update(id(e) for e in node.elts if isinstance(e, ast.Constant))
        elif isinstance(node, ast.Call):
            out.update(id(a) for a in node.args if isinstance(a, ast.Constant))
    return out


def test_no_module_below_the_command_line_spells_out_its_options() -> None:
    options = option_names() - {"--help"}
    found = []
    for path in sorted((REPO / "hil").rglob("*.py")):
        rel = path.relative_to(REPO).as_posix()
        if rel.startswith("hil/cli/") or rel in OWN_COMMAND_LINE:
            continue
        tree = ast.parse(path.read_text(), rel)
        argv = argv_strings(tree)
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in argv:
                found += [f"{rel}:{node.lineno}: {flag}" for flag in FLAG.findall(node.value) if flag in options]
    assert len(options) > 40  # the walk over the commands found them
    assert found == []


def test_the_api_names_the_parameter(tmp_path: Path) -> None:
    """`hil ident`'s own test (tests/ident/test_ident_cli.py) shows the same kind of error with its options."""
    session = REPO / "profiles" / "sessions" / "swing-1deg-1hz-eso.yaml"
    with pytest.raises(api.ConfigError, match=r"^axis='up': not el or az$"):
        api.ident(session, axis="up", out=tmp_path)  # type: ignore[arg-type]
    with pytest.raises(api.ConfigError, match=r"^offset_dps=10: the elevation axis would turn 90 deg .*; lower "
                                              r"offset_dps= or sweep_s=, or identify axis='az'$"):
        api.ident(session, offset_dps=10.0, out=tmp_path)
