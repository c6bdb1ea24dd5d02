"""Per-subject jobs: named by dotted path, resolved on the worker, their summaries encoded as JSON text.

A job is ``job(subject_dir: Path, out: Path, **kwargs) -> dict`` (the subject's
summary); module-level functions travel by name (``pkg.module:func``) and are
imported where they run.
"""
from __future__ import annotations

import importlib
import json
from pathlib import Path
from typing import Any, Callable

from lowerlimb.errors import FitError, InputError

#: environment of worker processes: one thread per BLAS/OpenMP pool
THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "VECLIB_MAXIMUM_THREADS": "1", "NUMEXPR_NUM_THREADS": "1", "MPLBACKEND": "Agg"}



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


def job_reference(job: str | Callable) -> str | Callable:
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


def error_text(exc: BaseException) -> str:
    kind = "input error" if isinstance(exc, InputError) else "fit error" if isinstance(exc, FitError) else "error"
    return " ".join(f"{kind}: {exc}".split())  # one line


class JobDied(RuntimeError):
    """The process running a subject's job died (signal, ``os._exit``, out of memory) before returning."""


class JobFailed(RuntimeError):
    """A subject's job raised an unexpected exception (not `InputError`/`FitError`) in its process."""


def summary_text(summary) -> str:
    if not isinstance(summary, dict):
        raise TypeError(f"the job returned {type(summary).__name__}, expected the summary dict")
    return json.dumps(summary, indent=1, default=_json_default, allow_nan=True) + "\n"


