"""Metrics of a validation run: a subject's summary flattened, grouped and summarised over subjects.

Metrics are whatever the job's summary holds, flattened with dots: for the full
pipeline ``errors.hip_centre_mm.mri|motion|fused``, ``errors.knee_axis_deg.*``,
``errors.ankle_axis_deg.*``, ``ik_rms_mm``, ``angle_rmse_deg.<angle>``; for the
surface job ``surfaces.<bone>.mean_abs_distance_mm`` etc.  ``metrics.csv`` holds
one row per subject (its draws and its flattened metrics), read back by `read_metrics`.
"""
from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from lowerlimb.atomic import write_text

#: estimate sources, in display order
SOURCES = ("mri", "motion", "fused")
#: summary keys that are settings, not metrics
NOT_METRICS = {"seed", "voxel_mm", "units", "version", "worker_pid", "n_frames", "frames"}
#: summary roots kept out of the report's tables (estimated coordinates, not errors; still in metrics.csv)
TABLE_ONLY_EXCLUDED = ("estimates", "truth_frame")


def flatten_metrics(summary: dict, prefix: str = "") -> dict[str, float]:
    """Numeric leaves of a summary as ``{"errors.hip_centre_mm.fused": 3.1, ...}`` (settings excluded)."""
    out: dict[str, float] = {}
    for k, v in summary.items():
        if k in NOT_METRICS:
            continue
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten_metrics(v, key + "."))
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out[key] = float(v)
    return out


def metric_groups(columns: Sequence[str]) -> dict[str, list[tuple[str, str]]]:
    """Group metric columns for plotting: {group: [(label, column), ...]}.

    ``a.b.<source>`` (source in mri/motion/fused) -> group ``a.b``, one box per source;
    ``a.<item>.<quantity>`` -> group ``a.<quantity>``, one box per item (e.g. bone);
    ``a.<item>`` -> group ``a``; a top-level scalar is its own group.
    """
    groups: dict[str, list[tuple[str, str]]] = {}
    for c in columns:
        parts = c.split(".")
        if parts[-1] in SOURCES and len(parts) >= 2:
            g, label = ".".join(parts[:-1]), parts[-1]
        elif len(parts) >= 3:
            g, label = ".".join(parts[:-2] + parts[-1:]), parts[-2]
        elif len(parts) == 2:
            g, label = parts[0], parts[1]
        else:
            g, label = c, c
        groups.setdefault(g, []).append((label, c))
    for g, items in groups.items():
        if all(lbl in SOURCES for lbl, _ in items):
            items.sort(key=lambda t: SOURCES.index(t[0]))
    return groups


def metric_statistics(rows: Sequence[dict], columns: Sequence[str]) -> list[dict]:
    """n, mean, sd, median, 95th percentile and max of each metric column over subjects."""
    stats = []
    for c in columns:
        v = np.array([r[c] for r in rows if isinstance(r.get(c), float) and math.isfinite(r[c])])
        if v.size == 0:
            continue
        stats.append({"metric": c, "n": int(v.size), "mean": float(v.mean()),
                      "sd": float(v.std(ddof=1)) if v.size > 1 else float("nan"),
                      "median": float(np.median(v)), "p95": float(np.percentile(v, 95)), "max": float(v.max())})
    return stats


def write_metrics_csv(path: Path, columns: Sequence[str], rows: Sequence[dict]) -> Path:
    """Atomically write ``metrics.csv``: one row per subject; floats to 6 significant digits, NaN and None empty."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow(["" if r.get(c) is None or (isinstance(r.get(c), float) and math.isnan(r[c])) else
                    (f"{r[c]:.6g}" if isinstance(r[c], float) else r[c]) for c in columns])
    return write_text(path, buf.getvalue())


def read_metrics(path: str | os.PathLike) -> list[dict]:
    """Rows of a metrics.csv; numeric cells as floats, empty cells as NaN."""
    rows = []
    with open(path, newline="", encoding="utf-8") as f:
        for r in csv.DictReader(f):
            row: dict[str, Any] = {}
            for k, v in r.items():
                if k in ("subject", "status", "error"):
                    row[k] = v
                else:
                    try:
                        row[k] = float(v) if v != "" else float("nan")
                    except ValueError:
                        row[k] = v
            rows.append(row)
    return rows


#: quantities estimated by both sources and fused (summary ``errors`` keys)
FUSED_QUANTITIES = ("hip_centre_mm", "knee_axis_deg", "ankle_axis_deg", "knee_centre_mm", "ankle_centre_mm")


def fusion_statistics(rows: Sequence[dict]) -> list[dict]:
    """How the fused estimates compare with each source, per subject (worst side) and per leg.

    For every quantity of `FUSED_QUANTITIES` present in the rows' metrics
    (``errors.<q>.<source>`` worst side; ``errors_per_side.<side>.<q>.<source>`` per leg):
    the fraction of cases where the fused error is below both sources', below
    the MRI-only one and below the motion-only one, and the median error of each source.
    """
    out = []
    for q in FUSED_QUANTITIES:
        for unit, prefixes in (("subject (worst side)", [f"errors.{q}."]),
                               ("leg", [f"errors_per_side.{s}.{q}." for s in ("r", "l")])):
            e = []
            for r in rows:
                for p in prefixes:
                    v = [r.get(p + src) for src in SOURCES]
                    if all(isinstance(x, float) and math.isfinite(x) for x in v):
                        e.append(v)
            if not e:
                continue
            e = np.array(e)
            out.append({"quantity": q, "unit": unit, "n": len(e),
                        "fused_below_both": float(np.mean(e[:, 2] < e[:, :2].min(axis=1))),
                        "fused_below_mri": float(np.mean(e[:, 2] < e[:, 0])),
                        "fused_below_motion": float(np.mean(e[:, 2] < e[:, 1])),
                        **{f"median_{src}": float(np.median(e[:, i])) for i, src in enumerate(SOURCES)}})
    return out

