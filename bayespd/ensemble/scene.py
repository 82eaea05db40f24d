"""A fracture scene for posterior-predictive ensembles, and one realisation of it.

A ``FractureScene`` says how a parameter draw becomes a stochastic fracture run (Dodwell 2019
eq 4 with the damage law of eq 2 or 5, ``bayespd.solvers.fracture``) and what to measure:

* ``build(params) -> StochasticFracture``: a picklable callable (a module-level function or
  a ``functools.partial`` of one) taking ``{name: float}`` for the names in ``params``;
* ``load_factors`` and ``dt`` of the run (the same for every realisation); ``x`` the
  particle positions (N, 2) of the body ``build`` makes (for the maps);
* ``origin`` and ``direction`` (2D): the line the crack is expected to follow; crack paths
  are read as their offset across it at stations along it (the credible band);
* ``failure_length``: failure is the load factor at which the crack first reaches this
  length (under Brownian forcing the reaction is too noisy for its peak to locate failure);
  ``load_component``: the reaction component reported as the load (None: its norm);
* ``observed_path``: an observed crack polyline (k, 2) to overlay, or None;
* ``tangent`` and ``max_rank``: the operator of the steps, "exact" or "lagged", and the
  largest Woodbury update of its factor; ``zone``: a mask of the particles where cracks may
  run, ordered last in that factor (``StochasticFracture.run``), or None.
"""
from __future__ import annotations

import contextlib
import gc
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from bayespd import linalg
from bayespd.damage import crack_length
from bayespd.ensemble.heap import keep_temporaries_on_heap
from bayespd.solvers.fracture import check_tangent
from bayespd.validate import in_range
from bayespd.linalg.lockstep import LockStep


@dataclass(frozen=True)
class FractureScene:
    build: Callable
    params: tuple
    load_factors: np.ndarray
    dt: float
    x: np.ndarray
    origin: tuple = (0.0, 0.0)
    direction: tuple = (1.0, 0.0)
    failure_length: float | None = None
    load_component: int | None = None
    threshold: float = 0.4
    path_threshold: float = 0.4
    hold: bool = True
    max_steps: int | None = None
    tangent: str = "exact"
    max_rank: int = 512
    observed_path: np.ndarray | None = None
    zone: np.ndarray | None = None
    attrs: dict = field(default_factory=dict)

    def __post_init__(self):
        if not callable(self.build):
            raise ValueError("build must be a callable params -> StochasticFracture")
        lams = np.asarray(self.load_factors, dtype=np.float64)
        if lams.ndim != 1 or len(lams) == 0 or not np.all(np.isfinite(lams)):
            raise ValueError("load_factors must be a non-empty 1D array of finite numbers")
        if not self.dt > 0:
            raise ValueError(f"dt must be positive, got {self.dt}")
        d = np.asarray(self.direction, dtype=np.float64)
        if d.shape != (2,) or not np.linalg.norm(d) > 0 or np.shape(self.origin) != (2,):
            raise ValueError("origin and direction must be 2D points/vectors (the crack band is "
                             "measured across a line in the plane), direction non-zero")
        check_tangent(self.tangent)
        for name in ("threshold", "path_threshold"):
            in_range(name, getattr(self, name), 0.0, 1.0, "it is a damage index phi", closed=(False, False))
        x = np.asarray(self.x, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != 2:
            raise ValueError(f"x must be the (N, 2) particle positions, got shape {x.shape}")
        if self.zone is not None:
            if np.shape(self.zone) != (len(x),):
                raise ValueError(f"zone must be a mask of the {len(x)} particles, got shape {np.shape(self.zone)}")
            object.__setattr__(self, "zone", np.asarray(self.zone, dtype=bool))
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "load_factors", lams)
        object.__setattr__(self, "direction", tuple(d / np.linalg.norm(d)))
        object.__setattr__(self, "params", tuple(self.params))


