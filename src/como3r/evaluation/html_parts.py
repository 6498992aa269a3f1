"""Small HTML pieces of ``report.html``: the style sheet, tables, number formats, sections,
embedded figures, sentences in place of what a section lacks and folded ``<details>``
blocks. Every text that goes into the page is escaped here."""

from __future__ import annotations

import base64
import html
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from matplotlib.figure import Figure

from como3r.evaluation.plot import png_bytes

logger = logging.getLogger(__name__)

STYLE = """
body { font-family: -apple-system, "Segoe UI", Roboto, Helvetica, Arial, sans-serif;
       margin: 2em auto; max-width: 62em; padding: 0 1.5em; color: #222; line-height: 1.45; }
h1 { font-weight: 600; margin-bottom: 0.3em; }
h1 .name { color: #555; font-weight: 400; }
h2 { border-bottom: 1px solid #ddd; padding-bottom: 0.2em; margin-top: 2em; }
nav { margin: 1em 0; font-size: 0.95em; }
nav a, a { color: #1f5fa8; text-decoration: none; }
.facts { display: flex; flex-wrap: wrap; gap: 0.4em 1.6em; background: #f5f7fa;
         padding: 0.7em 1em; border-radius: 6px; }
.facts b { color: #555; font-weight: 600; margin-right: 0.3em; }
ul.notes { padding-left: 1.2em; } ul.notes li.warn { color: #a33; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.92em; }
td, th { border: 1px solid #d8d8d8; padding: 0.25em 0.65em; text-align: right; }
th { background: #f0f2f5; font-weight: 600; }
td:first-child, th:first-child { text-align: left; }
tr:nth-child(even) td { background: #fafbfc; }
figure { margin: 1em 0; } figure img { max-width: 100%; height: auto; }
figcaption, .small { color: #555; font-size: 0.9em; }
.missing { color: #666; font-style: italic; }
details { margin: 0.6em 0; } summary { cursor: pointer; font-weight: 600; }
pre { background: #f7f7f7; padding: 0.8em; overflow-x: auto; font-size: 0.85em; }
"""


def fmt(value: Any) -> str:
    """A table cell: ``–`` for missing, 4 significant digits for floats, thousands
    separators for integers, lists joined."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        return f"{value:,.0f}" if abs(value) >= 1e4 else f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(fmt(v) for v in value)
    return str(value)


def fmt_bytes(count: float) -> str:
    """Bytes in B, kB, MB or GB (powers of 1000)."""
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if count >= size:
            return f"{count / size:.3g} {unit}"
    return f"{count:.0f} B"


def table(rows: Sequence[Mapping[str, Any]]) -> str:
    """A table with the keys of the first row as header (cells through :func:`fmt`)."""
    if not rows:
        return "<p class='missing'>none</p>"
    head = "".join(f"<th>{html.escape(str(k))}</th>" for k in rows[0])
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(fmt(row.get(k)))}</td>" for k in rows[0]) + "</tr>"
        for row in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def section(ident: str, heading: str, body: str) -> str:
    """An ``<h2>`` with an anchor and its content."""
    return f"<section id='{ident}'><h2>{html.escape(heading)}</h2>{body}</section>"


def details(summary: str, body: str) -> str:
    """A folded block, closed until clicked."""
    return f"<details><summary>{html.escape(summary)}</summary>{body}</details>"


def image(build: Callable[[], Figure], alt: str, caption: str = "") -> str:
    """A ``<figure>`` with the built figure embedded as a base64 PNG, or a sentence saying
    it could not be drawn (the report never fails a run)."""
    try:
        data = base64.b64encode(png_bytes(build())).decode("ascii")
    except Exception as exc:  # noqa: BLE001 - any plotting failure leaves a sentence
        logger.warning("report: the %s figure could not be drawn", alt, exc_info=True)
        return (
            f"<p class='missing'>The {html.escape(alt)} figure could not be drawn: "
            f"{html.escape(str(exc))}</p>"
        )
    text = f"<figcaption>{caption}</figcaption>" if caption else ""
    return (
        f"<figure><img alt='{html.escape(alt)}' src='data:image/png;base64,{data}'>{text}</figure>"
    )


def missing(sentence: str) -> str:
    """A sentence saying what a section has nothing to show for."""
    return f"<p class='missing'>{html.escape(sentence)}</p>"
