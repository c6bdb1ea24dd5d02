"""Cohorts: run the per-subject job on many subjects with dask.distributed.

One dask task per subject.  The runner

* validates the manifest (columns ``subject,path``; subject ids that are safe
  folder names, unique even ignoring case; existing subject folders, relative
  paths taken from the manifest's folder) and refuses it with one `InputError`
  naming the manifest and the row;
* skips subjects whose ``OUT/<subject>/summary.json`` is complete (resumption);
* runs each remaining subject's job into a staging folder published into
  ``OUT/<subject>/`` only when the job succeeded; ``summary.json`` - the
  completion marker - is written last, after everything else is in place;
* records a bad subject (`InputError`, `FitError`) as an error row while the
  others go on; other exceptions are retried (``retries``) and a worker that
  dies mid-task has its task rescheduled by the scheduler (up to
  ``distributed.scheduler.allowed-failures`` deaths, default 3), so nothing is lost;
* rewrites ``OUT/batch.csv`` (subject, status ok|error|skipped, seconds, error,
  output) atomically after every completed subject, so an interrupted batch
  still says what is done.

Workers run with one BLAS/OpenMP thread (the parallelism is across subjects).

>>> from personalize.cohort import run_batch
>>> result = run_batch("cohort/manifest.csv", "results", workers=2)
>>> result.counts
{'ok': 3, 'error': 1, 'skipped': 0}
"""
from __future__ import annotations

import contextlib
import csv
import importlib
import io
import json
import logging
import math
import os
import re
import shutil
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Sequence

from kinematics.atomic import inside, staged_dir, write_text
from kinematics.errors import FitError, InputError

#: the per-subject job used when none is given: ``run_subject(subject_dir, out, *, progress=None) -> dict``
DEFAULT_JOB = "personalize.pipeline.run_subject"
#: per-subject completion marker (the job's summary, written last)
SUMMARY = "summary.json"
#: the batch's table of results
BATCH_CSV = "batch.csv"
BATCH_COLUMNS = ("subject", "status", "seconds", "error", "output")
#: environment of worker processes: one thread per BLAS/OpenMP pool
THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "VECLIB_MAXIMUM_THREADS": "1", "NUMEXPR_NUM_THREADS": "1", "MPLBACKEND": "Agg"}

_SAFE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")


# --------------------------------------------------------------------------- records
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


# --------------------------------------------------------------------------- manifest
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


# --------------------------------------------------------------------------- job (runs on workers)
def resolve_job(job: str | Callable) -> Callable:
    """The job function from a callable or a dotted path (``pkg.module.func`` or ``pkg.module:func``)."""
    if callable(job):
        return job
    mod, sep, name = job.partition(":") if ":" in job else job.rpartition(".")
    if not mod or not name:
        raise InputError("job", f"{job!r} is not a dotted path module.function")
    try:
        module = importlib.import_module(mod)
    except ImportError as exc:
        raise InputError("job", f"cannot import {mod} for {job} ({exc})") from None
    fn = getattr(module, name, None)
    if not callable(fn):
        raise InputError("job", f"{mod} has no function {name}")
    return fn


def _job_reference(job: str | Callable) -> str | Callable:
    """Send module-level functions by name (imported on the worker); others are pickled by dask."""
    if isinstance(job, str):
        return job
    mod, qual = getattr(job, "__module__", None), getattr(job, "__qualname__", "")
    if mod and mod != "__main__" and "<" not in qual and "." not in qual:
        return f"{mod}:{qual}"
    return job


def _json_default(o: Any):
    if hasattr(o, "tolist"):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def _error_text(exc: BaseException) -> str:
    kind = "input error" if isinstance(exc, InputError) else "fit error" if isinstance(exc, FitError) else "error"
    return " ".join(f"{kind}: {exc}".split())  # one line


