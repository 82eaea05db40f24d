"""bayespd/ensemble/execution.py: tasks fanned out and every result handed back once, in this
process or over a spawned process pool, with the shared value; errors propagate after the
results already received."""
import pytest

from bayespd.ensemble.execution import check_workers, run_tasks


def power(shared, base, exponent):
    """A task: base ** exponent + the shared offset (module level: it pickles)."""
    if base < 0:
        raise ArithmeticError(f"negative base {base}")
    return base**exponent + shared["offset"]


TASKS = {f"t{k}": (k, 2) for k in range(6)}
EXPECTED = {f"t{k}": k**2 + 10 for k in range(6)}


def test_serial_run_hands_each_result_back_in_order():
    got = []
    run_tasks(power, TASKS, lambda key, value: got.append((key, value)), shared={"offset": 10},
              workers=1, progress=False)
    assert got == list(EXPECTED.items())


@pytest.mark.slow
def test_process_pool_gives_the_serial_results():
    """Two spawned workers (each imports bayespd and torch: 5-20 s on busy cores): every
    task once, the same values; the order is the completion order, so only the set is
    compared."""
    got = {}
    run_tasks(power, TASKS, lambda key, value: got.setdefault(key, value), shared={"offset": 10},
              workers=2, progress=False)
    assert got == EXPECTED


def test_an_error_propagates_after_the_results_before_it():
    """Serially: the results before the failing task were handed on; the task's exception
    is raised unchanged; no task after it runs."""
    got = {}
    tasks = {"a": (1, 2), "b": (-1, 2), "c": (3, 2)}
    with pytest.raises(ArithmeticError, match="negative base -1"):
        run_tasks(power, tasks, lambda key, value: got.setdefault(key, value), shared={"offset": 0},
                  workers=1, progress=False)
    assert got == {"a": 1}


def test_no_tasks_and_bad_worker_counts():
    got = []
    run_tasks(power, {}, lambda *a: got.append(a), workers=3, progress=False)
    assert got == []
    for bad in (0, -1, 1.5, "2"):
        with pytest.raises(ValueError, match="workers must be a positive integer"):
            check_workers(bad)
        with pytest.raises(ValueError, match="workers must be a positive integer"):
            run_tasks(power, TASKS, lambda *a: None, workers=bad, progress=False)
