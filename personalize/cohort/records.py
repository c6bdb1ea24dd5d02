"""A batch's records and files: the manifest read in, one result per subject, ``batch.csv`` written out.

A manifest is a CSV with columns ``subject`` (the output folder name: a safe
folder name, unique even ignoring case) and ``path`` (its SUBJECT_DIR, relative
paths taken from the manifest's folder).  ``OUT/<subject>/summary.json`` marks a
complete subject; ``OUT/batch.csv`` lists subject, status, seconds, error, output.
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

from lowerlimb.atomic import write_text
from lowerlimb.errors import InputError

#: the per-subject job used when none is given: ``run_subject(subject_dir, out, *, progress=None) -> dict``
DEFAULT_JOB = "personalize.pipeline.run_subject"
#: per-subject completion marker (the job's summary, written last)
SUMMARY = "summary.json"
#: the batch's table of results
BATCH_CSV = "batch.csv"
BATCH_COLUMNS = ("subject", "status", "seconds", "error", "output")

_SAFE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")


@dataclass(frozen=True)
class Subject:
    """One manifest row: subject id (output folder name) and its SUBJECT_DIR."""

    id: str
    path: Path


@dataclass(frozen=True)
class SubjectResult:
    """Outcome of one subject.

    Attributes
    ----------
    subject : str
    status : {"ok", "error", "skipped"}
        ``skipped``: already complete from an earlier run.
    seconds : float
        Wall time of the job on its worker (0 when skipped; NaN when the worker died).
    error : str
        One-line message for ``error`` rows, empty otherwise.
    output : str
        ``OUT/<subject>`` (exists only for ok/skipped rows).
    """

    subject: str
    status: str
    seconds: float
    error: str
    output: str

    def row(self) -> list:
        return [self.subject, self.status, "" if math.isnan(self.seconds) else f"{self.seconds:.3f}",
                self.error, self.output]


@dataclass(frozen=True)
class BatchResult:
    """Outcome of a batch.

    Attributes
    ----------
    results : tuple of SubjectResult, in manifest order
    out : Path
        Output folder.
    csv : Path
        ``OUT/batch.csv``.
    wall_seconds : float
        Wall time of the run, cluster start-up included.
    compute_seconds : float
        Wall time from the first submission to the last completion.
    workers : int
        Number of workers that were available.
    """

    results: tuple[SubjectResult, ...]
    out: Path
    csv: Path
    wall_seconds: float
    compute_seconds: float
    workers: int

    @property
    def counts(self) -> dict[str, int]:
        c = {"ok": 0, "error": 0, "skipped": 0}
        for r in self.results:
            c[r.status] += 1
        return c

    def by_subject(self) -> dict[str, SubjectResult]:
        return {r.subject: r for r in self.results}

    @property
    def subjects_per_minute(self) -> float:
        """Subjects run (ok + error) per minute of compute wall time."""
        n = self.counts["ok"] + self.counts["error"]
        return 60.0 * n / self.compute_seconds if self.compute_seconds > 0 else float("nan")



def check_subject_id(subject: str, source: str | os.PathLike, where: str) -> str:
    """Return `subject` if it is a safe folder name, else raise `InputError`."""
    if not _SAFE_ID.match(subject) or subject in (".", ".."):
        raise InputError(source, f"{where}: subject id {subject!r} is not a safe folder name "
                                 "(1-128 letters, digits, '.', '_' or '-', not starting with '.' or '-')")
    return subject


def read_manifest(path: str | os.PathLike) -> list[Subject]:
    """Read a cohort manifest: CSV with columns ``subject`` and ``path``.

    Relative paths are taken from the manifest's folder.  Extra columns are
    ignored.  Raises `InputError` naming the manifest (and row) for a missing
    file or column, an empty manifest, an unsafe or duplicate subject id, or a
    subject folder that does not exist.
    """
    mpath = Path(path)
    if not mpath.is_file():
        raise InputError(mpath, "manifest not found")
    try:
        text = mpath.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(mpath, "manifest is not UTF-8 text") from None
    reader = csv.reader(io.StringIO(text))
    header = next(reader, None)
    if header is None:
        raise InputError(mpath, "manifest is empty (expected a header row: subject,path)")
    cols = [h.strip().lower() for h in header]
    missing = [c for c in ("subject", "path") if c not in cols]
    if missing:
        raise InputError(mpath, f"missing column(s) {', '.join(missing)} (header: {', '.join(header)}; "
                                "expected columns subject,path)")
    i_sub, i_path = cols.index("subject"), cols.index("path")
    base = mpath.resolve().parent
    subjects: list[Subject] = []
    seen: dict[str, int] = {}
    for row in reader:
        if not row or all(not c.strip() for c in row):
            continue
        line = reader.line_num
        where = f"row {line}"
        if len(row) <= max(i_sub, i_path):
            raise InputError(mpath, f"{where}: {len(row)} field(s), expected at least {max(i_sub, i_path) + 1}")
        sid, raw = row[i_sub].strip(), row[i_path].strip()
        check_subject_id(sid, mpath, where)
        if sid.lower() in seen:
            raise InputError(mpath, f"{where}: subject id {sid!r} repeats row {seen[sid.lower()]} (ids must be unique, ignoring case)")
        seen[sid.lower()] = line
        if not raw:
            raise InputError(mpath, f"{where} ({sid}): empty path")
        p = Path(raw).expanduser()
        p = p if p.is_absolute() else base / p
        if not p.is_dir():
            raise InputError(mpath, f"{where} ({sid}): subject folder {p} not found")
        subjects.append(Subject(sid, p.resolve()))
    if not subjects:
        raise InputError(mpath, "manifest lists no subjects")
    return subjects


def write_manifest(path: str | os.PathLike, subjects: Iterable[Subject]) -> Path:
    """Write a manifest (paths relative to its folder when below it)."""
    path = Path(path)
    base = path.resolve().parent
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["subject", "path"])
    for s in subjects:
        p = Path(s.path).resolve()
        w.writerow([s.id, p.relative_to(base).as_posix() if base in p.parents else str(p)])
    return write_text(path, buf.getvalue())


def is_complete(subject_out: str | os.PathLike) -> bool:
    """Whether ``subject_out/summary.json`` exists and holds a JSON object (the completion marker)."""
    p = Path(subject_out) / SUMMARY
    try:
        return isinstance(json.loads(p.read_text(encoding="utf-8")), dict)
    except (OSError, ValueError):
        return False


def write_batch_csv(path: str | os.PathLike, results: Iterable[SubjectResult]) -> Path:
    """Atomically write ``batch.csv``: subject, status, seconds, error, output."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(BATCH_COLUMNS)
    for r in results:
        w.writerow(r.row())
    return write_text(path, buf.getvalue())


def read_batch_csv(path: str | os.PathLike) -> list[SubjectResult]:
    """Read a ``batch.csv`` written by `write_batch_csv`."""
    rows = []
    with open(path, newline="", encoding="utf-8") as f:
        for r in csv.DictReader(f):
            rows.append(SubjectResult(r["subject"], r["status"], float(r["seconds"]) if r["seconds"] else float("nan"),
                                      r["error"], r["output"]))
    return rows

