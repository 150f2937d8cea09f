"""HTML reports: one page of headings, text, tables and matplotlib figures as PNG.

A report is assembled from result objects by the caller and written
atomically: the folder appears complete or not at all.

Examples
--------
>>> rep = Report("Defect detection")                     # doctest: +SKIP
>>> rep.heading("Summary"); rep.text("42 defects")       # doctest: +SKIP
>>> fig, ax = new_figure(); ax.plot([1, 2, 3])           # doctest: +SKIP
>>> rep.figure(fig, "counts", "Defect count against time")  # doctest: +SKIP
>>> rep.write("out/report")                              # doctest: +SKIP
"""
from __future__ import annotations

import html
import io
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from forensics._shared.atomic import atomic_directory

_STYLE = """
body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}
h1{border-bottom:2px solid #446}h2{margin-top:2em;color:#335}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#eef}td:first-child,th:first-child{text-align:left}
figure{margin:1em 0}figcaption{color:#555;font-size:.9em}img{max-width:100%}
.note{background:#ffd;padding:.5em;border-left:4px solid #cc8}
"""


def new_figure(width: float = 6.4, height: float = 4.0, ncols: int = 1, nrows: int = 1):
    """A matplotlib figure and axes drawn off-screen (Agg), independent of pyplot state."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    axes = fig.subplots(nrows, ncols)
    return fig, axes


@dataclass
class Report:
    """An HTML page under construction; :meth:`write` puts it on disk."""

    title: str
    _parts: list[str] = field(default_factory=list)
    _images: dict[str, bytes] = field(default_factory=dict)

    def heading(self, text: str) -> None:
        self._parts.append(f"<h2>{html.escape(text)}</h2>")

    def text(self, text: str, note: bool = False) -> None:
        cls = ' class="note"' if note else ""
        self._parts.append(f"<p{cls}>{html.escape(text)}</p>")

    def preformatted(self, text: str) -> None:
        self._parts.append(f"<pre>{html.escape(text)}</pre>")

    def table(self, header: list[str], rows: list[list[Any]], caption: str | None = None) -> None:
        out = ["<table>"]
        if caption:
            out.append(f"<caption>{html.escape(caption)}</caption>")
        out.append("<tr>" + "".join(f"<th>{html.escape(str(h))}</th>" for h in header) + "</tr>")
        for row in rows:
            out.append("<tr>" + "".join(f"<td>{html.escape(_fmt(v))}</td>" for v in row) + "</tr>")
        out.append("</table>")
        self._parts.append("".join(out))

    def figure(self, fig: Any, name: str, caption: str = "") -> None:
        """Add a matplotlib figure, saved as ``name.png``."""
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=100)
        fname = f"{name}.png"
        if fname in self._images:
            raise ValueError(f"figure name {name!r} used twice in one report")
        self._images[fname] = buf.getvalue()
        self._parts.append(
            f'<figure><img src="{fname}" alt="{html.escape(caption or name)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>"
        )

    def extend(self, other: "Report", prefix: str) -> None:
        """Append another report's content (figures renamed with ``prefix``)."""
        body = "\n".join(other._parts)
        for fname, data in other._images.items():
            new = f"{prefix}{fname}"
            body = body.replace(f'src="{fname}"', f'src="{new}"')
            self._images[new] = data
        self._parts.append(body)

    def html(self) -> str:
        body = "\n".join(self._parts)
        return (
            f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(self.title)}</title>"
            f"<style>{_STYLE}</style></head><body><h1>{html.escape(self.title)}</h1>\n{body}\n</body></html>\n"
        )

    def write(self, directory: str | os.PathLike, force: bool = False) -> Path:
        """Write ``index.html`` and the PNGs into ``directory`` atomically; return the page's path."""
        directory = Path(directory)
        with atomic_directory(directory, force=force) as tmp:
            for fname, data in self._images.items():
                (tmp / fname).write_bytes(data)
            (tmp / "index.html").write_text(self.html(), encoding="utf-8")
        return directory / "index.html"


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)) and value and all(isinstance(v, float) for v in value):
        return "[" + ", ".join(f"{v:.4g}" for v in value) + "]"
    return str(value)