BATCH = 8  # realisations a task runs in lock-step, and the columns of every block solve they share


def realise(scene: FractureScene, params: dict, seed: int, device=None) -> dict:
    """One realisation (``realise_batch`` of one: the same bits as in any batch, its solves
    in blocks of BATCH columns as there, so alone it takes longer than its share of a batch);
    raises what the run raised."""
    (out,) = realise_batch(scene, [(params, seed)], device)
    if isinstance(out, BaseException):
        raise out
    return out


def realise_batch(scene: FractureScene, items: list, device=None) -> list:
    """Realisations ``items = [(params, seed), ...]``, run in lock-step (``linalg.lockstep``,
    BATCH columns to a solve, whatever the company: each gives the bits it gives alone), each
    built at its ``params``, with Brownian seed ``seed``, under ``torch.device(device)``
    (default CPU). One torch and one BLAS thread in every BLAS library loaded (numpy's,
    scipy's, CHOLMOD's: the result is the same bit for bit in any process or worker, and
    workers sharing the cores do not oversubscribe them), and large temporaries kept on the
    heap where the worker's environment fixed glibc's thresholds (Dask's,
    ``bayespd.ensemble.heap``). Returns, per item, float64 / int64 numpy arrays (see
    ``Realisation``) plus the derived peak load, failure load factor, first-failure time and
    final crack length, and its share of the batch's wall and CPU time; or the exception its
    run raised."""
    if not items:
        return []
    keep_temporaries_on_heap()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    start, cpu = time.perf_counter(), time.process_time()

    def job(params, seed):
        def run():
            with contextlib.nullcontext() if device in (None, "cpu") else torch.device(device):
                return scene.build({k: float(params[k]) for k in scene.params}).run(
                    scene.load_factors, scene.dt, seed=int(seed), hold=scene.hold,
                    max_steps=scene.max_steps, path_threshold=scene.path_threshold, tangent=scene.tangent,
                    max_rank=scene.max_rank, zone=scene.zone)
        return run

    try:
        # one thread for CHOLMOD's BLAS too: its sums depend on the thread count
        with threadpool_limits(1), linalg.settings(factor_threads=1):
            runs = LockStep(BATCH).run([job(params, seed) for params, seed in items])
    finally:
        torch.set_num_threads(threads)
        gc.collect()  # factors held in closures are cyclic garbage: free them before the next run
    share = {"wall_time_s": (time.perf_counter() - start) / len(items),
             "cpu_time_s": (time.process_time() - cpu) / len(items)}  # this process's CPU: load-independent
    return [run if isinstance(run, BaseException) else {**_outcomes(scene, run), **share} for run in runs]


def _outcomes(scene: FractureScene, run) -> dict:
    reaction = np.asarray(run.reaction, dtype=np.float64)
    load = (np.linalg.norm(reaction, axis=1) if scene.load_component is None
            else reaction[:, scene.load_component])
    k = int(np.argmax(np.abs(load)))
    first = run.first_failure
    failure = np.nan
    if scene.failure_length is not None:
        reached = np.flatnonzero(run.crack_length >= scene.failure_length)
        failure = float(run.load_factor[reached[0]]) if len(reached) else np.nan
    return {
        "t": np.asarray(run.t, np.float64), "load_factor": np.asarray(run.load_factor, np.float64),
        "reaction": reaction, "broken": np.asarray(run.broken, np.int64),
        "crack_length": np.asarray(run.crack_length, np.float64),
        "phi": np.asarray(run.phi, np.float64), "path": np.asarray(run.path, np.float64),
        "peak_load": np.float64(load[k]), "peak_load_factor": np.float64(run.load_factor[k]),
        "failure_load_factor": np.float64(failure),
        "first_failure_time": np.float64(np.nan if first is None else run.t[first]),
        "final_crack_length": np.float64(crack_length(run.path)),
        "device": np.str_(str(run.u.device)), "u_dtype": np.str_(str(run.u.dtype)),
    }
