"""MCMC chains (NUTS / HMC): per-chain seeds, process-parallel chains, checkpoints.

**Seeds.** Chain ``c`` runs with ``pyro.set_rng_seed(seed + c)`` from a fresh kernel, so its
draws do not depend on how (or whether) the other chains run.

**Processes.** Pyro's own multi-chain mode uses ``cpu_count() - 1`` workers: one on a 2-core
machine, i.e. sequential chains. Here ``chains="auto"`` runs the chains in
``min(num_chains, usable cores)`` worker processes when that is at least 2 (our parent process
only waits, so it needs no core of its own) and the model and data pickle, else one after
another in this process. Workers are *spawned*, not forked: CHOLMOD's OpenMP (libgomp)
deadlocks in a forked child once the parent has factorised. A spawned worker receives the
chain's spec by pickle, so the model must be importable (a module-level function or an
instance of a module-level class); a closure (``models.elastic_plate`` returns one) runs
sequentially under ``"auto"`` and is refused under ``"processes"``. Each worker uses
``cores // workers`` intra-op and BLAS threads and the parent's default dtype. Draws are bit-identical
either way.

**Faults** (``bayespd.infer.workers``). A script that runs chains in processes without an
``if __name__ == "__main__":`` guard gets ``MainGuardError`` (its workers would re-run it);
a chain whose worker is killed gets ``WorkerError`` naming the chain, after the other chains
ended (with a checkpoint, a rerun then resumes it from its last file; without, at once);
workers end with their parent.

**Checkpoints.** With ``checkpoint=<dir>``, chain ``c`` writes ``<dir>/chain<c>.pt``
(atomically) at the end of warmup, every ``checkpoint_every`` draws and at the end: the draws
so far, their statistics, and the sampler state (position, adapted step size and inverse mass
matrix, torch / numpy / python RNG states), all read and restored through Pyro's public kernel
API (``step_size``, ``inverse_mass_matrix``, ``initial_params``, ``setup``). A rerun with the same settings
loads finished chains without sampling and continues unfinished ones from their last file:
the continued draws are bit-identical to an uninterrupted run's. A kill during warmup loses
that chain's warmup (the adaptation's running averages are not saved); it restarts from its
seed, so the result is still the same. A checkpoint carries the run's fingerprint
(``bayespd.infer.fingerprint``: kernel, its options, warmup, the chain's seed, the data, the
model's sites and start, the mass matrix seed); a run with another is refused with
``CheckpointMismatchError`` naming what differs. ``num_samples`` is not part of it: draw ``i``
does not depend on how many follow, so a finished chain serves a run of fewer draws and
continues for one of more.
"""

import math
import os
import pickle
import random
import threading
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pyro
import torch
from pyro.ops.integrator import register_exception_handler
from threadpoolctl import threadpool_limits
from tqdm.auto import tqdm

from bayespd.atomic import atomic_path
from bayespd.validate import count, in_range, positive, reading
from bayespd.materials import ParameterRangeError
from bayespd.linalg.sparse import NotPositiveDefiniteError

from .fingerprint import run_fingerprint
from .kernels import KERNELS
from .space import max_plate_nesting
from .workers import run_in_processes


class ChainDivergedError(RuntimeError):
    """Every post-warmup transition of a chain diverged."""


class CheckpointMismatchError(ValueError):
    """A checkpoint directory holds the chains of another run."""


SETTINGS = {  # sampler setting: its check (``bayespd.validate``), with the fix named
    "checkpoint_every": lambda v: count("checkpoint_every", v, 1, "the draws between checkpoint writes, e.g. 50"),
    "max_tree_depth": lambda v: count("max_tree_depth", v, 1, "NUTS's largest tree has 2**max_tree_depth - 1 "
                                                              "leapfrog steps; 10 is usual"),
    "target_accept": lambda v: in_range("target_accept", v, 0, 1, "the acceptance probability the step size "
                                        "adapts to; 0.8 is usual, 0.95 for hard posteriors", closed=(False, False)),
    "trajectory_length": lambda v: v is None or positive("trajectory_length", v, "HMC's integration time per "
                                                         "draw: a finite number > 0, or None for 2 pi"),
}


