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
* runs each subject's job in a process of its own, started by the dask task
  (``python -m personalize.cohort``): a job that segfaults, calls ``os._exit``
  or is killed for memory takes only its own process down, so its death is
  attributed to that subject alone and the dask worker (and the subjects
  queued on it) never dies;
* records a bad subject (`InputError`, `FitError`) as an error row while the
  others go on; other exceptions and dead job processes are retried
  (``retries``), then reported with what killed the process (signal or exit code);
* rewrites ``OUT/batch.csv`` (subject, status ok|error|skipped, seconds, error,
  output) atomically after every completed subject, so an interrupted batch
  still says what is done; staging folders are removed;
* stops on SIGINT (Ctrl-C) or SIGTERM by cancelling the remaining subjects
  and raising `lowerlimb.errors.Interrupted` (the CLI exits 130 / 143); a
  rerun resumes from the complete subjects.

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
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Sequence

from lowerlimb.atomic import inside, write_text
from lowerlimb.errors import FitError, InputError

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


class JobDied(RuntimeError):
    """The process running a subject's job died (signal, ``os._exit``, out of memory) before returning."""


class JobFailed(RuntimeError):
    """A subject's job raised an unexpected exception (not `InputError`/`FitError`) in its process."""


def _summary_text(summary) -> str:
    if not isinstance(summary, dict):
        raise TypeError(f"the job returned {type(summary).__name__}, expected the summary dict")
    return json.dumps(summary, indent=1, default=_json_default, allow_nan=True) + "\n"


def _isolated(job, job_kwargs) -> bool:
    """Whether the job can run in a process of its own (named by module path, JSON keyword arguments)."""
    if not isinstance(job, str):
        return False
    try:
        json.dumps(job_kwargs or {})
    except (TypeError, ValueError):
        return False
    return True


def _death_text(code: int, log: Path) -> str:
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        what = f"killed by {name}" + (" (a crash in native code)" if -code in (signal.SIGSEGV, signal.SIGBUS, signal.SIGABRT)
                                      else " (out of memory?)" if -code == signal.SIGKILL else "")
    else:
        what = f"exited with code {code} without a result"
    tail = ""
    try:
        lines = [ln for ln in log.read_text(encoding="utf-8", errors="replace").splitlines() if ln.strip()]
        if lines:
            tail = f"; last output: {lines[-1].strip()[:200]}"
    except OSError:
        pass
    return f"the job's process {what}{tail}"


