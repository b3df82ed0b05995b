"""A report document as Markdown (report.md: tables, figures as relative links) and as one self-contained HTML
page (report.html: the same blocks, figures inlined as base64 PNG, a small stylesheet, no script, no CDN)."""

from __future__ import annotations

import base64
import html
import os
from pathlib import Path

from hil.reporting._document import (
    Banner,
    Block,
    Bullets,
    Cell,
    Figure,
    Heading,
    Item,
    Table,
    Text,
)


def _md_cell(c: Cell) -> str:
    text = c.text.replace("|", "\\|")
    return f"**{text}**" if c.best or c.status == "fail" else text


def _md_table(t: Table) -> str:
    lines = ["| " + " | ".join(h.replace("|", "\\|") for h in t.header) + " |",
             "|" + "|".join("---:" if t.right(i) else "---" for i in range(len(t.header))) + "|"]
    lines += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in t.rows]
    return "\n".join(lines)


def _md_item(i: Item) -> str:
    head = f"- **{i.status.upper()}** {i.text}" if i.status else f"- {i.text}"
    return "\n".join([head, *(f"  - {s}" for s in i.sub)])


def render_markdown(doc: list[Block], out_dir: Path) -> str:
    parts = []
    for b in doc:
        match b:
            case Heading():
                parts.append(f"{'#' * b.level} {b.text}")
            case Banner():
                parts.append(f"> **Verdict: {b.headline}.** {b.text}")
            case Text():
                parts.append(b.text)
            case Bullets():
                parts.append("\n".join(_md_item(i) for i in b.items))
            case Table():
                parts.append(_md_table(b))
            case Figure():
                parts.append(f"![{b.caption}]({Path(os.path.relpath(b.path, out_dir)).as_posix()})\n\n*{b.caption}*")
    return "\n\n".join(parts) + "\n"


CSS = """
body { font-family: system-ui, sans-serif; max-width: 1200px; margin: 2em auto; padding: 0 1em; color: #222; }
table { border-collapse: collapse; margin: 1em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.3em 0.6em; text-align: right; vertical-align: top; }
th { background: #f2f2f2; }
th.l, td.l { text-align: left; }
td.best { font-weight: bold; background: #dff3e4; }
.pass { color: #0a7d28; font-weight: bold; }
.fail { color: #b00020; font-weight: bold; }
.banner { padding: 0.8em 1.2em; border-radius: 6px; margin: 1em 0; }
.banner .headline { font-size: 1.6em; font-weight: bold; }
.banner.pass { background: #dff3e4; border: 2px solid #0a7d28; }
.banner.fail { background: #fde7ea; border: 2px solid #b00020; }
figure { margin: 1em 0; } figure img { max-width: 100%; } figcaption { color: #555; font-size: 0.9em; }
"""


def _esc(text: str) -> str:
    return html.escape(text).replace("+-", "±")


def _html_cell(c: Cell, right: bool) -> str:
    cls = " ".join(x for x in ("best" if c.best else "", c.status or "", "" if right else "l") if x)
    return f'<td class="{cls}">{_esc(c.text)}</td>' if cls else f"<td>{_esc(c.text)}</td>"


def _html_table(t: Table) -> str:
    head = "".join(("<th>" if t.right(i) else '<th class="l">') + f"{_esc(h)}</th>" for i, h in enumerate(t.header))
    rows = "".join("<tr>" + "".join(_html_cell(c, t.right(i)) for i, c in enumerate(row)) + "</tr>\n"
                   for row in t.rows)
    return f"<table>\n<thead><tr>{head}</tr></thead>\n<tbody>\n{rows}</tbody>\n</table>"


def _html_item(i: Item) -> str:
    status = f'<span class="{i.status}">{i.status.upper()}</span> ' if i.status else ""
    sub = "<ul>" + "".join(f"<li>{_esc(s)}</li>" for s in i.sub) + "</ul>" if i.sub else ""
    return f"<li>{status}{_esc(i.text)}{sub}</li>"


def _html_figure(f: Figure) -> str:
    data = base64.b64encode(f.path.read_bytes()).decode("ascii")
    return (f'<figure><img alt="{_esc(f.caption)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{_esc(f.caption)}</figcaption></figure>")


def _html_block(b: Block) -> str:
    match b:
        case Heading():
            return f"<h{b.level}>{_esc(b.text)}</h{b.level}>"
        case Banner():
            cls = "pass" if b.passed else "fail"
            return f'<div class="banner {cls}"><div class="headline">{_esc(b.headline)}</div>{_esc(b.text)}</div>'
        case Text():
            return f"<p>{_esc(b.text)}</p>"
        case Bullets():
            return "<ul>" + "".join(_html_item(i) for i in b.items) + "</ul>"
        case Table():
            return _html_table(b)
        case Figure():
            return _html_figure(b)
    raise TypeError(f"not a report block: {b!r}")


def render_html(doc: list[Block]) -> str:
    title = next((b.text for b in doc if isinstance(b, Heading)), "Campaign report")
    body = "\n".join(_html_block(b) for b in doc)
    return (f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n<title>{_esc(title)}</title>\n'
            f"<style>{CSS}</style>\n</head>\n<body>\n{body}\n</body>\n</html>\n")