def check_settings(**settings) -> None:
    """Refuse a sampler setting (a keyword of ``SETTINGS``) outside its range (the counts
    shared with other methods are checked by ``Method`` and ``Sampler``)."""
    for name, value in settings.items():
        SETTINGS[name](value)


def check_mass_matrix_seed(covariance) -> None:
    """Refuse an inverse mass matrix seed that is not a finite symmetric positive definite matrix."""
    if covariance is None:
        return
    c = torch.as_tensor(covariance, dtype=torch.float64)
    smallest = float(torch.linalg.eigvalsh(c).min()) if c.isfinite().all() and torch.equal(c, c.T) else math.nan
    if not smallest > 0:
        raise ValueError(
            f"mass_matrix_from gives an inverse mass matrix (the covariance of its draws) that is not "
            f"finite, symmetric and positive definite (smallest eigenvalue {smallest:.3g}): give a fit "
            "whose draws vary in every latent site, or mass_matrix_from='laplace'")


@dataclass
class ChainSpec:
    """Everything a chain needs; ``options`` are keyword arguments of the Pyro kernel."""

    model: object
    data: dict
    kernel: str
    num_warmup: int
    num_samples: int
    seed: int
    init: object
    options: dict = field(default_factory=dict)
    seed_covariance: torch.Tensor | None = None
    progress: bool = True
    checkpoint: Path | None = None
    checkpoint_every: int = 50
    fingerprint: dict | None = None  # the run's (``run_fingerprint``), set by ``run_chains`` to checkpoint


SHOWN = ("kernel", "num_warmup", "seed", "options")  # fingerprint entries shown by value, the others are hashes


def _fingerprint(spec, chain) -> dict:
    return {"kernel": spec.kernel, "num_warmup": spec.num_warmup, "seed": spec.seed + chain,
            "options": repr(sorted(spec.options.items())), **spec.fingerprint}


def _rng_state():
    kind, keys, pos, has_gauss, gauss = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    return {"torch": torch.get_rng_state(), "numpy": torch.as_tensor(keys.astype(np.int64)),
            "numpy_rest": [pos, has_gauss, gauss], "python": [version, list(internal), gauss_next]}


def _set_rng_state(state):
    torch.set_rng_state(state["torch"])
    pos, has_gauss, gauss = state["numpy_rest"]
    np.random.set_state(("MT19937", state["numpy"].numpy().astype(np.uint32), pos, has_gauss, gauss))
    version, internal, gauss_next = state["python"]
    random.setstate((version, tuple(internal), gauss_next))


def _save(path, fingerprint, kernel, z, draws, stats):
    state = {
        "fingerprint": fingerprint, "step_size": kernel.step_size,
        "inverse_mass_matrix": [[list(k), v] for k, v in kernel.inverse_mass_matrix.items()],
        "z": z, "rng": _rng_state(), "num_grad_evals": kernel.num_grad_evals,
        "draws": {k: torch.stack(v) for k, v in draws.items()} if draws else {},
        "stats": {k: list(v) for k, v in stats.items()},
    }
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def _load(path, fingerprint):
    if not path.exists():
        return None
    with reading(path, "a chain checkpoint (torch.save)", f"delete it (or {path.parent}) to start that chain afresh"):
        state = torch.load(path, weights_only=True)
        state["fingerprint"], state["draws"]
    if state["fingerprint"] != fingerprint:
        raise CheckpointMismatchError(
            f"checkpoint {path} belongs to another run: {_differences(state['fingerprint'], fingerprint)} "
            f"differ(s). Use another checkpoint directory for this run, or delete {path.parent} to "
            "start this one afresh there")
    return state


