"""Progress a person can read: step N of M, elapsed time and an estimate of the time left.

On a terminal a rich bar is redrawn in place; when stderr is not a terminal
(piped to a file, a CI log, a batch scheduler) each step is one plain line::

    run [ 5/18]   0:12 elapsed, ~0:31 left  detecting landmarks

The estimate assumes the remaining steps take as long on average as the
finished ones; the step count is an estimate too when the number of steps is
only known as the work goes (``~M``), and grows if the work outruns it.

`BatchProgress` shows a batch the same way, one subject at a time::

    batch [2/5] 0:41 elapsed, ~1:02 left  s2: ok; 2 ok, 0 error, 0 skipped

Both draw on a rich Console the command gives them (stderr); they are the only
library objects that write to the terminal, and only when asked to.
"""
from __future__ import annotations

import time


def _clock(seconds: float) -> str:
    s = int(round(max(seconds, 0.0)))
    h, rem = divmod(s, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class StepProgress:
    """Context manager; call it (``progress(message)``) at the start of each step.

    Parameters
    ----------
    name : shown first (the command)
    total : expected number of steps (an estimate is fine)
    console : rich Console (stderr); quiet consoles show nothing
    exact : whether `total` is exact (else shown as ``~M``)
    """

    def __init__(self, name: str, total: int, console, *, exact: bool = False):
        self.name, self.total, self.console, self.exact = name, max(int(total), 1), console, exact
        self.done = 0
        self.t0 = time.perf_counter()
        self._live = None
        self._task = None

    # ------------------------------------------------------------------ text
    def _estimate(self) -> str:
        el = time.perf_counter() - self.t0
        if self.done <= 1:
            return f"{_clock(el)} elapsed"
        left = el / (self.done - 1) * (self.total - self.done + 1)
        return f"{_clock(el)} elapsed, ~{_clock(left)} left"

    def line(self, message: str) -> str:
        width = len(str(self.total))
        tot = f"{'' if self.exact else '~'}{self.total}"
        return f"{self.name} [{self.done:>{width}}/{tot}] {self._estimate():>26}  {message}"

    # ------------------------------------------------------------------ protocol
    def __enter__(self) -> "StepProgress":
        if not self.console.quiet and self.console.is_terminal:
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

            self._live = Progress(TextColumn(f"[bold]{self.name}[/bold]"), BarColumn(),
                                  TextColumn("step {task.completed:.0f} of {task.fields[tot]}"), TimeElapsedColumn(),
                                  TextColumn("~"), TimeRemainingColumn(), TextColumn("{task.description}"),
                                  console=self.console, transient=True)
            self._live.__enter__()
            self._task = self._live.add_task("starting", total=self.total, tot=self._tot())
        return self

    def _tot(self) -> str:
        return f"{'' if self.exact else '~'}{self.total}"

    def __call__(self, message: str) -> None:
        self.done += 1
        if self.done > self.total:
            self.total = self.done + max(1, self.total // 10)
        if self.console.quiet:
            return
        if self._live is not None:
            self._live.update(self._task, completed=self.done - 1, total=self.total, tot=self._tot(),
                              description=message)
        else:
            self.console.print(self.line(message), markup=False, highlight=False, soft_wrap=True)

    def __exit__(self, *exc) -> None:
        if self._live is not None:
            self._live.__exit__(*exc)
        if exc[0] is None and not self.console.quiet:
            self.console.print(f"{self.name}: {self.done} steps in {_clock(time.perf_counter() - self.t0)}",
                               markup=False, highlight=False)


class BatchProgress:
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

    def advance(self, subject: str, r, status: str) -> None:
        """One subject done: `r` is its `personalize.cohort.SubjectResult`, `status` the running counts."""
        self.done += 1
        if self.bar is not None:
            self.bar.update(self.task, advance=1, description=subject, status=status)
        elif self.enabled:
            el = time.perf_counter() - self.t0
            left = el / self.done * (self.total - self.done)
            self.console.print(f"batch [{self.done}/{self.total}] {_clock(el)} elapsed, ~{_clock(left)} left  "
                               f"{subject}: {r.status}{(' (' + r.error + ')') if r.error else ''}; {status}",
                               markup=False, highlight=False, soft_wrap=True)
