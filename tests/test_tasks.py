"""lowerlimb.tasks.run_tasks: dependencies respected, priority order on one thread, errors and cycles raised."""
import threading
import time

import pytest

from lowerlimb.tasks import run_tasks


def test_dependencies_finish_before_their_dependants_on_any_number_of_threads():
    for workers in (1, 2, 3):
        log, lock = [], threading.Lock()

        def task(name, dt):
            def fn():
                time.sleep(dt)
                with lock:
                    log.append(name)
            return fn
        g = {"c": (("a", "b"), task("c", 0.0)), "a": ((), task("a", 0.02)), "b": (("a",), task("b", 0.0)),
             "d": (("absent",), task("d", 0.01))}
        run_tasks(g, workers=workers)
        assert sorted(log) == ["a", "b", "c", "d"]
        assert log.index("a") < log.index("b") < log.index("c")


def test_one_thread_runs_ready_tasks_in_the_order_listed():
    log = []
    g = {n: (deps, lambda n=n: log.append(n)) for n, deps in
         [("x", ("z",)), ("y", ()), ("z", ()), ("w", ("y",))]}
    run_tasks(g, workers=1)
    # y and z ready at the start (y listed first); then x (listed before w) once z is done
    assert log == ["y", "z", "x", "w"]


def test_a_task_error_and_a_cycle_are_raised():
    def boom():
        raise RuntimeError("bad bone")
    with pytest.raises(RuntimeError, match="bad bone"):
        run_tasks({"a": ((), boom), "b": (("a",), lambda: None)})
    with pytest.raises(ValueError, match="cycle"):
        run_tasks({"a": (("b",), lambda: None), "b": (("a",), lambda: None)})