def run_subject_task(subject: str, subject_dir: str, out_dir: str, job: str | Callable,
                     job_kwargs: dict | None = None) -> dict:
    """Run one subject on a worker; returns a `SubjectResult` as a dict.

    The job writes into a staging folder that is published into `out_dir` only
    on success; the returned summary is then written to ``out_dir/summary.json``
    last, so its presence means the subject is complete.  `InputError` and
    `FitError` (deterministic, caused by the subject) become an error result;
    any other exception propagates so that dask retries the task.
    """
    for k, v in THREAD_ENV.items():
        os.environ.setdefault(k, v)
    fn = resolve_job(job)
    final = Path(out_dir)
    t0 = time.perf_counter()
    try:
        with staged_dir(final) as stage:
            summary = fn(Path(subject_dir), stage, **(job_kwargs or {}))
            if not isinstance(summary, dict):
                raise TypeError(f"the job returned {type(summary).__name__}, expected the summary dict")
            text = json.dumps(summary, indent=1, default=_json_default, allow_nan=True) + "\n"
            (stage / SUMMARY).unlink(missing_ok=True)  # published last, below
        write_text(final / SUMMARY, text)
    except (InputError, FitError) as exc:
        return {"subject": subject, "status": "error", "seconds": time.perf_counter() - t0,
                "error": _error_text(exc), "output": str(final)}
    return {"subject": subject, "status": "ok", "seconds": time.perf_counter() - t0, "error": "", "output": str(final)}


# --------------------------------------------------------------------------- client side
@contextlib.contextmanager
def _quiet_dask() -> Iterator[None]:
    """Silence distributed's INFO/WARNING chatter (worker restarts, connection notices) in this process."""
    loggers = [logging.getLogger(n) for n in ("distributed", "distributed.nanny", "distributed.scheduler",
                                                "distributed.worker", "distributed.core", "distributed.client")]
    old = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    try:
        yield
    finally:
        for lg, lv in zip(loggers, old):
            lg.setLevel(lv)


@contextlib.contextmanager
def dask_client(scheduler=None, workers: int = 2) -> Iterator[Any]:
    """A dask Client: on `scheduler` (address or Client), else on a new LocalCluster of `workers` processes."""
    from distributed import Client, LocalCluster

    if scheduler is not None and not isinstance(scheduler, str):
        yield scheduler  # a Client owned by the caller
        return
    if scheduler:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise InputError("--scheduler", f"cannot connect to {scheduler} ({exc})") from None
        try:
            yield client
        finally:
            client.close()
        return
    import dask

    if not (1 <= int(workers) <= 256):
        raise InputError("--workers", f"{workers} is outside 1-256")
    # dask's default pre-spawn environment sets MALLOC_TRIM_THRESHOLD_=65536, which makes glibc return
    # memory to the OS on nearly every free: measured on run_demo, 20x the page faults and 1.8x the CPU
    # time per subject.  Subjects allocate and free large arrays, so keep glibc's adaptive threshold.
    pre_spawn = {k: v for k, v in (dask.config.get("distributed.nanny.pre-spawn-environ") or {}).items()
                 if k != "MALLOC_TRIM_THRESHOLD_"}
    pre_spawn.update(THREAD_ENV)
    saved_env = dict(os.environ)  # the nanny copies its pre-spawn environment into this process's os.environ
    try:
        with dask.config.set({"distributed.nanny.pre-spawn-environ": pre_spawn}):
            cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                                   dashboard_address=None, silence_logs=logging.ERROR)
        client = Client(cluster)
        try:
            yield client
        finally:
            client.close()
            cluster.close()
    finally:
        os.environ.clear()
        os.environ.update(saved_env)


def _failure_row(s: Subject, dst: Path, fut) -> SubjectResult:
    try:
        exc = fut.exception()
    except Exception as cancelled:  # a cancelled future (scheduler lost) raises instead of returning
        exc = cancelled
    if type(exc).__name__ == "KilledWorker":
        msg = "worker died while running this subject, on every attempt (out of memory or a crash in native code?)"
    elif isinstance(exc, (InputError, FitError)):
        msg = _error_text(exc)
    else:
        msg = " ".join(f"internal error ({type(exc).__name__}: {exc}) after all retries".split())
    return SubjectResult(s.id, "error", float("nan"), msg, str(dst))


def _progress(console, enabled: bool):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    TimeRemainingColumn(), TextColumn("{task.fields[status]}"), console=console, disable=not enabled,
                    transient=False)


