"""The one HTML report builder of phm_torch: sections, banners, notes, tables and PNG figures embedded as
base64, written as one self-contained page that reads offline. ``phm-run``'s report
(:mod:`phm_torch.report.paper`) and the workbench page (:mod:`phm_torch.report.workbench`) are both built
with it.

Tables take Python values and format them here (floats to 4 significant digits, ``None`` as an en dash,
booleans as yes/no, a mapping as ``key value`` pairs): a caller never pastes a JSON dump into a page.
"""

from __future__ import annotations

import base64
import html
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ..io.atomic import atomic_open

_STYLE = """body{font-family:sans-serif;max-width:1200px;margin:auto;padding:1em;color:#222}
table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #bbb;padding:3px 8px;text-align:right;
font-size:92%}th{background:#eee}td:first-child,th:first-child{text-align:left}
img{max-width:100%;border:1px solid #ddd}.ok{color:#070}.bad{color:#b00}
h2{border-bottom:1px solid #ccc;margin-top:1.6em}.banner{background:#fff6d5;border:1px solid #e0c060;
padding:0.6em 1em;margin:1em 0}.note{color:#555;font-size:90%}"""

MISSING = "–"


def esc(value: Any) -> str:
    """``value`` as text safe to put inside HTML."""
    return html.escape(str(value))


def fmt(value: Any, digits: int = 4) -> str:
    """One table cell as text: floats to ``digits`` significant digits (a non-finite one as ``inf``/``nan``),
    ``None`` as an en dash, booleans as yes/no, a mapping as ``key value; ...`` and a sequence comma-joined."""
    if value is None:
        return MISSING
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.{digits}g}" if math.isfinite(value) else str(value)
    if isinstance(value, Mapping):
        return "; ".join(f"{k} {fmt(v, digits)}" for k, v in value.items())
    if isinstance(value, (list, tuple)):
        return ", ".join(fmt(v, digits) for v in value)
    return str(value)


class HtmlReport:
    """Accumulate sections, then :meth:`render` (a string) or :meth:`write` one self-contained file.

    Text given to :meth:`paragraph`, :meth:`note`, :meth:`banner`, :meth:`section` and table cells is escaped;
    :meth:`markup` takes a fragment the caller built itself (every value inside it passed through
    :func:`esc`)."""

    def __init__(self, title: str, heading: str | None = None):
        self.title = title
        self.heading = title if heading is None else heading
        self.parts: list[str] = []

    def section(self, title: str, text: str = "", level: int = 2) -> None:
        if level not in (2, 3):
            raise ValueError(f"level must be 2 or 3, got {level!r}")
        self.parts.append(f"<h{level}>{esc(title)}</h{level}>")
        if text:
            self.paragraph(text)

    def paragraph(self, text: str) -> None:
        self.parts.append(f"<p>{esc(text)}</p>")

    def note(self, text: str) -> None:
        """A small grey paragraph: what a table leaves out and why, units, definitions."""
        self.parts.append(f'<p class="note">{esc(text)}</p>')

    def banner(self, lines: Sequence[str], links: Sequence[tuple[str, str]] = ()) -> None:
        """A highlighted box, one paragraph per line (the run's scale, where the other figures are), then the
        ``links`` (text, URL) on a line of their own."""
        body = "".join(f"<p>{esc(x)}</p>" for x in lines)
        if links:
            body += "<p>Open: " + ", ".join(f'<a href="{esc(url)}">{esc(text)}</a>' for text, url in links) + "</p>"
        self.parts.append(f'<div class="banner">{body}</div>')

    def markup(self, fragment: str) -> None:
        """A fragment of HTML built by the caller (values inside it escaped with :func:`esc`)."""
        self.parts.append(fragment)

    def table(self, header: Sequence[Any], rows: Sequence[Sequence[Any]], digits: int = 4) -> None:
        """One table; each cell formatted by :func:`fmt`. Every row must have the header's length."""
        for i, row in enumerate(rows):
            if len(row) != len(header):
                raise ValueError(f"rows[{i}] has {len(row)} cells, the header {len(header)}")
        self.parts.append(table_html(header, rows, digits))

    def figure(self, source: str | os.PathLike | bytes | None, caption: str = "", alt: str | None = None) -> None:
        """A PNG figure from a file path or from its bytes (a missing file is said, not skipped silently); no
        caption line when ``caption`` is empty (``alt`` defaults to the caption)."""
        if isinstance(source, bytes):
            data = source
        elif source is None or not Path(source).is_file():
            self.parts.append(f'<p class="note">(figure not available: {esc(source)})</p>')
            return
        else:
            data = Path(source).read_bytes()
        b64 = base64.b64encode(data).decode()
        below = f"<figcaption>{esc(caption)}</figcaption>" if caption else ""
        self.parts.append(
            f'<figure><img src="data:image/png;base64,{b64}" alt="{esc(caption if alt is None else alt)}">'
            f"{below}</figure>"
        )

    def render(self) -> str:
        return (
            f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{esc(self.title)}</title>"
            f"<style>{_STYLE}</style></head><body><h1>{esc(self.heading)}</h1>{''.join(self.parts)}"
            "</body></html>\n"
        )

    def write(self, path: str | os.PathLike) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_open(path, "w", encoding="utf-8") as fh:
            fh.write(self.render())
        return path


def table_html(header: Sequence[Any], rows: Sequence[Sequence[Any]], digits: int = 4) -> str:
    """The ``<table>`` of :meth:`HtmlReport.table`, for a caller composing a fragment."""
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{esc(fmt(c, digits))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"
