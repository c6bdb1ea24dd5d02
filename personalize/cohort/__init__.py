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
  (``python -m personalize.cohort``, `personalize.cohort.process`): a job that segfaults, calls ``os._exit``
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

Modules: `records` (manifest, per-subject results, ``batch.csv``), `jobs` (jobs by
dotted path), `process` (a subject's job in a process of its own), `runner` (dask).

>>> from personalize.cohort import run_batch
>>> result = run_batch("cohort/manifest.csv", "results", workers=2)
>>> result.counts
{'ok': 3, 'error': 1, 'skipped': 0}
"""
from __future__ import annotations

from personalize.cohort.records import (DEFAULT_JOB, BatchResult, Subject, SubjectResult, read_batch_csv, read_manifest,
                                        write_manifest)
from personalize.cohort.runner import run_batch

__all__ = ["DEFAULT_JOB", "BatchResult", "Subject", "SubjectResult", "read_batch_csv", "read_manifest",
           "write_manifest", "run_batch"]
