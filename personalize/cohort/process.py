"""One subject's job in a process of its own, started by the dask task on a worker.

A job that segfaults, calls ``os._exit`` or is killed for memory takes only its
own process down (`JobDied`, with what killed it), so its death is attributed to
that subject alone and the dask worker, with the subjects queued on it, lives
on.  The child is ``python -m personalize.cohort REQUEST.json``; it writes its
outcome (summary text, or the kind and message of the error) to a result file.
The job writes into a staging folder published as ``OUT/<subject>/`` only on
success, ``summary.json`` (the completion marker) last.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable

from lowerlimb.atomic import write_text
from lowerlimb.errors import FitError, InputError

from personalize.cohort.jobs import THREAD_ENV, JobDied, JobFailed, error_text, resolve_job, summary_text
from personalize.cohort.records import SUMMARY

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


def child_main(request: str) -> int:
    """Entry point of a job's own process: ``python -m personalize.cohort REQUEST.json``."""
    req = json.loads(Path(request).read_text(encoding="utf-8"))
    _watch_parent()
    res = Path(req["result"])
    try:
        fn = resolve_job(req["job"])
        out = {"status": "ok", "summary": summary_text(fn(Path(req["subject_dir"]), Path(req["out"]), **req["kwargs"]))}
    except InputError as exc:
        out = {"status": "input", "message": str(exc)}
    except FitError as exc:
        out = {"status": "fit", "message": str(exc)}
    except Exception as exc:
        out = {"status": "exception", "message": " ".join(f"{type(exc).__name__}: {exc}".split())}
    write_text(res, json.dumps(out))
    return 0


def remove_leftovers(out: Path, subject: str) -> None:
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
    from personalize.outputs import replaced_dir

    for k, v in THREAD_ENV.items():
        os.environ.setdefault(k, v)
    final = Path(out_dir)
    t0 = time.perf_counter()
    try:
        with replaced_dir(final) as stage:
            if _isolated(job, job_kwargs):
                text = _run_isolated(job, subject_dir, stage, job_kwargs)
            else:
                text = summary_text(resolve_job(job)(Path(subject_dir), stage, **(job_kwargs or {})))
            write_text(stage / SUMMARY, text)
    except (InputError, FitError) as exc:
        return {"subject": subject, "status": "error", "seconds": time.perf_counter() - t0,
                "error": error_text(exc), "output": str(final)}
    finally:
        remove_leftovers(final.parent, subject)
    return {"subject": subject, "status": "ok", "seconds": time.perf_counter() - t0, "error": "", "output": str(final)}