def _run_isolated(job: str, subject_dir: str, stage: Path, job_kwargs: dict | None) -> str:
    """Run the job in a child process; returns the summary text, raises InputError/FitError/JobFailed/JobDied."""
    tmp = Path(tempfile.mkdtemp(prefix="personalize-job-"))
    try:
        req, res, log = tmp / "request.json", tmp / "result.json", tmp / "output.log"
        req.write_text(json.dumps({"job": job, "subject_dir": subject_dir, "out": str(stage),
                                   "kwargs": job_kwargs or {}, "result": str(res)}), encoding="utf-8")
        env = dict(os.environ)
        env.update({k: env.get(k, v) for k, v in THREAD_ENV.items()})
        env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
        with open(log, "wb") as lf:
            # a session of its own: a Ctrl-C at the terminal reaches the batch, which stops the jobs itself
            proc = subprocess.Popen([sys.executable, "-m", "personalize.cohort", str(req)], stdin=subprocess.DEVNULL,
                                    stdout=lf, stderr=subprocess.STDOUT, env=env, start_new_session=True)
            try:
                code = proc.wait()
            except BaseException:
                proc.kill()
                proc.wait()
                raise
        try:
            out = json.loads(res.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            raise JobDied(_death_text(code, log)) from None
        if out["status"] == "ok":
            return out["summary"]
        if out["status"] == "input":
            raise InputError(None, out["message"])
        if out["status"] == "fit":
            raise FitError(out["message"])
        raise JobFailed(out["message"])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _watch_parent() -> None:
    """Exit when the parent (the dask worker) is gone: an orphaned job must not run on."""
    parent = os.getppid()

    def watch():
        while True:
            time.sleep(0.5)
            if os.getppid() != parent:
                os._exit(143)

    threading.Thread(target=watch, daemon=True).start()


def _child_main(request: str) -> int:
    """Entry point of a job's own process: ``python -m personalize.cohort REQUEST.json``."""
    req = json.loads(Path(request).read_text(encoding="utf-8"))
    _watch_parent()
    res = Path(req["result"])
    try:
        fn = resolve_job(req["job"])
        out = {"status": "ok", "summary": _summary_text(fn(Path(req["subject_dir"]), Path(req["out"]), **req["kwargs"]))}
    except InputError as exc:
        out = {"status": "input", "message": str(exc)}
    except FitError as exc:
        out = {"status": "fit", "message": str(exc)}
    except Exception as exc:
        out = {"status": "exception", "message": " ".join(f"{type(exc).__name__}: {exc}".split())}
    write_text(res, json.dumps(out))
    return 0


def _remove_leftovers(out: Path, subject: str) -> None:
    """Staging and set-aside folders of `subject` left by a job that died (the runner's and the job's nested ones)."""
    for pat in (f".{subject}.staging-*", f"..{subject}.staging-*", f".{subject}.old-*", f"..{subject}.staging-*.old-*"):
        for stale in out.glob(pat):
            shutil.rmtree(stale, ignore_errors=True)


def run_subject_task(subject: str, subject_dir: str, out_dir: str, job: str | Callable,
                     job_kwargs: dict | None = None) -> dict:
    """Run one subject on a worker; returns a `SubjectResult` as a dict.

    The job runs in a process of its own (see the module docstring; a job given
    as a callable that cannot be named by module path runs in the worker) and
    writes into a staging folder that replaces `out_dir` whole only on success,
    with the returned summary as ``summary.json`` (so its presence means the
    subject is complete).  `InputError` and `FitError` (deterministic, caused by
    the subject) become an error result; an unexpected exception (`JobFailed`)
    or a dead job process (`JobDied`) propagates so that dask retries the task.
    """
    from .outputs import replaced_dir

    for k, v in THREAD_ENV.items():
        os.environ.setdefault(k, v)
    final = Path(out_dir)
    t0 = time.perf_counter()
    try:
        with replaced_dir(final) as stage:
            if _isolated(job, job_kwargs):
                text = _run_isolated(job, subject_dir, stage, job_kwargs)
            else:
                text = _summary_text(resolve_job(job)(Path(subject_dir), stage, **(job_kwargs or {})))
            write_text(stage / SUMMARY, text)
    except (InputError, FitError) as exc:
        return {"subject": subject, "status": "error", "seconds": time.perf_counter() - t0,
                "error": _error_text(exc), "output": str(final)}
    finally:
        _remove_leftovers(final.parent, subject)
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
        # the worker processes ignore SIGINT (inherited across their exec): a Ctrl-C at the terminal reaches the
        # whole process group, and the batch, not each worker with its traceback, stops the work
        main = threading.current_thread() is threading.main_thread()
        old = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
        try:
            with dask.config.set({"distributed.nanny.pre-spawn-environ": pre_spawn}), warnings.catch_warnings():
                warnings.filterwarnings("ignore", message="Port .* is already in use")
                cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                                       dashboard_address=None, silence_logs=logging.ERROR)
        finally:
            if old is not None:
                signal.signal(signal.SIGINT, old)
        client = Client(cluster)
        try:
            yield client
        finally:
            client.close()
            cluster.close()
    finally:
        os.environ.clear()
        os.environ.update(saved_env)


def _failure_row(s: Subject, dst: Path, fut, attempts: int, started_ns: int) -> SubjectResult:
    """The row of a subject whose task failed; a subject found complete (written during this run) is ok."""
    if is_complete(dst) and (dst / SUMMARY).stat().st_mtime_ns >= started_ns:
        return SubjectResult(s.id, "ok", float("nan"), "", str(dst))
    try:
        exc = fut.exception()
    except BaseException as cancelled:  # a cancelled future (scheduler lost) raises instead of returning
        exc = cancelled
    if isinstance(exc, JobDied):
        msg = f"{exc}, on {'each of ' + str(attempts) + ' attempts' if attempts > 1 else 'its only attempt'}"
    elif isinstance(exc, JobFailed):
        msg = f"internal error ({exc}) after {attempts} attempt(s)"
    elif type(exc).__name__ == "KilledWorker":
        msg = "the dask worker running this subject died on every attempt (out of memory?)"
    elif isinstance(exc, (InputError, FitError)):
        msg = _error_text(exc)
    else:
        msg = f"internal error ({type(exc).__name__}: {exc}) after {attempts} attempt(s)"
    return SubjectResult(s.id, "error", float("nan"), " ".join(msg.split()), str(dst))


