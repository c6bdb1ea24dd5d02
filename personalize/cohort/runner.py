"""The dask side of a batch: a cluster, one task per subject, results as they complete.

`run_batch` validates the subjects, skips complete ones (resumption), submits
the rest (`personalize.cohort.process.run_subject_task`) and rewrites
``batch.csv`` after every completed subject; SIGINT / SIGTERM cancel the
remaining subjects and raise `lowerlimb.errors.Interrupted`.
"""
from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time
import uuid
import warnings
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

from lowerlimb.atomic import inside
from lowerlimb.errors import FitError, InputError

from personalize.cohort.jobs import THREAD_ENV, JobDied, JobFailed, error_text, job_reference, resolve_job
from personalize.cohort.process import remove_leftovers, run_subject_task
from personalize.cohort.records import (BATCH_CSV, DEFAULT_JOB, SUMMARY, BatchResult, Subject, SubjectResult,
                                        check_subject_id, is_complete, read_manifest, write_batch_csv)
from personalize.progress import BatchProgress


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
        msg = error_text(exc)
    else:
        msg = f"internal error ({type(exc).__name__}: {exc}) after {attempts} attempt(s)"
    return SubjectResult(s.id, "error", float("nan"), " ".join(msg.split()), str(dst))



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
    job_ref = job_reference(job)
    if isinstance(job_ref, str):
        resolve_job(job_ref)  # fail here, once, rather than on every subject
    from personalize.outputs import check_output_dir

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
            remove_leftovers(out, s.id)  # left by a batch killed mid-job

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
                    remove_leftovers(out, s.id)
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
            with BatchProgress(console, progress, len(todo), n_skipped) as bar:
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

