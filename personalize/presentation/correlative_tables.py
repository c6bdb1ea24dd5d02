"""Correlative-law tables and the deviation figure, in the form of Pronost et al. (2010).

`coefficient_table` (their Table 1), `deviation_table` (Table 2) and
`fit_table` (fit statistics per law and dependent) and
`plot_deviation` (Figure 3: deviation between data and law coloured over the
independent coordinates) for `personalize correlate` and the paper
benchmarks; `TextTable` renders CSV and Markdown.
"""
from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from kinematics.mechanisms.correlative import CorrelativeLaw
from lowerlimb.errors import InputError

__all__ = ["TextTable", "coefficient_table", "deviation_table", "fit_table", "format_number", "plot_deviation"]


@dataclass(frozen=True)
class TextTable:
    """A small table with CSV and Markdown renderings."""

    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    title: str = ""

    def to_csv(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(self.header)
        w.writerows(self.rows)
        return buf.getvalue()

    def to_markdown(self) -> str:
        widths = [max(len(str(r[i])) for r in (self.header,) + self.rows) for i in range(len(self.header))]
        line = lambda r: "| " + " | ".join(str(c).ljust(w) for c, w in zip(r, widths)) + " |"  # noqa: E731
        out = [f"{self.title}\n" if self.title else ""]
        out.append(line(self.header))
        out.append("| " + " | ".join("-" * w for w in widths) + " |")
        out.extend(line(r) for r in self.rows)
        return "\n".join(out).lstrip("\n") + "\n"


def coefficient_table(laws: Mapping[str, CorrelativeLaw], digits: int = 4, with_sd: bool = True) -> TextTable:
    """Seed Table 1 form: one column per law, rows ``c1_d..ck_d, c0_d`` grouped by dependent.

    Slopes in the law's dependent unit per independent unit, constants in the
    dependent unit; ``value ± sd`` when the law has a covariance.
    """
    laws = dict(laws)
    if not laws:
        raise InputError(None, "no law to tabulate")
    first = next(iter(laws.values()))
    for name, law in laws.items():
        if law.dependent != first.dependent or law.independent != first.independent:
            raise InputError(None, f"law {name!r} has other coordinates than {first.joint!r}: cannot share a table")
    k = len(first.independent)
    rows = []
    for d, dn in enumerate(first.dependent):
        for i in range(k + 1):
            label = f"c{i + 1}" if i < k else f"c{k + 1}"
            what = first.independent[i] if i < k else "constant"
            unit = (f"{first.dependent_units[d]}/{first.independent_units[i]}" if i < k else first.dependent_units[d])
            row = [dn, f"{label} ({what})", unit]
            for law in laws.values():
                v = law.coefficients[d, i]
                sd = law.coefficient_sd
                row.append(f"{v:.{digits}f}" + (f" ± {sd[d, i]:.{digits}f}" if with_sd and sd is not None else ""))
            rows.append(tuple(row))
    header = ("dependent", "coefficient", "unit") + tuple(laws)
    return TextTable(header, tuple(rows), "Multiple regression coefficients (seed Table 1 form)")


def deviation_table(cells: Mapping[str, Mapping[str, tuple[float, float | None]]], unit: str = "mm",
                    digits: int = 2) -> TextTable:
    """Seed Table 2 form: average deviation, ``motion specific / sub-motion specific``.

    Parameters
    ----------
    cells : ``{row (motion): {column (subject): (motion_law_dev, submotion_law_dev or None)}}``
        Deviations in metres (mean Euclidean distance between data and law).
    unit : ``"mm"`` or ``"m"``
    """
    f = {"mm": 1e3, "m": 1.0}[unit]
    cols = list(dict.fromkeys(c for row in cells.values() for c in row))
    rows = []
    for rname, row in cells.items():
        out = [rname]
        for c in cols:
            if c not in row:
                out.append("")
                continue
            a, b = row[c]
            sa = "-" if a is None or not math.isfinite(a) else f"{a * f:.{digits}f}"
            sb = "-" if b is None or not math.isfinite(b) else f"{b * f:.{digits}f}"
            out.append(f"{sa} / {sb}")
        rows.append(tuple(out))
    return TextTable(("motion",) + tuple(cols), tuple(rows),
                     f"Average deviation ({unit}) between data and law (motion specific / sub-motion specific)")


def format_number(x, scale: float = 1.0, digits: int = 3) -> str:
    """``x * scale`` with `digits` decimals; ``-`` for None or non-finite values."""
    return "-" if x is None or not np.isfinite(x) else f"{x * scale:.{digits}f}"


def fit_table(laws: Mapping[str, CorrelativeLaw]) -> TextTable:
    """Fit statistics per law and dependent (lengths in mm, angles in rad)."""
    rows = []
    for name, law in laws.items():
        f = law.fit
        for d, dn in enumerate(law.dependent):
            s = 1e3 if law.dependent_units[d] == "m" else 1.0
            u = "mm" if s == 1e3 else law.dependent_units[d]
            loto = None if f.loto_rms is None else f.loto_rms[d]
            rows.append((name, dn, u, format_number(f.r2[d], 1, 4), format_number(f.rms[d], s),
                         format_number(f.max_abs[d], s), "yes" if f.seed_criterion[d] else "no",
                         format_number(loto, s), str(f.n_frames), f"{f.condition:.3g}"))
    header = ("law", "dependent", "unit", "R2", "rms", "max_abs", "seed criterion", "held-out rms",
              "frames", "condition")
    return TextTable(header, tuple(rows), "Fit statistics (seed criterion: max|MC - E| < min|E|; held-out: "
                                          "leave-one-trial-out, or contiguous blocks with --folds)")


def plot_deviation(path: str | os.PathLike, independent, deviation, names: Sequence[str],
                   title: str = "", unit: str = "mm", angle_unit: str = "deg") -> Path:
    """Seed Figure 3 form: deviation coloured over the independent coordinates (PNG, Agg).

    Parameters
    ----------
    independent : array (F, k), radians (shown in degrees when `angle_unit` is ``deg``)
    deviation : array (F,), metres
    names : independent names (axis labels)
    """
    from personalize.presentation.html_report import new_figure, save_png   # no pyplot, no backend switched

    X = np.asarray(independent, float)
    X = np.atleast_2d(X.T).T
    dev = np.asarray(deviation, float) * {"mm": 1e3, "m": 1.0}[unit]
    if angle_unit == "deg":
        X = np.degrees(X)
    k = X.shape[1]
    fig = new_figure(7.5, 6.0)
    if k >= 3:
        ax = fig.add_subplot(111, projection="3d")
        sc = ax.scatter(X[:, 0], X[:, 1], X[:, 2], c=dev, cmap="jet", s=8, vmin=dev.min(), vmax=dev.max())
        ax.set_zlabel(f"{names[2]} ({angle_unit})", labelpad=8)
        ax.set_box_aspect(None, zoom=0.85)
    elif k == 2:
        ax = fig.add_subplot(111)
        sc = ax.scatter(X[:, 0], X[:, 1], c=dev, cmap="jet", s=8)
    else:
        ax = fig.add_subplot(111)
        sc = ax.scatter(X[:, 0], dev, c=dev, cmap="jet", s=8)
        ax.set_ylabel(f"deviation ({unit})")
    ax.set_xlabel(f"{names[0]} ({angle_unit})")
    if k >= 2:
        ax.set_ylabel(f"{names[1]} ({angle_unit})")
    fig.colorbar(sc, ax=ax, shrink=0.7, pad=0.12, label=f"deviation ({unit}), blue = min, red = max")
    ax.set_title(title or "Deviation between data and correlative law")
    return save_png(fig, path, dpi=110)
