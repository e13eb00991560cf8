"""Markdown of the report without extra dependencies: pipe tables from DataFrames
(:func:`to_markdown`) and the little Markdown the report writes as HTML (:func:`to_html`)."""

from __future__ import annotations

import html
import re

import numpy as np
import pandas as pd

NO_VALUE = "—"
"""A cell without a value (the summary adds the reason: ``— (reason)``)."""


def format_value(value, digits: int = 3) -> str:
    """A cell as text: integers as is, floats with ``digits`` decimals (two from 10, one from 100,
    ``digits`` significant digits below 0.01); no value
    (None, NaN, empty text) is ``—``, never an empty cell."""
    if value is None:
        return NO_VALUE
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        if np.isnan(value):
            return NO_VALUE
        if np.isinf(value):
            return "inf" if value > 0 else "-inf"
        if value == int(value) and abs(value) < 1e6:
            return f"{value:.1f}" if digits else str(int(value))
        mag = abs(value)
        if mag < 0.01:
            return f"{value:.{max(digits, 1)}g}"
        if mag >= 100:
            return f"{value:.1f}"
        if mag >= 10:
            return f"{value:.2f}"
        return f"{value:.{digits}f}"
    text = str(value).replace("|", "\\|").replace("\n", " ")
    return text if text.strip() else NO_VALUE


def to_markdown(df: pd.DataFrame, digits: int = 3) -> str:
    """A GitHub-style pipe table of ``df`` (index dropped)."""
    header = "| " + " | ".join(str(c) for c in df.columns) + " |"
    rule = "|" + "|".join("---" for _ in df.columns) + "|"
    lines = [header, rule]
    for row in df.itertuples(index=False):
        lines.append("| " + " | ".join(format_value(v, digits) for v in row) + " |")
    return "\n".join(lines) + "\n"


# -- Markdown to HTML -------------------------------------------------------------------------

_LONG_FLOAT = re.compile(r"(?<![\w.])-?\d+\.\d{5,}(?:[eE][+-]?\d+)?(?![\w.])")
_TABLE_RULE = re.compile(r"^\|?\s*:?-{3,}:?\s*(\|\s*:?-{3,}:?\s*)*\|?\s*$")
_LIST_ITEM = re.compile(r"^(\s*)([-*]|\d+\.)\s+(.*)$")


def round_floats(text: str, digits: int = 4) -> str:
    """``text`` with every float of more than four decimals written to ``digits`` significant digits."""
    return _LONG_FLOAT.sub(lambda m: format(float(m.group(0)), f".{digits}g"), text)


def shift_headings(text: str, levels: int) -> str:
    """``text`` with every ATX heading (``# ...``) moved ``levels`` levels down (at most ``######``)."""
    return re.sub(r"^(#{1,6})(?= )", lambda m: "#" * min(6, len(m.group(1)) + levels), text, flags=re.M)


def inline_html(text: str) -> str:
    """One line of Markdown as HTML: ``code``, **bold**, [links](url); everything else escaped."""
    out = []
    for i, part in enumerate(text.split("`")):
        if i % 2 and i < len(text.split("`")) - 1:
            out.append(f"<code>{html.escape(part)}</code>")
            continue
        if i % 2:  # an unmatched backtick
            part = "`" + part
        s = html.escape(part, quote=False)
        s = re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", s)
        s = re.sub(r"\[([^\]]+)\]\(([^)\s]+)\)", r'<a href="\2">\1</a>', s)
        out.append(s)
    return "".join(out)


def _cells(line: str) -> list[str]:
    line = line.strip()
    line = line[1:] if line.startswith("|") else line
    line = line[:-1] if line.endswith("|") and not line.endswith("\\|") else line
    return [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", line)]


def _table_html(lines: list[str]) -> str:
    head = "".join(f"<th>{inline_html(c)}</th>" for c in _cells(lines[0]))
    body = "".join("<tr>" + "".join(f"<td>{inline_html(c)}</td>" for c in _cells(ln)) + "</tr>" for ln in lines[2:])
    return f'<div class="tbl"><table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table></div>'


def to_html(text: str) -> str:
    """The Markdown of the report as HTML: ATX headings, paragraphs, fenced code, ``-``/``1.``
    lists (one level), pipe tables, and inline code, bold and links."""
    lines, out, i = text.strip("\n").split("\n"), [], 0
    while i < len(lines):
        line = lines[i]
        if not line.strip():
            i += 1
        elif line.lstrip().startswith("```"):
            j = i + 1
            while j < len(lines) and not lines[j].lstrip().startswith("```"):
                j += 1
            out.append(f"<pre><code>{html.escape(chr(10).join(lines[i + 1:j]))}</code></pre>")
            i = j + 1
        elif m := re.match(r"^(#{1,6}) +(.*?)#*\s*$", line):
            n = len(m.group(1))
            out.append(f"<h{n}>{inline_html(m.group(2))}</h{n}>")
            i += 1
        elif line.lstrip().startswith("|") and i + 1 < len(lines) and _TABLE_RULE.match(lines[i + 1].strip()):
            j = i + 2
            while j < len(lines) and lines[j].lstrip().startswith("|"):
                j += 1
            out.append(_table_html(lines[i:j]))
            i = j
        elif m := _LIST_ITEM.match(line):
            tag = "ol" if m.group(2)[0].isdigit() else "ul"
            items = []
            while i < len(lines) and lines[i].strip():
                m = _LIST_ITEM.match(lines[i])
                if m:
                    items.append(m.group(3))
                else:  # a continuation line of the item
                    items[-1] += " " + lines[i].strip()
                i += 1
            out.append(f"<{tag}>" + "".join(f"<li>{inline_html(x)}</li>" for x in items) + f"</{tag}>")
        else:
            j = i
            while (j < len(lines) and lines[j].strip() and not lines[j].lstrip().startswith(("```", "#", "|"))
                   and not (j > i and _LIST_ITEM.match(lines[j]))):
                j += 1
            j = max(j, i + 1)
            out.append("<p>" + inline_html(" ".join(ln.strip() for ln in lines[i:j])) + "</p>")
            i = j
    return "\n".join(out)
