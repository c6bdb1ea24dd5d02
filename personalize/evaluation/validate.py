"""Validation runs: the per-subject job on a drawn set of subjects, errors against truth.

`run_validation` draws N phantom subjects (`personalize.evaluation.phantom_set`),
`run_realistic_validation` the realistic set (`personalize.evaluation.realistic_set`);
both run one dask task per subject through `personalize.cohort.run_batch` (the
task first materialises its subject folder, then runs the job on it) and collect
every numeric entry of each subject's ``summary.json`` into ``metrics.csv``
(`personalize.evaluation.metrics`) and a ``report.html`` with their distributions
(`personalize.presentation.validation_report`).

Layout of ``OUT``::

    manifest.csv              subject,path of the subjects
    subjects/<id>/            phantom.json or realistic.json (the draws) + the written subject
    results/<id>/             the job's outputs and summary.json
    results/batch.csv         status per subject
    metrics.csv               one row per subject: draws + flattened metrics
    fusion.json               fused vs each source: fractions of subjects / legs, medians (phantom set)
    table.json                per marker set and lab (realistic set)
    report.html               tables and distribution plots (self-contained)
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from lowerlimb.atomic import inside, write_text
from lowerlimb.errors import InputError

from personalize.cohort import DEFAULT_JOB, BatchResult, Subject, run_batch, write_manifest
from personalize.cohort.jobs import resolve_job
from personalize.evaluation.metrics import TABLE_ONLY_EXCLUDED, flatten_metrics, fusion_statistics, write_metrics_csv
from personalize.evaluation.phantom_set import SPEC, draw_subjects, validation_job
from personalize.evaluation.realistic_set import (REALISTIC_SPEC, coverage_metrics, draw_realistic_subjects,
                                                  realistic_table, realistic_validation_job)
from personalize.presentation.validation_report import realistic_report, validation_report


@dataclass(frozen=True)
class ValidationResult:
    """Outcome of `run_validation` / `run_realistic_validation`: the paths written and the per-subject rows."""

    out: Path
    metrics_csv: Path
    report: Path
    rows: tuple
    metric_columns: tuple
    batch: BatchResult


def _checked_job(out: Path, job: str | None) -> str:
    """The per-subject job (default: the full pipeline), importable; `out` must be a folder if it exists."""
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")
    job = job or DEFAULT_JOB
    resolve_job(job)
    return job


def _stage_subjects(out: Path, specs: Sequence, spec_name: str) -> list[Subject]:
    """Write each spec as ``out/subjects/<id>/<spec_name>`` (kept when identical) and ``out/manifest.csv``.

    A folder holding a run with other settings (a spec file that differs) is refused.
    """
    subjects = []
    for s in specs:
        d = inside(out, f"subjects/{s.subject}")
        text = json.dumps(s.to_json(), indent=1) + "\n"
        if (d / spec_name).is_file() and (d / spec_name).read_text(encoding="utf-8") != text:
            raise InputError(out, f"holds a validation run with other settings ({s.subject} differs); use a new --out folder")
        if not (d / spec_name).is_file():
            write_text(d / spec_name, text)
        subjects.append(Subject(s.subject, d))
    write_manifest(inside(out, "manifest.csv"), subjects)
    return subjects


def _metric_rows(specs: Sequence, subjects: Sequence[Subject], batch: BatchResult,
                 metrics: Callable[[dict, Path], dict]) -> tuple[list[dict], list[str], list[str]]:
    """One row per subject (status, one-line error, draws, ``metrics(summary, subject_dir)``); metric and factor columns."""
    status = batch.by_subject()
    rows, metric_cols = [], {}
    factor_cols: dict[str, None] = {}
    for s, subj in zip(specs, subjects):
        r = status[s.subject]
        # a subject completed by an earlier run counts as ok here (batch.csv says "skipped")
        row: dict[str, Any] = {"subject": s.subject, "status": "ok" if r.status == "skipped" else r.status,
                               "error": (r.error or "").strip().splitlines()[-1] if r.error else ""}
        f = s.factors()
        factor_cols.update(dict.fromkeys(f))
        row.update(f)
        if r.status in ("ok", "skipped"):
            m = metrics(json.loads((Path(r.output) / "summary.json").read_text(encoding="utf-8")), Path(subj.path))
            metric_cols.update(dict.fromkeys(m))
            row.update(m)
        rows.append(row)
    return rows, list(metric_cols), list(factor_cols)


def run_validation(n: int, seed: int, out: str | os.PathLike, *, scheduler=None, workers: int = 2,
                   job: str | None = None, ranges: dict | None = None, bones: Sequence[str] | None = None,
                   motion: bool = True, progress: bool = True, console=None) -> ValidationResult:
    """Draw, write and run `n` phantom subjects; write ``metrics.csv`` and ``report.html`` into `out`.

    Parameters
    ----------
    n, seed : number of subjects and master seed (same values -> same subjects)
    out : output folder (re-running with the same n and seed resumes)
    scheduler, workers : see `personalize.cohort.run_batch`
    job : per-subject job (dotted path); default: the full pipeline (`personalize.cohort.DEFAULT_JOB`)
    ranges : overrides of `personalize.evaluation.phantom_set.DEFAULT_RANGES`
    bones : write only these bones (default all)
    motion : write the motion trials too
    """
    out = Path(out)
    job = _checked_job(out, job)
    specs = draw_subjects(n, seed, ranges=ranges, bones=bones, motion=motion)
    subjects = _stage_subjects(out, specs, SPEC)
    batch = run_batch(subjects, inside(out, "results"), job=validation_job, job_kwargs={"job": job},
                      scheduler=scheduler, workers=workers, progress=progress, console=console)
    rows, mcols, factor_cols = _metric_rows(specs, subjects, batch, lambda summary, _: flatten_metrics(summary))
    csv_path = write_metrics_csv(inside(out, "metrics.csv"), ["subject", "status", *factor_cols, *mcols, "error"], rows)
    fus = fusion_statistics([r for r in rows if r["status"] == "ok"])
    if fus:
        write_text(inside(out, "fusion.json"), json.dumps({"units": "fractions; medians in mm or deg as named",
                                                            "rows": fus}, indent=1) + "\n")
    rep = validation_report(inside(out, "report.html"), rows, mcols, factor_cols, seed=seed, job=job, batch=batch)
    return ValidationResult(out, csv_path, rep, tuple(rows), tuple(mcols), batch)


def _realistic_metrics(summary: dict, subject_dir: Path) -> dict:
    m = flatten_metrics({k: v for k, v in summary.items() if k not in TABLE_ONLY_EXCLUDED})
    m.update(coverage_metrics(summary, subject_dir))
    return m


def run_realistic_validation(n: int, seed: int, out: str | os.PathLike, *, data_root: str | os.PathLike | None = None,
                             scheduler=None, workers: int = 2, job: str | None = None, progress: bool = True,
                             console=None, palpation: bool = True) -> ValidationResult:
    """`draw_realistic_subjects` (``palpation``: see there), write and run them; ``metrics.csv`` (refusals as rows with their reason) and report.

    Metrics per subject: every numeric summary entry (joint centre and axis errors of the MRI-only,
    motion-only and fused estimates, IK angle RMSE, IK residuals) plus `coverage_metrics`.
    `data_root` defaults to ``shared/data`` beside the repository.
    """
    out = Path(out)
    job = _checked_job(out, job)
    if data_root is None:
        data_root = Path(__file__).resolve().parents[3] / "shared" / "data"
    specs = draw_realistic_subjects(n, seed, data_root if Path(data_root).is_dir() else None, palpation=palpation)
    if console is not None and all(s.anatomy == "analytic" for s in specs):
        console.print(f"[yellow]warning:[/] no real anatomy under {data_root} (bones/ICL_MRI, bones/LHDL_CT and "
                      "their reference_models): every subject is analytic; give the real data with --data")
    subjects = _stage_subjects(out, specs, REALISTIC_SPEC)
    batch = run_batch(subjects, inside(out, "results"), job=realistic_validation_job, job_kwargs={"job": job},
                      scheduler=scheduler, workers=workers, progress=progress, console=console)
    rows, mcols, factor_cols = _metric_rows(specs, subjects, batch, _realistic_metrics)
    csv_path = write_metrics_csv(inside(out, "metrics.csv"), ["subject", "status", *factor_cols, *mcols, "error"], rows)
    table = realistic_table(rows)
    write_text(inside(out, "table.json"), json.dumps({"units": "mm, deg, fractions", "rows": table}, indent=1,
                                                     default=float) + "\n")
    rep = realistic_report(inside(out, "report.html"), rows, specs, table, mcols, factor_cols, seed=seed, job=job)
    return ValidationResult(out, csv_path, rep, tuple(rows), tuple(mcols), batch)