class _BatchProgress:
    """Subjects done of N, elapsed, estimate: a rich bar on a terminal, one plain line per subject otherwise."""

    def __init__(self, console, enabled: bool, total: int, skipped: int):
        self.console, self.enabled, self.total, self.done = console, enabled, total, 0
        self.t0 = time.perf_counter()
        self.bar = None
        if enabled and console.is_terminal:
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                                       TimeRemainingColumn)

            self.bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                                TimeRemainingColumn(), TextColumn("{task.fields[status]}"), console=console,
                                transient=False)
            self.task = self.bar.add_task("subjects", total=total, status=f"{skipped} skipped")

    def __enter__(self):
        if self.bar is not None:
            self.bar.__enter__()
        return self

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.__exit__(*exc)

    def advance(self, subject: str, r: SubjectResult, status: str) -> None:
        self.done += 1
        if self.bar is not None:
            self.bar.update(self.task, advance=1, description=subject, status=status)
        elif self.enabled:
            from .progress import _clock

            el = time.perf_counter() - self.t0
            left = el / self.done * (self.total - self.done)
            self.console.print(f"batch [{self.done}/{self.total}] {_clock(el)} elapsed, ~{_clock(left)} left  "
                               f"{subject}: {r.status}{(' (' + r.error + ')') if r.error else ''}; {status}",
                               markup=False, highlight=False, soft_wrap=True)


def _progress(console, enabled: bool, total: int, skipped: int) -> _BatchProgress:
    return _BatchProgress(console, enabled, total, skipped)


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
    from .outputs import check_output_dir

    out = Path(out)
    # a batch folder is resumed, never replaced: only its kind, its place and that it can be written are checked
    check_output_dir(out, inputs=[s.path for s in subjects], overwrite=True)
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
            _remove_leftovers(out, s.id)  # left by a batch killed mid-job

    def ordered():
        return [results[s.id] for s in subjects if s.id in results]

    write_batch_csv(csv_path, ordered())
    if console is None:
        from rich.console import Console

        console = Console(stderr=True)
    n_workers = 0
    t0 = t1 = time.perf_counter()
    started_ns = time.time_ns() - 1_000_000_000  # file times have coarse resolution on some file systems
    if todo:
        from lowerlimb.errors import Interrupted

        with _termination_raises(), _quiet_dask():
            try:
                n_workers, t0 = _run_todo(todo, subjects, results, ordered, csv_path, out, job_ref, job_kwargs,
                                          scheduler, workers, retries, progress, console, started_ns)
            except (KeyboardInterrupt, Interrupted) as exc:
                for s, _ in todo:
                    _remove_leftovers(out, s.id)
                done = sum(r.status in ("ok", "skipped") for r in results.values())
                sig = exc.signum if isinstance(exc, Interrupted) else signal.SIGINT
                raise Interrupted(sig, f": batch stopped; {out / BATCH_CSV} lists {len(results)} subject(s) "
                                       f"({done} complete); rerun the same command to resume") from None
        t1 = time.perf_counter()
    return BatchResult(tuple(ordered()), out, csv_path, time.perf_counter() - t_start, t1 - t0, n_workers)


@contextlib.contextmanager
def _termination_raises() -> Iterator[None]:
    """SIGTERM raises `Interrupted` (as SIGINT raises KeyboardInterrupt) while the batch runs, in the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    from lowerlimb.errors import Interrupted

    def handler(signum, frame):
        raise Interrupted(signum)

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _run_todo(todo, subjects, results, ordered, csv_path, out, job_ref, job_kwargs, scheduler, workers, retries,
              progress, console, started_ns):
    from distributed import as_completed

    with dask_client(scheduler, workers) as client:
        n_workers = len(client.nthreads())
        t0 = time.perf_counter()
        futures = {}
        try:
            for s, dst in todo:
                fut = client.submit(run_subject_task, s.id, str(s.path), str(dst), job_ref, job_kwargs,
                                    key=f"personalize-{s.id}-{uuid.uuid4().hex[:8]}", pure=False, retries=retries)
                futures[fut] = (s, dst)
            counts = {"ok": 0, "error": 0}
            n_skipped = len(subjects) - len(todo)
            with _progress(console, progress, len(todo), n_skipped) as bar:
                for fut in as_completed(futures):
                    s, dst = futures[fut]
                    try:
                        r = SubjectResult(**fut.result()) if fut.status == "finished" else \
                            _failure_row(s, dst, fut, retries + 1, started_ns)
                    except Exception:  # KilledWorker, a lost scheduler...: still this subject's row, never the batch's end
                        r = _failure_row(s, dst, fut, retries + 1, started_ns)
                    results[s.id] = r
                    counts[r.status] += 1
                    write_batch_csv(csv_path, ordered())
                    bar.advance(s.id, r, f"{counts['ok']} ok, {counts['error']} error, {n_skipped} skipped")
                    fut.release()
        except BaseException:
            for f in futures:
                f.cancel()
            raise
    return n_workers, t0


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


if __name__ == "__main__":  # a subject's job in a process of its own (see run_subject_task)
    sys.exit(_child_main(sys.argv[1]))
