"""A dependency graph of callables run on a few threads, earliest-listed ready task first.

Written here rather than taken from dask: the graphs are a dozen tasks of 5-300 ms on in-memory arrays
(numpy releases the GIL), where a dask scheduler's per-task overhead and its copies would cost more than
the parallelism gains.  The order of the graph is the priority (list the longest chain first); which
thread runs a task never changes what it computes, so results are those of a sequential run in any
topological order.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait

__all__ = ["run_tasks"]


def run_tasks(tasks: Mapping[str, tuple[tuple[str, ...], Callable[[], object]]], workers: int = 2) -> None:
    """Run every task once its dependencies have finished, at most `workers` at a time.

    Parameters
    ----------
    tasks : name -> (dependencies, callable), in priority order; a dependency
        that is not a task name counts as finished
    workers : threads

    Raises
    ------
    ValueError
        If the dependencies form a cycle.
    Exception
        The first exception a task raised (the running ones are finished first).
    """
    pending = {name: tuple(d for d in deps if d in tasks) for name, (deps, _) in tasks.items()}
    done: set[str] = set()
    running: dict = {}
    with ThreadPoolExecutor(max_workers=max(1, int(workers))) as pool:
        while pending or running:
            for name in [n for n, deps in pending.items() if done.issuperset(deps)]:
                if len(running) >= workers:
                    break
                del pending[name]
                running[pool.submit(tasks[name][1])] = name
            if not running:
                raise ValueError(f"task dependencies form a cycle among {', '.join(pending)}")
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for fut in finished:
                fut.result()
                done.add(running.pop(fut))
