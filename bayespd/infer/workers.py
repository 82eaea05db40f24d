"""Jobs in spawned worker processes, one process per job, that end with their parent and
report their faults instead of hanging.

* **A script without** ``if __name__ == "__main__":``: a spawned worker first re-runs the
  parent's main script, which (unguarded) starts the workers again. ``refuse_bootstrap``
  makes such a worker exit with ``GUARD_EXIT`` (the test is multiprocessing's own
  ``_check_not_importing_main``), and the parent raises ``MainGuardError`` saying to add the
  guard. Any other death before a job starts is a ``WorkerError`` too.
* **A killed worker**: its pipe closes without a result; the parent notes it, lets the other
  jobs finish when a rerun can reuse them (``finish_others``), and then raises ``WorkerError``
  naming the job (at once when ``finish_others`` is false). A job that raises sends its
  exception, which the parent re-raises at once.
* **A killed parent**: each worker dies with it, at once on Linux (``PR_SET_PDEATHSIG``) and
  everywhere by a thread that waits for the parent's sentinel to close.
"""

import ctypes
import multiprocessing
import os
import signal
import sys
import threading
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait

GUARD_EXIT = 75  # a worker that found itself re-running an unguarded main script
PARENT_GONE = 76  # a worker whose parent died


class WorkerError(RuntimeError):
    """A worker process died without a result."""


class MainGuardError(RuntimeError):
    """The main script has no ``if __name__ == "__main__":`` guard, so workers cannot start."""


def refuse_bootstrap() -> None:
    """Exit with ``GUARD_EXIT`` when called in a spawned worker that is still importing the
    parent's main script, i.e. from the unguarded top level of that script."""
    if getattr(multiprocessing.current_process(), "_inheriting", False):
        sys.exit(GUARD_EXIT)


def _die_with_parent() -> None:
    parent = multiprocessing.parent_process()
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != parent.pid:  # died before prctl took effect
        os._exit(PARENT_GONE)
    threading.Thread(target=lambda: (wait([parent.sentinel]), os._exit(PARENT_GONE)), daemon=True).start()


def _child(conn: Connection, work, args) -> None:
    _die_with_parent()
    conn.send(("started", os.getpid()))
    try:
        result = ("done", work(*args))
    except BaseException as e:  # sent to the parent, which re-raises it
        result = ("error", e)
    try:
        conn.send(result)
    except Exception as e:  # an exception that does not pickle
        conn.send(("error", RuntimeError(f"{type(result[1]).__name__}: {result[1]} (did not pickle: {e})")))


@dataclass
class _Running:
    process: multiprocessing.Process
    conn: Connection
    pid: int | None = None


def _how(exitcode: int) -> str:
    if exitcode is not None and exitcode < 0:
        return f"was killed by {signal.Signals(-exitcode).name}"
    return f"exited with code {exitcode}"


def _main_script() -> str:
    return getattr(sys.modules["__main__"], "__file__", None) or "the main script"


def _start_error(label: str, exitcode: int) -> Exception:
    if exitcode == GUARD_EXIT:
        return MainGuardError(
            f"the worker processes that run the chains re-run {_main_script()} on start, and its top "
            "level runs the fit again: put the script's work under `if __name__ == \"__main__\":` "
            "(see the README), or pass chains='sequential'")
    return WorkerError(f"the worker process of {label} {_how(exitcode)} while starting, before the "
                       "job began (its error is printed above): fix that, or pass chains='sequential'")


def run_in_processes(work, jobs: list, workers: int, labels: list[str], on_death, finish_others: bool) -> list:
    """``[work(*job) for job in jobs]``, each in its own spawned process, ``workers`` at a time.
    ``on_death(index, how)`` is the message of a job whose worker died after starting: raised
    as ``WorkerError`` at once, or after the other jobs ended if ``finish_others``; a job
    that raises stops all and re-raises. Workers still running on any exit are terminated."""
    refuse_bootstrap()
    ctx = multiprocessing.get_context("spawn")
    pending, running, results, dead = list(range(len(jobs))), {}, {}, []
    try:
        while pending or running:
            while pending and len(running) < workers:
                j = pending.pop(0)
                receive, send = ctx.Pipe(duplex=False)
                process = ctx.Process(target=_child, args=(send, work, jobs[j]), name=labels[j])
                process.start()
                send.close()
                running[j] = _Running(process, receive)
            wait([r.conn for r in running.values()])
            for j, r in list(running.items()):
                if not r.conn.poll():
                    continue
                try:
                    kind, value = r.conn.recv()
                except (EOFError, OSError):  # died without a result
                    r.process.join()
                    del running[j]
                    if r.pid is None:
                        raise _start_error(labels[j], r.process.exitcode) from None
                    dead.append(on_death(j, _how(r.process.exitcode)))
                    if not finish_others:
                        raise WorkerError(dead[0])
                    continue
                if kind == "started":
                    r.pid = value
                elif kind == "done":
                    results[j] = value
                    r.process.join()
                    del running[j]
                else:
                    raise value
        if dead:
            raise WorkerError("; ".join(dead))
        return [results[j] for j in range(len(jobs))]
    finally:
        _stop([r.process for r in running.values()])


def _stop(processes) -> None:
    for p in processes:
        p.terminate()
    for p in processes:
        p.join(5)
        if p.is_alive():
            p.kill()
            p.join()
