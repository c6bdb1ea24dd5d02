"""personalize.presentation.html_report: self-contained HTML with escaped text, tables and embedded PNG figures."""
from __future__ import annotations

import base64
import struct
from html.parser import HTMLParser

import numpy as np
import pytest

from lowerlimb.errors import InputError
from personalize.presentation.html_report import (Figure, Section, Table, find_chromium, headless_screenshot, new_figure, png_bytes,
                                render_report)



class _Collect(HTMLParser):
    def __init__(self):
        super().__init__()
        self.tags: list[tuple[str, dict]] = []
        self.cells: list[str] = []
        self._in_cell = False
        self.text: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))
        self._in_cell = tag in ("td", "th")

    def handle_endtag(self, tag):
        if tag in ("td", "th"):
            self._in_cell = False

    def handle_data(self, data):
        self.text.append(data)
        if self._in_cell:
            self.cells.append(data)


def _png_size(data: bytes) -> tuple[int, int]:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", data[16:24])


def _red_square_figure():
    fig = new_figure(4, 3)
    ax = fig.add_axes([0, 0, 1, 1])
    ax.add_patch(__import__("matplotlib.patches", fromlist=["Rectangle"]).Rectangle((0, 0), 1, 1, color=(1, 0, 0)))
    ax.set_axis_off()
    return fig


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    d = tmp_path_factory.mktemp("report")
    png = d / "curve.png"
    fig = new_figure(3, 2)
    ax = fig.add_subplot()
    ax.plot(np.linspace(0, 1, 20), np.linspace(0, 1, 20) ** 2)
    fig.savefig(png, dpi=50)
    sections = [
        Section("Joint centres <estimates>", [
            "Right hip centre from each source & fused, mm.",
            Table(["source", "hip error (mm)", "n"], [["mri", 1.23456, 3], ["<script>alert(1)</script>", float("nan"), None]],
                  caption="Errors"),
            [{"joint": "knee", "deg": 2.5}, {"joint": "ankle", "deg": 4.0, "extra": "x"}],
        ]),
        Section("Figures", [Figure(_red_square_figure(), caption="red square", dpi=50), png,
                            Section("Nested", ["sub-section text"])]),
    ]
    path = render_report(d / "report.html", "Subject <S01>", sections, meta="phantom seed 3")
    return path, png


def test_report_structure_escaping_and_embedded_images(report):
    path, png = report
    text = path.read_text(encoding="utf-8")
    p = _Collect()
    p.feed(text)
    tags = [t for t, _ in p.tags]
    assert tags.count("table") == 2
    assert tags.count("img") == 2
    assert "script" not in tags                      # the cell's markup was escaped, not parsed
    assert "<script>alert(1)</script>" in p.cells  # ...and shows as text
    assert "1.235" in p.cells and "-" in p.cells   # float format .4g; NaN and None shown as "-"
    assert ["joint", "deg", "extra"] == p.cells[9:12]  # list-of-dicts table: first-seen key order
    assert "Subject <S01>" in "".join(p.text)
    # self-contained: every resource is inline data, no link or external URL
    for tag, attrs in p.tags:
        for k, v in attrs.items():
            if k in ("src", "href"):
                assert v.startswith("data:image/png;base64,"), (tag, k, v[:40])
    imgs = [a["src"].split(",", 1)[1] for t, a in p.tags if t == "img"]
    first, second = (base64.b64decode(s) for s in imgs)
    w, h = _png_size(first)
    assert 150 <= w <= 210 and 110 <= h <= 160          # 4 x 3 in at 50 dpi (tight bbox)
    assert second == png.read_bytes()                   # a PNG file is embedded byte for byte
    assert "h3" in tags                                 # nested section -> sub-heading


def test_bad_figures_are_refused(tmp_path):
    (tmp_path / "not.png").write_text("hello")
    with pytest.raises(InputError, match="not a PNG"):
        png_bytes(tmp_path / "not.png")
    with pytest.raises(InputError, match="not found"):
        png_bytes(tmp_path / "missing.png")
    with pytest.raises(ValueError, match="2 cells for 3 columns"):
        render_report(tmp_path / "r.html", "t", [Section("s", [Table(["a", "b", "c"], [[1, 2]])])])
    assert not (tmp_path / "r.html").exists()          # no partial output


@pytest.mark.skipif(find_chromium() is None, reason="chromium is not installed")
def test_report_renders_in_headless_chromium(report, tmp_path):
    """The page renders offline and its embedded figure is painted (red pixels in the screenshot)."""
    from matplotlib.image import imread

    path, _ = report
    shot = headless_screenshot(path, tmp_path / "shot.png", width=1000, height=1400)
    img = imread(shot)[..., :3]
    red = (img[..., 0] > 0.9) & (img[..., 1] < 0.15) & (img[..., 2] < 0.15)
    # the 200 x 150 px red figure is on the page (allow scaling): thousands of pure red pixels
    assert red.sum() > 5000
    # and the page is not just the figure: dark text pixels (headings, tables) are present
    assert ((img.sum(axis=-1) < 0.6).sum()) > 2000