def run_batch(manifest: str | os.PathLike | Sequence[Subject], out: str | os.PathLike, *,
              job: str | Callable = DEFAULT_JOB, job_kwargs: dict | None = None, scheduler=None, workers: int = 2,
              retries: int = 2, resume: bool = True, progress: bool = True, console=None) -> BatchResult:
    """Run `job` on every subject of `manifest`, results in ``out/<subject>/``.

    Parameters
    ----------
    manifest : path to a manifest CSV (see `read_manifest`) or a sequence of `Subject`
    out : path
        Output folder; ``out/<subject>/`` per subject and ``out/batch.csv``.
    job : callable or dotted path
        ``job(subject_dir: Path, out: Path, **job_kwargs) -> dict`` (the summary).
        Module-level functions are imported by name on the workers.
    scheduler : str, distributed.Client or None
        Scheduler address (``tcp://host:8786``) of an existing cluster, a
        Client, or None for a LocalCluster of `workers` single-threaded processes.
    workers : int
        LocalCluster size (ignored with a scheduler).
    retries : int
        Extra attempts for a task that raised an unexpected exception.
    resume : bool
        Skip subjects whose ``summary.json`` is complete.
    progress : bool
        Show a rich progress bar (on `console`, default stderr).

    Returns
    -------
    BatchResult
    """
    t_start = time.perf_counter()
    if scheduler is None and not (1 <= int(workers) <= 256):
        raise InputError("--workers", f"{workers} is outside 1-256")
    subjects = read_manifest(manifest) if isinstance(manifest, (str, os.PathLike)) else list(manifest)
    ids = set()
    for s in subjects:
        check_subject_id(s.id, "subjects", "subject list")
        if s.id.lower() in ids:
            raise InputError("subjects", f"subject id {s.id!r} repeats")
        ids.add(s.id.lower())
    job_ref = _job_reference(job)
    if isinstance(job_ref, str):
        resolve_job(job_ref)  # fail here, once, rather than on every subject
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    csv_path = out / BATCH_CSV
    results: dict[str, SubjectResult] = {}
    todo: list[tuple[Subject, Path]] = []
    for s in subjects:
        dst = inside(out, s.id)
        if resume and is_complete(dst):
            results[s.id] = SubjectResult(s.id, "skipped", 0.0, "", str(dst))
        else:
            todo.append((s, dst))
            # staging folders left by a worker killed mid-job (the runner's and the job's nested one)
            for stale in [*out.glob(f".{s.id}.staging-*"), *out.glob(f"..{s.id}.staging-*")]:
                shutil.rmtree(stale, ignore_errors=True)

    def ordered():
        return [results[s.id] for s in subjects if s.id in results]

    write_batch_csv(csv_path, ordered())
    if console is None:
        from rich.console import Console

        console = Console(stderr=True)
    n_workers = 0
    t0 = t1 = time.perf_counter()
    if todo:
        from distributed import as_completed

        with _quiet_dask(), dask_client(scheduler, workers) as client:
            n_workers = len(client.nthreads())
            t0 = time.perf_counter()
            futures = {}
            for s, dst in todo:
                fut = client.submit(run_subject_task, s.id, str(s.path), str(dst), job_ref, job_kwargs,
                                    key=f"personalize-{s.id}-{uuid.uuid4().hex[:8]}", pure=False, retries=retries)
                futures[fut] = (s, dst)
            counts = {"ok": 0, "error": 0}
            with _progress(console, progress) as bar:
                task = bar.add_task("subjects", total=len(todo), status=f"{len(results)} skipped")
                for fut in as_completed(futures):
                    s, dst = futures[fut]
                    if fut.status == "finished":
                        r = SubjectResult(**fut.result())
                    else:
                        r = _failure_row(s, dst, fut)
                    results[s.id] = r
                    counts[r.status] += 1
                    write_batch_csv(csv_path, ordered())
                    bar.update(task, advance=1, description=s.id,
                               status=f"{counts['ok']} ok, {counts['error']} error, {len(subjects) - len(todo)} skipped")
                    fut.release()
            t1 = time.perf_counter()
    return BatchResult(tuple(ordered()), out, csv_path, time.perf_counter() - t_start, t1 - t0, n_workers)


def print_batch(result: BatchResult, console) -> None:
    """Print the batch's error rows and counts with rich."""
    from rich.table import Table

    errors = [r for r in result.results if r.status == "error"]
    if errors:
        t = Table(title="Subjects that failed")
        t.add_column("subject")
        t.add_column("error", overflow="fold")
        for r in errors:
            t.add_row(r.subject, r.error)
        console.print(t)
    c = result.counts
    console.print(f"{c['ok']} ok, {c['error']} error, {c['skipped']} skipped (already complete); "
                  f"table in {result.csv}")
