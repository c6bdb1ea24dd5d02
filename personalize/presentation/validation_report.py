"""The validation reports: ``report.html`` of a phantom validation run and of the realistic set.

Distribution plots (box plots with the subjects as dots, histograms for scalar
metrics) and tables of per-metric statistics, drawn from the rows of
``metrics.csv`` (`personalize.evaluation.metrics`).
"""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from personalize.cohort import BatchResult
from personalize.evaluation.metrics import SOURCES, TABLE_ONLY_EXCLUDED, fusion_statistics, metric_groups, metric_statistics
from personalize.presentation.html_report import Figure, Section, Table, new_figure, render_report

#: summary roots plotted in the report, in this order (errors vs truth, IK residuals, angle errors, surfaces)
FIGURE_ROOTS = ("errors", "ik_rms_mm", "angle_rmse_deg", "ik", "surfaces")


def _box_figure(group: str, items: list[tuple[str, str]], rows: Sequence[dict]):
    fig = new_figure(max(3.5, 1.1 * len(items) + 1.5), 3.4)
    ax = fig.add_subplot()
    data, labels = [], []
    for label, c in items:
        v = np.array([r[c] for r in rows if isinstance(r.get(c), float) and math.isfinite(r[c])])
        data.append(v)
        labels.append(f"{label}\n(n={v.size})")
    ax.boxplot(data, showfliers=False)
    ax.set_xticks(range(1, len(labels) + 1), labels)
    jit = np.random.default_rng(0)
    for i, v in enumerate(data, start=1):
        ax.plot(i + jit.uniform(-0.12, 0.12, v.size), v, "o", ms=3.5, alpha=0.6, color="tab:blue")
    ax.set_ylabel(group.split(".")[-1])
    ax.set_title(group, fontsize=10)
    ax.grid(axis="y", alpha=0.3)
    return fig


