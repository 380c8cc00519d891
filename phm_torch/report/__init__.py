"""Self-contained HTML reports (figures embedded, readable offline)."""

from .html import HtmlReport

__all__ = ["HtmlReport"]
