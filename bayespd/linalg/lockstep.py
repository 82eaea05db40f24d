"""Runs in lock-step: several jobs in one process share the half solves of one factor.

The runs of an ensemble (e.g. the realisations of a fracture ensemble) may start from one
factor per process (``trailing.shared``), each step of each doing one forward and one
backward half solve with it. A block of W columns costs little more than one column, so
``LockStep(W).run(jobs)`` runs the jobs as cooperative threads, one at a time: a job runs
until its next half solve of one vector (``TrailingFactor.forward`` / ``backward``, which
ask ``current()``) and waits; when every live job waits, the solves are done W columns to a
call (zeros fill a block) and the jobs resume in turn. As only one job runs at any time,
they may share bodies and caches, and nothing contends for the interpreter.

Bit for bit: a column's result does not depend on the other columns of its block or on its
place there, but it does depend on the block's width (BLAS-3 kernels add in another order
than BLAS-2 ones), so every solve of a lock-step run is done in blocks of exactly W columns:
a job gives the same bits alone as in any company (tests/linalg/test_lockstep.py).
"""
from __future__ import annotations

import threading
from typing import Callable

import numpy as np

_LOCAL = threading.local()


def current() -> "_Member | None":
    """The lock-step member running in this thread (None outside ``LockStep.run``)."""
    return getattr(_LOCAL, "member", None)


class _Member:
    """One job's thread: ``solve(key, fn, v)`` hands the vector v to the round and waits for
    fn's column of it; ``key`` groups the requests that share fn (a factor's half solve)."""

    def __init__(self, round_: "_Round", slot: int):
        self.round, self.slot = round_, slot
        self.turn = threading.Event()
        self.done = False

    def solve(self, key, fn: Callable, v: np.ndarray) -> np.ndarray:
        r = self.round
        r.pending[self.slot] = (key, fn, np.asarray(v, dtype=np.float64))
        self._yield()
        answer = r.answers.pop(self.slot)
        if isinstance(answer, BaseException):
            raise answer
        return answer

    def _yield(self):
        self.round.back.set()
        self.turn.wait()
        self.turn.clear()


class _Round:
    """The state of one ``LockStep.run``: the requests of the waiting jobs and their answers."""

    def __init__(self, width: int):
        self.width, self.back = width, threading.Event()
        self.pending, self.answers = {}, {}

    def solve_pending(self):
        groups = {}
        for slot in sorted(self.pending):
            key, fn, v = self.pending[slot]
            groups.setdefault(key, (fn, []))[1].append((slot, v))
        self.pending.clear()
        for fn, items in groups.values():
            for start in range(0, len(items), self.width):
                chunk = items[start:start + self.width]
                block = np.zeros((len(chunk[0][1]), self.width))
                for c, (_, v) in enumerate(chunk):
                    block[:, c] = v
                try:
                    out = fn(block)
                    for c, (slot, _) in enumerate(chunk):
                        self.answers[slot] = np.ascontiguousarray(out[:, c])
                except Exception as e:  # every job of the block sees the failure
                    for slot, _ in chunk:
                        self.answers[slot] = e


class LockStep:
    """Run jobs (callables without arguments) in lock-step, their shared half solves batched
    ``width`` columns at a time (module docstring)."""

    def __init__(self, width: int = 8):
        if not (isinstance(width, int) and width >= 1):
            raise ValueError(f"width must be a positive integer, got {width!r}")
        self.width = width

    def run(self, jobs: list) -> list:
        """Each job's return value, or the exception it raised, in the order of ``jobs``."""
        r = _Round(self.width)
        members = [_Member(r, slot) for slot in range(len(jobs))]
        results = [None] * len(jobs)

        def work(member, job):
            member.turn.wait()
            member.turn.clear()
            _LOCAL.member = member
            try:
                results[member.slot] = job()
            except BaseException as e:  # handed back, never lost in a thread
                results[member.slot] = e
            finally:
                member.done = True
                r.back.set()

        threads = [threading.Thread(target=work, args=(m, job), daemon=True) for m, job in zip(members, jobs)]
        for t in threads:
            t.start()
        live = members
        while live:
            for m in live:  # one at a time, until its next solve or its end
                m.turn.set()
                r.back.wait()
                r.back.clear()
            live = [m for m in live if not m.done]
            r.solve_pending()
        for t in threads:
            t.join()
        return results
