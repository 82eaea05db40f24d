"""Inference cost on the demo plate: gradient evaluations per second inside Pyro against the
bare solve + adjoint, and NUTS wall time to bulk ESS >= 400 for every parameter.

* ``bare``: ``scene.solve`` at (K, G, delta), observation, the Normal log-likelihood, and its
  gradient in (K, G, delta, sigma) by the adjoint; plain torch, no priors, no transforms.
* ``pyro``: the potential NUTS differentiates (``bayespd.infer.space.Unconstrained``: Pyro's
  ``potential_fn`` of ``models.elastic_plate``: trace, priors, constraint transforms and
  their log-Jacobians, the same solve) and its gradient. Overhead = 1 - bare / pyro time.
* Both are timed interleaved (bare, pyro, bare, ...; best of ``--repeat`` each) so that the
  machine's load hits them alike.
* ``nuts``: ``fit(..., "nuts")`` as demo.py runs it (MAP start, Laplace-seeded dense mass
  matrix) with ``--chains`` chains of ``--warmup`` + ``--draws``; bulk ESS per parameter by
  ArviZ. If the smallest ESS is below 400 the time to 400 is extrapolated linearly
  (wall x 400 / ESS_min, warmup included: conservative), and the output says so.

Scenes: ``demo`` is experiments/demo.py's plate (h = 2 mm, delta_max = 6, its DIC points and
data); ``5k`` is the same geometry at h = 0.4 mm, delta_max = 3 h (4,7xx particles), with
data from the model itself (a benchmark, not a result). NUTS on ``5k`` is not run by
default (``--nuts-on demo 5k`` runs it; ``--nuts-on`` alone runs none): its time is
extrapolated from the demo's gradients per effective draw.

    python benchmarks/inference.py [--scenes demo 5k] [--repeat 10] [--draws 300 --warmup 200 --chains 2]
                                   [--rule linear|smooth] [--nuts-on demo 5k] [--reduced SNAPSHOTS]

With ``--reduced 30`` every scene is replaced by its reduced model (``bp.ReducedScene``): the
gradients then cost an r x r solve (experiments/reduced_likelihood.py measures the whole path).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import demo  # noqa: E402  (sets one torch thread; the repository root on sys.path)

import arviz as az  # noqa: E402
import pyro.distributions as dist  # noqa: E402
from pyro.infer.autoguide.initialization import init_to_value  # noqa: E402

import bayespd as bp  # noqa: E402
from bayespd.linalg import sparse  # noqa: E402
from bayespd.infer import fit, to_inference_data  # noqa: E402
from bayespd.infer.space import Unconstrained  # noqa: E402
from bayespd.models.elastic_plate import elastic_plate  # noqa: E402
from timing import best  # noqa: E402

ESS_TARGET = 400


def demo_problem(rule="linear"):
    points, y, sigma = demo.synthetic_data(demo.TRUTH, 0)
    return demo.plate(demo.H_MODEL, demo.DELTA_MAX, points, rule), y, sigma


def fine_problem(h=0.4, rule="linear"):
    model_particles = demo.plate(h, 3 * h).particles
    points = model_particles.x[model_particles.x[:, 0] > demo.CLAMP]
    scene = demo.plate(h, 3 * h, points, rule)
    with torch.no_grad():
        clean = scene.observe(scene.solve({**{k: demo.TRUTH[k] for k in ("K", "G")}, "delta": 2.5 * h}))
    sigma = 0.01 * float(clean.abs().max())
    return scene, clean + sigma * torch.randn(clean.shape, generator=torch.Generator().manual_seed(0)), sigma


def at_truth(scene, sigma):
    return {"K": demo.TRUTH["K"], "G": demo.TRUTH["G"],
            "delta": min(demo.TRUTH["delta"], 0.8 * scene.material.bonds.delta_max), "sigma": sigma}


def reduced(scene, y, sigma, snapshots: int):
    """The scene's reduced model (``bp.ReducedScene``) from ``snapshots`` prior draws, to 1 % of
    the noise sd; needs ``rule="smooth"`` bonds to be worth it."""
    priors = elastic_plate(scene, demo.NOMINAL, noise_scale=0.05 * float(y.abs().max())).priors
    draws = bp.prior_draws(priors, snapshots, 0, names=["K", "G", "delta"])
    start = time.perf_counter()
    rom = bp.ReducedScene(scene, draws, 0.01 * sigma)
    print(f"reduced model: rank {rom.rank}, {rom.report['delta_pieces']} pieces in delta, built in "
          f"{time.perf_counter() - start:.1f} s from {snapshots} full solves", flush=True)
    return rom


def gradient_rates(scene, y, sigma, repeat):
    """(bare seconds, pyro seconds) per gradient evaluation, best of ``repeat``."""
    point = at_truth(scene, sigma)
    leaves = {k: torch.tensor(v, requires_grad=True) for k, v in point.items()}

    def bare():
        u = scene.predict({k: leaves[k] for k in ("K", "G", "delta")})
        lp = dist.Normal(u, leaves["sigma"]).log_prob(y).sum()
        torch.autograd.grad(lp, list(leaves.values()))

    model = elastic_plate(scene, demo.NOMINAL, noise_scale=0.05 * float(y.abs().max()))
    space = Unconstrained(model, {"y": y}, init_to_value(values={k: torch.tensor(v) for k, v in point.items()}))
    z0 = space.initial

    def pyro_potential():
        z = z0.clone().requires_grad_()
        torch.autograd.grad(space.potential(z), z)

    bare(), pyro_potential()  # warm-up (symbolic factorisation)
    times = [(best(bare, 1), best(pyro_potential, 1)) for _ in range(repeat)]  # interleaved: same load
    return min(t[0] for t in times), min(t[1] for t in times), model


def nuts_to_ess(model, y, scene, draws, warmup, chains, adapt_mass=True, target_accept=0.8):
    tree = fit(model, {"y": y}, "nuts", num_samples=draws, num_warmup=warmup, num_chains=chains,
               init="map", mass_matrix_from="laplace", adapt_mass=adapt_mass, target_accept=target_accept,
               seed=0, progress=False)
    ess = az.ess(to_inference_data(tree), var_names=list(demo.NAMES), method="bulk")
    ess = {k: float(ess[k]) for k in demo.NAMES}
    wall = float(tree.attrs["wall_time_s"])
    grads = int(tree.attrs["num_grad_evals"])
    low = min(ess.values())
    return {"wall_time_s": wall, "grad_evals": grads, "ess_bulk": ess, "ess_min": low,
            "time_to_ess_400_s": wall * max(1.0, ESS_TARGET / low), "extrapolated": low < ESS_TARGET,
            "grads_per_effective_draw": grads / low,
            "divergences": int(tree["sample_stats"]["diverging"].sum()),
            "tree_depth_mean": float(tree["sample_stats"]["tree_depth"].mean())}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["demo", "5k"], choices=["demo", "5k"])
    parser.add_argument("--repeat", type=int, default=10)
    parser.add_argument("--draws", type=int, default=300)
    parser.add_argument("--warmup", type=int, default=200)
    parser.add_argument("--chains", type=int, default=2)
    parser.add_argument("--nuts-on", nargs="*", default=["demo"], choices=["demo", "5k"],
                        help="the scenes NUTS runs on, none for gradients only (the others: "
                             "extrapolated from its gradients per effective draw)")
    parser.add_argument("--fixed-mass", action="store_true",
                        help="keep the Laplace mass matrix through warmup (fit's adapt_mass=False)")
    parser.add_argument("--target-accept", type=float, default=0.8)
    parser.add_argument("--reduced", type=int, default=0, metavar="SNAPSHOTS",
                        help="time the scenes' reduced models (bp.ReducedScene from this many full solves) "
                             "instead of the full ones; use with --rule smooth")
    parser.add_argument("--rule", default="linear", choices=["linear", "smooth"],
                        help="partial-volume ramp in delta of the model (bayespd.bonds.partial_volume)")
    args = parser.parse_args()
    print(f"load average at start {os.getloadavg()[0]:.2f}; torch threads {torch.get_num_threads()}; "
          f"backend {sparse.default_backend()}; partial volumes {args.rule}")
    nuts = None
    for name in args.scenes:
        scene, y, sigma = demo_problem(args.rule) if name == "demo" else fine_problem(rule=args.rule)
        if args.reduced:
            scene = reduced(scene, y, sigma, args.reduced)
        t_bare, t_pyro, model = gradient_rates(scene, y, sigma, args.repeat)
        print(f"{name}{' (reduced)' if args.reduced else ''}: {scene.particles.n} particles, {len(y)} points, "
              f"{scene.material.bonds.n} bonds; "
              f"gradient: bare {1e3 * t_bare:.1f} ms ({1 / t_bare:.0f}/s), in Pyro {1e3 * t_pyro:.1f} ms "
              f"({1 / t_pyro:.0f}/s); Pyro overhead {100 * (1 - t_bare / t_pyro):.0f} % of each gradient", flush=True)
        if name in args.nuts_on:
            start = time.perf_counter()
            nuts = nuts_to_ess(model, y, scene, args.draws, args.warmup, args.chains, not args.fixed_mass,
                               args.target_accept)
            how = "extrapolated" if nuts["extrapolated"] else "measured"
            print(f"{name} NUTS {args.chains} x ({args.warmup} + {args.draws}): {nuts['wall_time_s']:.1f} s "
                  f"(fit call {time.perf_counter() - start:.1f} s), {nuts['grad_evals']} gradients, bulk ESS "
                  f"{ {k: round(v) for k, v in nuts['ess_bulk'].items()} }, divergences {nuts['divergences']}; "
                  f"time to ESS {ESS_TARGET} for every parameter: {nuts['time_to_ess_400_s']:.1f} s ({how}); "
                  f"{nuts['grads_per_effective_draw']:.1f} gradients per effective draw, mean tree depth "
                  f"{nuts['tree_depth_mean']:.2f}", flush=True)
        elif nuts is not None:
            print(f"{name}: NUTS to ESS {ESS_TARGET} extrapolated from the demo's "
                  f"{nuts['grads_per_effective_draw']:.1f} gradients per effective draw: "
                  f"{ESS_TARGET * nuts['grads_per_effective_draw'] * t_pyro:.0f} s", flush=True)


if __name__ == "__main__":
    main()
