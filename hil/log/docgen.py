"""Generate the tables of docs/log-format.md from ``hil.log.schema``.

The document keeps hand-written prose around blocks fenced by
``<!-- BEGIN GENERATED: name -->`` / ``<!-- END GENERATED: name -->``; a test fails when the
committed document differs from the rendering. Regenerate with

    .venv/bin/python -m hil.log.docgen --write
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import numpy as np

from hil.log.schema import ATTRS, SCHEMA, AttrSpec, Group
from hil.log.writer import chunk_rows

DOC_PATH = Path(__file__).resolve().parents[2] / "docs" / "log-format.md"

_MATLAB = {"f8": "double", "f4": "single", "i8": "int64", "i4": "int32", "u4": "uint32", "u1": "uint8"}
_NUMPY = {"f8": "float64", "f4": "float32", "i8": "int64", "i4": "int32", "u4": "uint32", "u1": "uint8"}


def _types(dtype: str) -> tuple[str, str]:
    dt = np.dtype(dtype)
    if dt.kind == "S":
        return f"`S{dt.itemsize}` (ASCII, NUL-padded)", f"char ({dt.itemsize} x N)"
    code = dt.str[1:]  # '<f8' -> 'f8'
    return f"`{_NUMPY[code]}`", _MATLAB[code]


def render_groups(schema: tuple[Group, ...] = SCHEMA) -> str:
    lines = ["| group | rate | channels | chunk (rows) | contents |", "|---|---|---:|---:|---|"]
    for g in schema:
        lines.append(f"| `/{g.name}` | {g.rate} | {len(g.channels)} | {chunk_rows(g)} | {g.doc} |")
    return "\n".join(lines)


def render_channels(schema: tuple[Group, ...] = SCHEMA) -> str:
    out: list[str] = []
    for g in schema:
        out += [
            f"### `/{g.name}` ({g.rate})",
            "",
            g.doc,
            "",
            "| # | channel (dataset) | dtype | MATLAB class | unit | description |",
            "|---:|---|---|---|---|---|",
        ]
        for i, c in enumerate(g.channels, 1):
            np_type, ml_type = _types(c.dtype)
            out.append(f"| {i} | `{c.name}` | {np_type} | {ml_type} | `{c.unit}` | {c.doc} |")
        out.append("")
    return "\n".join(out).rstrip("\n")


def render_attrs(attrs: tuple[AttrSpec, ...] = ATTRS) -> str:
    lines = ["| attribute | stored as | written by | meaning |", "|---|---|---|---|"]
    for a in attrs:
        lines.append(f"| `{a.name}` | {a.type} | {a.source} | {a.doc} |")
    return "\n".join(lines)


def render_blocks() -> dict[str, str]:
    return {"groups": render_groups(), "channels": render_channels(), "attrs": render_attrs()}


_BLOCK = re.compile(r"(<!-- BEGIN GENERATED: (\w+) -->\n)(.*?)(<!-- END GENERATED: \2 -->)", re.S)


def apply(doc: str, blocks: dict[str, str] | None = None) -> str:
    """Return ``doc`` with every generated block replaced by its current rendering."""
    blocks = render_blocks() if blocks is None else blocks
    missing = set(blocks) - {found[1] for found in _BLOCK.findall(doc)}
    if missing:
        raise ValueError(f"docs/log-format.md lacks the generated block(s): {', '.join(sorted(missing))}")
    return _BLOCK.sub(lambda mo: mo.group(1) + blocks[mo.group(2)] + "\n" + mo.group(4), doc)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true", help="rewrite the generated blocks")
    ap.add_argument("--path", type=Path, default=DOC_PATH)
    args = ap.parse_args(argv)
    old = args.path.read_text()
    new = apply(old)
    if new == old:
        print(f"{args.path}: up to date with hil.log.schema")
        return 0
    if args.write:
        args.path.write_text(new)
        print(f"{args.path}: regenerated")
        return 0
    print(f"{args.path} differs from hil.log.schema; run `python -m hil.log.docgen --write`", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