def _hist_figure(column: str, rows: Sequence[dict]):
    fig = new_figure(4.0, 3.0)
    ax = fig.add_subplot()
    v = np.array([r[column] for r in rows if isinstance(r.get(column), float) and math.isfinite(r[column])])
    ax.hist(v, bins=max(5, min(30, v.size // 2 or 1)), color="tab:blue", alpha=0.8)
    ax.set_xlabel(column)
    ax.set_ylabel("subjects")
    ax.set_title(column, fontsize=10)
    return fig


def validation_report(path: str | os.PathLike, rows: Sequence[dict], metric_columns: Sequence[str],
                      factor_columns: Sequence[str], *, seed: int, job: str, batch: BatchResult | None = None) -> Path:
    """Write ``report.html``: cohort, metric statistics, distribution plots, failures, draws."""
    ok = [r for r in rows if r["status"] in ("ok", "skipped")]
    failed = [r for r in rows if r["status"] == "error"]
    sections = [Section("Cohort", [
        f"{len(rows)} phantom subjects drawn from seed {seed}: random anatomy, MRI voxel size, segmentation "
        f"noise, soft-tissue artefact and marker noise; job {job}. {len(ok)} completed, {len(failed)} failed.",
        "Errors are against the phantoms' exact truth; angles in degrees, distances in millimetres "
        "(per metric name). metrics.csv holds one row per subject.",
    ])]
    # headline metrics get statistics and plots; the rest (per-side errors, registration, ...) a second table;
    # estimates themselves (coordinates) are only in metrics.csv
    def root_rank(c):
        r = c.split(".")[0]
        return FIGURE_ROOTS.index(r) if r in FIGURE_ROOTS else len(FIGURE_ROOTS)

    primary = sorted((c for c in metric_columns if root_rank(c) < len(FIGURE_ROOTS)), key=root_rank)
    if not primary:
        primary = list(metric_columns)
    headline = [c for c in primary if c.split(".")[0] != "ik"]  # per-trial IK residuals: plotted, tabled below
    other = [c for c in metric_columns if c not in headline and c.split(".")[0] not in TABLE_ONLY_EXCLUDED]
    stats = metric_statistics(ok, headline)
    items: list[Any] = [Table.from_records(stats, caption="Per-metric statistics over the completed subjects")
                        if stats else "No metric was produced."]
    if "angle_rmse_deg" not in {c.split(".")[0] for c in metric_columns}:
        items.append("The job's summary has no joint-angle RMSE against truth (angle_rmse_deg); none is reported.")
    for g, members in metric_groups(primary).items():
        if len(members) == 1 and members[0][1] == g:
            items.append(Figure(_hist_figure(g, ok), caption=f"Distribution of {g} over subjects"))
        else:
            items.append(Figure(_box_figure(g, members, ok),
                                caption=f"{g}: box = quartiles, whiskers = 1.5 IQR, dots = subjects"))
    sections.append(Section("Metrics", items))
    fus = fusion_statistics(ok)
    if fus:
        sections.append(Section("Fusion against each source", [Table.from_records(
            fus, caption="Fraction of subjects (worst side) and of legs where the fused error is below both "
                         "sources', below the MRI-only and below the motion-only error; median errors (mm or deg)")]))
    other_stats = metric_statistics(ok, other)
    if other_stats:
        sections.append(Section("Other summary quantities", [Table.from_records(
            other_stats, caption="Per-trial IK residuals, per-side errors, registration and other summary entries")]))
    if failed:
        sections.append(Section("Failed subjects", [Table.from_records(
            [{"subject": r["subject"], "error": r.get("error", "")} for r in failed])]))
    sections.append(Section("Draws per subject", [Table.from_records(
        [{c: r.get(c) for c in ["subject", "status", *factor_columns]} for r in rows],
        caption="Random factors of each phantom subject (stature m, angles deg, voxel mm, marker noise mm)")]))
    if batch is not None:
        sections.append(Section("Run", [f"{batch.workers} dask workers; {batch.compute_seconds:.1f} s of compute wall time "
                                         f"for {batch.counts['ok'] + batch.counts['error']} subjects run, "
                                         f"{batch.counts['skipped']} already complete."]))
    return render_report(path, "Validation on phantom subjects", sections, meta=f"personalize validate, seed {seed}")



def realistic_report(path: str | os.PathLike, rows: Sequence[dict], specs: Sequence, table: Sequence[dict],
                     metric_columns: Sequence[str], factor_columns: Sequence[str], *, seed: int, job: str) -> Path:
    """Write the realistic set's ``report.html``: the set, per marker set and lab, coverage, metrics, subjects.

    `specs` are the set's `personalize.evaluation.realistic_set.RealisticSpec`; `table` is
    `personalize.evaluation.realistic_set.realistic_table` of `rows`.
    """
    ok = [r for r in rows if r["status"] == "ok"]
    cov_rows = []
    for src in SOURCES:
        v = [r[c] for r in ok for c in r if c.startswith("coverage.") and c.endswith(f".{src}")]
        if v:
            cov_rows.append({"source": src, "joints": len(v), "inside_95pct_ellipsoid": float(np.mean(v))})
    sections = [
        Section("Realistic set", [
            f"{len(rows)} subjects from seed {seed}: anatomy analytic / ICL-MRI / LHDL-CT, marker sets "
            f"{', '.join(sorted({s.marker_set for s in specs}))}, labs {', '.join(sorted({s.lab for s in specs}))}, "
            f"tissue {', '.join(sorted({s.tissue for s in specs}))}, {sum(not s.functional for s in specs)} without a "
            f"functional trial, {sum(s.imaging == 'meshes' for s in specs)} with a mesh folder instead of a label "
            f"volume; job {job}. {len(ok)} completed, {len(rows) - len(ok)} refused or failed."]),
        Section("Per marker set and lab", [Table.from_records(table, caption="Fused errors (median, mm / deg), "
                                                                           "95 % coverage of the stated covariances")]),
    ]
    if cov_rows:
        sections.append(Section("Coverage", [Table.from_records(cov_rows, caption="Fraction of true joint centres "
                                                                                   "inside the stated 95 % ellipsoid")]))
    stats = metric_statistics(ok, [c for c in metric_columns if c.split(".")[0] in ("errors", "angle_rmse_deg", "ik_rms_mm")])
    if stats:
        sections.append(Section("Metrics", [Table.from_records(stats, caption="Completed subjects")]))
    sections.append(Section("Subjects", [Table.from_records(
        [{c: r.get(c) for c in ["subject", "status", *factor_columns, "error"]} for r in rows],
        caption="Each subject's factors and, when refused, the one-line reason")]))
    return render_report(path, "Realistic validation", sections, meta=f"personalize validate --realistic, seed {seed}")