def _differences(saved, now) -> str:
    if not isinstance(saved, dict):
        return "all settings (it was written by an older bayespd)"
    keys = [*now, *(k for k in saved if k not in now)]
    return ", ".join(f"{k} ({saved.get(k)} there, {now.get(k)} here)" if k in SHOWN else k
                     for k in keys if saved.get(k) != now.get(k))


def _kernel(spec: ChainSpec, state):
    """A fresh kernel; resuming from ``state``, one past warmup, through Pyro's public API: the
    saved step size (``step_size``, ``adapt_step_size=False``) and position (``initial_params``),
    to be set up with no warmup steps."""
    options = dict(spec.options)
    if state is not None:
        options.update(step_size=state["step_size"], adapt_step_size=False)
    kernel = KERNELS[spec.kernel](
        spec.model, init_strategy=spec.init, seed_covariance=None if state is not None else spec.seed_covariance,
        max_plate_nesting=max_plate_nesting(spec.model, spec.data, spec.init), **options)
    if state is not None:
        kernel.initial_params = state["z"]
    return kernel


def _restore(kernel, state):
    """Put a kernel set up from ``state`` (``_kernel``) into the saved post-warmup state."""
    kernel.mass_matrix_adapter.inverse_mass_matrix = {tuple(k): v for k, v in state["inverse_mass_matrix"]}
    kernel.num_grad_evals = state["num_grad_evals"]
    kernel.stats.clear()
    kernel.stats.update({k: list(v) for k, v in state["stats"].items()})
    _set_rng_state(state["rng"])
    return state["z"]


def run_chain(spec: ChainSpec, chain: int, position: int = 0) -> dict:
    """One chain: ``{"draws": {site: (num_samples, ...)}, "stats": {...}, "grad_evals": n}``."""
    register_exception_handler(  # a numerical failure inside a trajectory is a divergence
        "bayespd_numerical_trouble",
        lambda e: isinstance(e, (NotPositiveDefiniteError, ParameterRangeError)),
        warn_on_overwrite=False,
    )
    path = None if spec.checkpoint is None else spec.checkpoint / f"chain{chain}.pt"
    fingerprint = None if path is None else _fingerprint(spec, chain)
    state = None if path is None else _load(path, fingerprint)
    if state is not None and len(next(iter(state["draws"].values()), [])) >= spec.num_samples:
        return _result({k: v[:spec.num_samples] for k, v in state["draws"].items()},
                       {k: v[:spec.num_samples] for k, v in state["stats"].items()},
                       state["num_grad_evals"], chain)
    pyro.set_rng_seed(spec.seed + chain)
    kernel = _kernel(spec, state)
    with pyro.validation_enabled(False):
        kernel.setup(spec.num_warmup if state is None else 0, **spec.data)
        z = kernel.initial_params
        draws = {k: [] for k in sorted(z)}
        bar = tqdm(total=spec.num_warmup + spec.num_samples, desc=f"{spec.kernel} chain {chain}",
                   position=position, disable=not spec.progress, leave=True)
        if state is None:
            for _ in range(spec.num_warmup):
                z = kernel.sample(z)
                bar.update()
            if path is not None:
                _save(path, fingerprint, kernel, z, {}, kernel.stats)
        else:
            z = _restore(kernel, state)
            draws = {k: list(v) for k, v in state["draws"].items()} or draws
            bar.update(spec.num_warmup + len(draws[next(iter(draws))]))
        while len(draws[next(iter(draws))]) < spec.num_samples:
            z = kernel.sample(z)
            for k, v in z.items():
                draws[k].append(kernel.transforms[k].inv(v).detach())
            done = len(draws[next(iter(draws))])
            if path is not None and (done % spec.checkpoint_every == 0 or done == spec.num_samples):
                _save(path, fingerprint, kernel, z, draws, kernel.stats)
            bar.update()
            if done % 10 == 0:
                bar.set_postfix(step_size=f"{kernel.step_size:.2e}",
                                divergences=sum(kernel.stats["diverging"]))
        bar.close()
    return _result({k: torch.stack(v) for k, v in draws.items()}, kernel.stats,
                   kernel.num_grad_evals, chain)


