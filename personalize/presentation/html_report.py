"""Self-contained HTML reports: headings, paragraphs, tables and figures in one file.

`render_report` writes a single ``.html`` file that a browser opens without any
network access: figures are embedded as base64 PNG ``<img>`` elements, the style
sheet is inline, there is no JavaScript and no external URL.  Every piece of text
(titles, cells, captions) is HTML-escaped, so names read from user files cannot
inject markup.

A report is a list of `Section` objects; a section's items may be

* ``str`` - a paragraph;
* `Table` or a list of dicts (one dict per row, keys = column names);
* `Figure`, a ``matplotlib.figure.Figure`` or a path to a ``.png`` file;
* a nested `Section` (sub-heading).

>>> from personalize.presentation.html_report import Section, Table, render_report
>>> render_report("out/report.html", "Subject S01",
...               [Section("Joint centres", ["Right hip, mm.", Table(["source", "x"], [["mri", 1.0]])])])
"""
from __future__ import annotations

import base64
import html
import io
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

from lowerlimb.atomic import atomic_path, write_text
from lowerlimb.errors import InputError

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Helvetica,Arial,sans-serif;margin:2em auto;max-width:70em;
     color:#222;line-height:1.45;padding:0 1em}
h1{border-bottom:2px solid #345;padding-bottom:.2em}
h2{border-bottom:1px solid #ccc;margin-top:1.6em}
table{border-collapse:collapse;margin:.8em 0;font-size:.92em}
caption{caption-side:top;text-align:left;font-weight:600;padding:.3em 0}
th,td{border:1px solid #ccc;padding:.25em .6em}
th{background:#eef2f6;text-align:left}
td.num{text-align:right;font-variant-numeric:tabular-nums}
figure{display:inline-flex;flex-direction:column;width:min-content;vertical-align:top;margin:.6em 1.2em .6em 0}
figure img{max-width:calc(100vw - 3em);height:auto;border:1px solid #ddd;display:block}
div.table{overflow-x:auto}
figcaption{font-size:.9em;color:#555}
p.meta{color:#666;font-size:.85em}
""".strip()


@dataclass(frozen=True)
class Table:
    """A table: column names and rows of cells.

    Attributes
    ----------
    columns : sequence of str
        Column headings.
    rows : sequence of sequences
        Cells; numbers are formatted with `floatfmt`, ``None``/NaN shown as ``-``.
    caption : str
        Optional caption shown above the table.
    floatfmt : str
        Format spec for floats (default ``.4g``).
    """

    columns: Sequence[str]
    rows: Sequence[Sequence[Any]]
    caption: str = ""
    floatfmt: str = ".4g"

    @classmethod
    def from_records(cls, records: Sequence[dict], caption: str = "", floatfmt: str = ".4g",
                     columns: Sequence[str] | None = None) -> "Table":
        """Table from a list of dicts; columns in first-seen key order unless given."""
        if columns is None:
            seen: dict[str, None] = {}
            for r in records:
                for k in r:
                    seen.setdefault(str(k), None)
            columns = list(seen)
        rows = [[r.get(c) for c in columns] for r in records]
        return cls(list(columns), rows, caption, floatfmt)


@dataclass(frozen=True)
class Figure:
    """A figure: a matplotlib Figure, PNG bytes or a path to a PNG file.

    Attributes
    ----------
    image : matplotlib.figure.Figure or bytes or path
    caption : str
    alt : str
        Alternative text (defaults to the caption).
    dpi : int
        Resolution used when rendering a matplotlib figure.
    """

    image: Any
    caption: str = ""
    alt: str = ""
    dpi: int = 110


@dataclass(frozen=True)
class Section:
    """A heading and its content (paragraphs, tables, figures, sub-sections)."""

    heading: str
    items: Sequence[Any] = field(default_factory=tuple)


def png_bytes(image: Any, dpi: int = 110) -> bytes:
    """PNG bytes of a matplotlib Figure, of PNG bytes, or of a ``.png`` file.

    Raises
    ------
    InputError
        If a path does not exist or the data is not a PNG image.
    """
    if hasattr(image, "savefig"):
        buf = io.BytesIO()
        image.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
        data = buf.getvalue()
        source = "matplotlib figure"
    elif isinstance(image, (bytes, bytearray)):
        data, source = bytes(image), "figure bytes"
    elif isinstance(image, (str, os.PathLike)):
        p = Path(image)
        if not p.is_file():
            raise InputError(p, "figure file not found")
        data, source = p.read_bytes(), p
    else:
        raise InputError("figure", f"cannot embed an object of type {type(image).__name__} (give a matplotlib Figure or a PNG)")
    if not data.startswith(PNG_SIGNATURE):
        raise InputError(source, "is not a PNG image")
    return data


def _fmt(value: Any, floatfmt: str) -> tuple[str, bool]:
    """Cell text and whether it is numeric (right-aligned)."""
    if value is None:
        return "-", False
    if isinstance(value, bool):
        return str(value), False
    if isinstance(value, int) or (hasattr(value, "dtype") and getattr(value.dtype, "kind", "") in "iu"):
        return str(int(value)), True
    if isinstance(value, float) or (hasattr(value, "dtype") and getattr(value.dtype, "kind", "") == "f"):
        v = float(value)
        if math.isnan(v):
            return "-", True
        return format(v, floatfmt), True
    return str(value), False


def _table_html(t: Table) -> str:
    out = ['<div class="table"><table>']
    if t.caption:
        out.append(f"<caption>{html.escape(t.caption)}</caption>")
    out.append("<thead><tr>" + "".join(f"<th>{html.escape(str(c))}</th>" for c in t.columns) + "</tr></thead>")
    out.append("<tbody>")
    for row in t.rows:
        if len(row) != len(t.columns):
            raise ValueError(f"table row has {len(row)} cells for {len(t.columns)} columns")
        cells = []
        for v in row:
            text, num = _fmt(v, t.floatfmt)
            cells.append(f'<td class="num">{html.escape(text)}</td>' if num else f"<td>{html.escape(text)}</td>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</tbody></table></div>")
    return "\n".join(out)


def _figure_html(f: Figure) -> str:
    data = base64.b64encode(png_bytes(f.image, f.dpi)).decode("ascii")
    alt = html.escape(f.alt or f.caption or "figure", quote=True)
    cap = f"<figcaption>{html.escape(f.caption)}</figcaption>" if f.caption else ""
    return f'<figure><img alt="{alt}" src="data:image/png;base64,{data}">{cap}</figure>'


def _item_html(item: Any, level: int) -> str:
    if isinstance(item, Section):
        return _section_html(item, min(level + 1, 6))
    if isinstance(item, str):
        return f"<p>{html.escape(item)}</p>"
    if isinstance(item, Table):
        return _table_html(item)
    if isinstance(item, Figure):
        return _figure_html(item)
    if isinstance(item, (list, tuple)) and item and all(isinstance(r, dict) for r in item):
        return _table_html(Table.from_records(item))
    if hasattr(item, "savefig") or isinstance(item, (os.PathLike, bytes, bytearray)):
        return _figure_html(Figure(item))
    raise TypeError(f"cannot render a report item of type {type(item).__name__}")


def _section_html(s: Section, level: int = 2) -> str:
    body = "\n".join(_item_html(it, level) for it in s.items)
    return f"<section>\n<h{level}>{html.escape(s.heading)}</h{level}>\n{body}\n</section>"


def render_html(title: str, sections: Iterable[Section | Any], meta: str = "") -> str:
    """The report as one HTML string (UTF-8, no external resources, no scripts).

    Parameters
    ----------
    title : str
        Page title and top heading.
    sections : iterable of Section (or of bare items, rendered under the title)
    meta : str
        Optional small print under the title (tool version, date, input).
    """
    parts = []
    for s in sections:
        parts.append(_section_html(s) if isinstance(s, Section) else _item_html(s, 1))
    t = html.escape(title)
    meta_html = f'<p class="meta">{html.escape(meta)}</p>\n' if meta else ""
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>{t}</title>\n<style>\n{_CSS}\n</style>\n</head>\n<body>\n<h1>{t}</h1>\n{meta_html}"
            + "\n".join(parts) + "\n</body>\n</html>\n")


def render_report(path: str | os.PathLike, title: str, sections: Iterable[Section | Any], meta: str = "") -> Path:
    """Write the report to `path` atomically and return the path (see `render_html`)."""
    return write_text(path, render_html(title, sections, meta))


def new_figure(width: float = 6.4, height: float = 4.0):
    """A matplotlib Figure on the Agg canvas, outside pyplot's global state (no leak, thread-safe)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure as MplFigure

    fig = MplFigure(figsize=(width, height))
    FigureCanvasAgg(fig)
    return fig


def save_png(fig, path: str | os.PathLike, dpi: int = 110) -> Path:
    """Write a matplotlib Figure to `path` as PNG, atomically (no partial file is ever visible); returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    return path


def find_chromium() -> str | None:
    """Path of a Chromium/Chrome executable, or None."""
    import shutil

    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable", "chrome"):
        p = shutil.which(name)
        if p:
            return p
    return None


def headless_screenshot(html_path: str | os.PathLike, png_path: str | os.PathLike, *, width: int = 1100,
                        height: int = 1600, chromium: str | None = None, timeout: float = 120.0) -> Path:
    """Render `html_path` offline in headless Chromium and save a PNG screenshot (a rendering check).

    Chromium runs with a throw-away profile, no sandbox, no GPU and no network
    features (background networking, component updates and sync disabled).

    Raises
    ------
    FileNotFoundError
        If no Chromium executable is found.
    subprocess.CalledProcessError, subprocess.TimeoutExpired
        If Chromium fails.
    """
    import subprocess
    import tempfile

    exe = chromium or find_chromium()
    if exe is None:
        raise FileNotFoundError("no chromium executable found (apt-get install chromium)")
    png_path = Path(png_path)
    with tempfile.TemporaryDirectory(prefix="chromium-profile-") as profile, atomic_path(png_path) as tmp:
        cmd = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
               "--disable-component-update", "--disable-sync", "--no-first-run", "--hide-scrollbars",
               f"--user-data-dir={profile}", f"--window-size={int(width)},{int(height)}", f"--screenshot={tmp}",
               Path(html_path).resolve().as_uri()]
        subprocess.run(cmd, check=True, capture_output=True, timeout=timeout)
        if not tmp.is_file() or tmp.stat().st_size == 0:
            raise RuntimeError(f"chromium wrote no screenshot for {html_path}")
    return png_path
