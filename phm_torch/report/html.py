"""A minimal HTML report builder: sections of text, tables and PNG figures embedded as base64."""

from __future__ import annotations

import base64
import html
import os
from pathlib import Path
from typing import Any

from ..io.atomic import atomic_open

_STYLE = """body{font-family:sans-serif;max-width:1200px;margin:auto;padding:1em;color:#222}
table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}
th{background:#eee}td:first-child,th:first-child{text-align:left}img{max-width:100%;border:1px solid #ddd}
.ok{color:#070}.bad{color:#b00}h2{border-bottom:1px solid #ccc;margin-top:1.6em}"""


def fmt(value: Any, digits: int = 4) -> str:
    """Numbers to short strings; other values as text."""
    if isinstance(value, bool) or value is None:
        return str(value)
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return str(value)


class HtmlReport:
    """Accumulate sections, then :meth:`write` one self-contained file."""

    def __init__(self, title: str):
        self.title = title
        self.parts: list[str] = []

    def section(self, title: str, text: str = "") -> None:
        self.parts.append(f"<h2>{html.escape(title)}</h2>")
        if text:
            self.parts.append(f"<p>{html.escape(text)}</p>")

    def paragraph(self, text: str) -> None:
        self.parts.append(f"<p>{html.escape(text)}</p>")

    def table(self, header: list[str], rows: list[list[Any]]) -> None:
        head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
        body = "".join("<tr>" + "".join(f"<td>{html.escape(fmt(c))}</td>" for c in row) + "</tr>" for row in rows)
        self.parts.append(f"<table><tr>{head}</tr>{body}</table>")

    def figure(self, path: str | os.PathLike | None, caption: str = "") -> None:
        if path is None or not Path(path).is_file():
            self.parts.append(f"<p><em>(figure not available: {html.escape(str(path))})</em></p>")
            return
        data = base64.b64encode(Path(path).read_bytes()).decode()
        self.parts.append(f'<figure><img src="data:image/png;base64,{data}" alt="{html.escape(caption)}">'
                          f"<figcaption>{html.escape(caption)}</figcaption></figure>")

    def write(self, path: str | os.PathLike) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        doc = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(self.title)}</title>"
               f"<style>{_STYLE}</style></head><body><h1>{html.escape(self.title)}</h1>{''.join(self.parts)}"
               "</body></html>")
        with atomic_open(path, "w") as fh:
            fh.write(doc)
        return path