def _result(draws, stats, grad_evals, chain):
    if stats["diverging"] and all(stats["diverging"]):
        raise ChainDivergedError(
            f"every transition of chain {chain} diverged: the sampler cannot integrate this "
            "posterior. Reparametrise (sample log-moduli or non-centred fields), tighten the "
            "priors, use a dense mass matrix (dense_mass=True or mass_matrix_from='laplace'), "
            "start at the MAP (init='map'), or raise target_accept")
    return {"draws": {k: v.detach().numpy() for k, v in draws.items()},
            "stats": {k: np.asarray(v) for k, v in stats.items()}, "grad_evals": grad_evals}


def _worker(payload, chain, threads, dtype):
    torch.set_num_threads(threads)
    torch.set_default_dtype(dtype)
    tqdm.set_lock(threading.RLock())  # tqdm's default lock makes semaphores nobody releases
    with threadpool_limits(threads):  # every BLAS (numpy's, CHOLMOD's): workers must not oversubscribe
        return run_chain(pickle.loads(payload), chain, position=chain)


def usable_cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _pickled(spec):
    try:
        return pickle.dumps(spec)
    except (pickle.PicklingError, AttributeError, TypeError):
        return None


def _chain_died(spec):
    """The message of a chain whose worker process died: how a rerun resumes it."""
    def message(chain, how):
        if spec.checkpoint is None:
            return (f"the worker process of chain {chain} {how}: its draws are lost (pass checkpoint=DIR to make "
                    "a rerun resume killed chains), run the fit again")
        return (f"the worker process of chain {chain} {how}; the other chains ran to their end. Its checkpoint "
                f"{spec.checkpoint / f'chain{chain}.pt'} keeps its draws up to the last save: run the "
                "same fit again to resume it (the draws are the same as an uninterrupted run's)")
    return message


def _in_processes(spec, num_chains, workers, payload):
    jobs = [(payload, c, max(1, usable_cores() // workers), torch.get_default_dtype()) for c in range(num_chains)]
    return run_in_processes(_worker, jobs, workers, [f"chain {c}" for c in range(num_chains)],
                            _chain_died(spec), finish_others=spec.checkpoint is not None)


def run_chains(spec: ChainSpec, num_chains: int, chains="auto") -> tuple[dict, dict, int]:
    """All chains; ``chains`` is ``"auto"``, ``"sequential"`` or ``"processes"``.
    Returns ``(draws, stats, grad_evals)`` with arrays shaped ``(chain, draw, ...)``."""
    if chains not in ("auto", "sequential", "processes"):
        raise ValueError(f"chains must be 'auto', 'sequential' or 'processes', not {chains!r}")
    check_mass_matrix_seed(spec.seed_covariance)
    if spec.checkpoint is not None:
        spec.checkpoint.mkdir(parents=True, exist_ok=True)
        spec = replace(spec, fingerprint=run_fingerprint(spec.model, spec.data, spec.init, spec.seed,
                                                         spec.seed_covariance))
    workers = min(num_chains, usable_cores())
    payload = _pickled(spec) if chains == "processes" or (chains == "auto" and workers >= 2) else None
    if chains == "processes" and payload is None:
        raise ValueError("chains='processes' sends the model to spawned workers by pickle, and "
                         "this model does not pickle (a closure?): define it at module level "
                         "or use chains='sequential'")
    if payload is not None:
        results = _in_processes(spec, num_chains, workers, payload)
    else:
        results = [run_chain(spec, c) for c in range(num_chains)]
    draws = {k: np.stack([r["draws"][k] for r in results]) for k in results[0]["draws"]}
    stats = {k: np.stack([r["stats"][k] for r in results]) for k in results[0]["stats"]}
    return draws, stats, sum(r["grad_evals"] for r in results)
