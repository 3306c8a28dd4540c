"""A report's pages as HTML: ``report.html`` (``report.md``'s sections, styled, with its tables as
tables and its figures inline) and ``table.html`` beside each table; standalone pages, with their
own style sheet and no external resources.
"""

from __future__ import annotations

import html
import re
from collections.abc import Sequence

import pandas as pd

from eabc.experiments.tables import to_html, to_markdown

STYLE = """
body { font: 15px/1.5 -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; color: #222;
       max-width: 72rem; margin: 2rem auto; padding: 0 1.5rem; }
h1 { font-size: 1.7rem; border-bottom: 2px solid #333; padding-bottom: .3rem; }
h2 { font-size: 1.25rem; margin-top: 2.2rem; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 1rem 0; font-variant-numeric: tabular-nums; }
th, td { padding: .3rem .7rem; text-align: center; }
thead th { border-top: 2px solid #333; border-bottom: 1px solid #333; }
tbody tr:last-child th, tbody tr:last-child td { border-bottom: 2px solid #333; }
tbody th { text-align: left; font-weight: normal; }
tbody tr:nth-child(even) { background: #f6f6f6; }
td b { color: #0b4f9c; }
.note { color: #555; font-size: .92rem; }
.warning { background: #fff4e0; border-left: 4px solid #e69500; padding: .5rem .8rem; }
figure { margin: 1.2rem 0; } figure img { max-width: 100%; border: 1px solid #eee; }
figcaption { color: #555; font-size: .9rem; }
"""


def html_page(title: str, body: str) -> str:
    """A standalone HTML page (its own style sheet, no external resources) around ``body``."""
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f"<title>{html.escape(title)}</title>\n<style>{STYLE}</style>\n</head>\n<body>\n"
        f"<h1>{html.escape(title)}</h1>\n{body}\n</body>\n</html>\n"
    )


def _markdown_table_html(text: str) -> str:
    """A Markdown table (as this module writes them) as an HTML table."""
    rows = [line.strip().strip("|").split(" | ") for line in text.strip().splitlines()]
    rows = [r for i, r in enumerate(rows) if i != 1]  # the |---| line
    cell = lambda t: re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", html.escape(t.strip()))
    head = "".join(f"<th>{cell(t)}</th>" for t in rows[0])
    body = "".join(
        "<tr>" + f"<th>{cell(r[0])}</th>" + "".join(f"<td>{cell(t)}</td>" for t in r[1:]) + "</tr>"
        for r in rows[1:]
    )
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def report_page(sections: list[str], tables: list[pd.DataFrame], formats: Sequence[str]) -> str:
    """``report.md``'s content as one styled page: tables as tables (score tables, ``tables``,
    in their own renderer), figures as SVG where ``formats`` has it (else PNG), each linking its
    PDF where ``formats`` has that."""
    score_tables = {to_markdown(t).strip(): to_html(t) for t in tables}
    parts = []
    blocks = [b.strip() for section in sections[1:] for b in re.split(r"\n\s*\n", section)]
    for text in filter(None, blocks):  # sections[0] is report.md's title
        if text.startswith("#"):
            level = len(text) - len(text.lstrip("#"))
            parts.append(f"<h{level}>{html.escape(text[level:].strip())}</h{level}>")
        elif text.startswith("!["):
            parts.extend(_figures_html(text, formats))
        elif text.startswith("|"):
            parts.append(score_tables.get(text) or _markdown_table_html(text))
        elif text.startswith("**Warning:**"):
            parts.append(f'<p class="warning">{_inline(text)}</p>')
        else:
            parts.append(f'<p class="note">{_inline(text)}</p>')
    return html_page("Experiment report", "\n".join(parts))


def _figures_html(text: str, formats: Sequence[str]) -> list[str]:
    out = []
    for alt, target in re.findall(r"!\[([^\]]*)\]\(([^)]+)\)", text):
        stem = html.escape(target.removesuffix(".png"))
        image = f"{stem}.svg" if "svg" in formats else html.escape(target)
        pdf = f' (<a href="{stem}.pdf">PDF</a>)' if "pdf" in formats else ""
        out.append(
            f'<figure><a href="{html.escape(target)}"><img src="{image}" '
            f'alt="{html.escape(alt)}"></a><figcaption>{html.escape(alt)}{pdf}</figcaption></figure>'
        )
    return out


def _inline(text: str) -> str:
    """Markdown's bold, code and links in one paragraph, as HTML."""
    text = html.escape(text)
    text = re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", text)
    text = re.sub(r"`([^`]+)`", r"<code>\1</code>", text)
    return re.sub(r"\[([^\]]+)\]\(([^)]+)\)", r'<a href="\2">\1</a>', text)
