"""Fan independent tasks out and hand each result back, in the calling process, as it
arrives: in this process (``workers=1``), over a local process pool (default, spawned
workers, so no state leaks in from the parent), or over ``dask.distributed`` (a ``Client``
or a scheduler address). The caller writes each result as it comes (see
``store``), so a crash loses only the tasks in flight.
"""
from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor, as_completed

from tqdm.auto import tqdm


def run_tasks(fn, tasks: dict, on_result, *, shared=None, scheduler=None, workers: int = 2,
              progress: bool = True, label: str = "realisations") -> None:
    """Call ``fn(shared, *args)`` for each ``key: args`` of ``tasks`` and ``on_result(key,
    value)`` here as each finishes (in completion order). ``shared`` is sent once per worker
    where the engine allows (Dask: scattered). An exception in a task propagates after the
    results already received were handed on."""
    check_workers(workers)
    bar = tqdm(total=len(tasks), desc=label, disable=not progress)
    try:
        if not tasks:
            return
        if scheduler is not None:
            _dask(fn, tasks, on_result, shared, scheduler, bar)
        elif workers == 1:
            for key, args in tasks.items():
                on_result(key, fn(shared, *args))
                bar.update()
        else:
            _pool(fn, tasks, on_result, shared, workers, bar)
    finally:
        bar.close()


def check_workers(workers) -> None:
    if not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")


_SHARED = {}


def _keep(shared):
    _SHARED["value"] = shared


def _call(fn, *args):
    return fn(_SHARED["value"], *args)


def _pool(fn, tasks, on_result, shared, workers, bar):
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(min(workers, len(tasks)), mp_context=context,
                             initializer=_keep, initargs=(shared,)) as pool:
        futures = {pool.submit(_call, fn, *args): key for key, args in tasks.items()}
        try:
            for future in as_completed(futures):
                on_result(futures[future], future.result())
                bar.update()
        except BaseException:
            pool.shutdown(wait=False, cancel_futures=True)
            raise


def _dask(fn, tasks, on_result, shared, scheduler, bar):
    try:
        from distributed import Client, as_completed as dask_completed
    except ImportError as e:  # pragma: no cover - the extra is part of dev
        raise ImportError("a Dask scheduler needs dask.distributed: pip install 'bayespd[dask]'") from e
    own = not isinstance(scheduler, Client)
    client = Client(scheduler) if own else scheduler
    try:
        remote = client.scatter(shared, broadcast=True) if shared is not None else None
        futures = {client.submit(fn, remote, *args, pure=False): key for key, args in tasks.items()}
        try:
            for future in dask_completed(futures):
                on_result(futures[future], future.result())
                bar.update()
                future.release()
        except BaseException:
            client.cancel(list(futures))
            raise
    finally:
        if own:
            client.close()
