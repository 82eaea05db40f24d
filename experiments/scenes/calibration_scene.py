"""The cheap scene of the calibration checks (SBC, coverage) and its checkpointed replications.

An 8 x 8 LPS plate (h = 1, delta_max = 2.5, 64 particles), clamped on a layer delta_max deep
on the left, pulled and sheared on the right and pulled up along the top, observed at every
free particle; the model is ``models.elastic_plate`` with its default priors (K, G
LogNormal(log nominal, 0.5), delta ScaledBeta(h, delta_max, 2, 2), sigma HalfNormal).
By default delta is known (conditioned at DELTA_KNOWN) and (K, G, sigma) are inferred:
with delta free the likelihood has a kink wherever delta crosses a bond length (partial
volumes are piecewise linear in delta); in trial fits NUTS with the metric re-adapted in
warmup then took ~1.8x the gradients (1.8-5.6 k per fit) and mixed delta poorly (bulk ESS
15-30 of 150 draws). ``free_delta=True`` runs that variant with the Laplace metric kept
through warmup and target_accept 0.95 (benchmarks/README.md, inference.py: 2.8x fewer
gradients per effective draw, no divergences at the kinks), and, for every method, the MAP
taken as the best of 8 searches (``FREE_DELTA``): the kinks split delta into basins whose
modes lie up to 120 nats apart, and one search from the prior median ends in the wrong basin
often enough to fail SBC (40 of 100 NUTS intervals missed delta with one search). Every method
also fits every mode found with at least 1e-3 of the largest Laplace mass and mixes them by
their mass (``modes="weighted"``, ``bayespd.infer.mixture``): a chain need not cross
to a second basin a few nats away. And with delta free the partial volumes use the smooth
(C1) ramp (FREE_DELTA_RULE): the linear ramp's kinks put cusps in the potential along delta
(``experiments/delta_ridges.py``) that chains cross rarely; with it, delta coverage stayed at
0.82 whether the best mode alone or every mode was fitted.

Replication ``i`` draws (K, G, delta, sigma) and then y from the model itself (seed
``1000 + i``): the prior predictive, so the data come from the same model that is calibrated
*by definition* of SBC and coverage, which check the inference, not the model. (The no-inverse-
crime rule of DESIGN.md is for results about the physics; delta_identifiability.py uses finer
data.) Each replication's summary is written atomically to
``runs/calibration_reps/<method>-<fingerprint>/rep_<i>.json`` as it finishes, so a killed run
resumes and sbc.py and interval_coverage.py share the NUTS fits.
"""
from __future__ import annotations

import hashlib
import json
import time
from functools import lru_cache
from pathlib import Path

import pyro
import torch

import common
from bayespd.infer.calibration import central_interval, rank, thin

import bayespd as bp
from bayespd.infer import NotPositiveDefiniteHessian, fit
from bayespd.models.elastic_plate import elastic_plate

NX, NY, H, DELTA_MAX = 8, 8, 1.0, 2.5
NOMINAL = {"K": 3000.0, "G": 1200.0}
NOISE_FRACTION = 0.05  # prior scale of sigma, as a fraction of max |u| at the nominal values
DELTA_KNOWN = 1.75  # between the bond lengths sqrt(2) and 2

# the settings of each method's fit; changing one changes the cache folder
METHODS = {
    "nuts": {"num_warmup": 100, "num_samples": 100, "num_chains": 1, "init": "map",
             "mass_matrix_from": "laplace", "rank_draws": 19},
    "laplace": {"num_samples": 400, "hessian": "exact"},
    "svi": {"guide": "mvn", "svi_steps": 300, "svi_lr": 0.02, "num_samples": 400, "init": "map"},
}
MAP_STARTS = 8  # with delta free: the median and a 7-point Latin hypercube of the prior
FREE_DELTA = {"nuts": {"adapt_mass": False, "target_accept": 0.95, "map_starts": MAP_STARTS,
                       "modes": "weighted"},
              "laplace": {"map_starts": MAP_STARTS, "modes": "weighted"},
              "svi": {"map_starts": MAP_STARTS, "modes": "weighted"}}
FREE_DELTA_RULE = "smooth"  # C1 partial volumes: the linear ramp's kinks make ridges in delta


def settings(method: str, free_delta: bool = False) -> dict:
    """The options of ``method``'s fits (METHODS, and FREE_DELTA's with delta free)."""
    return {**METHODS[method], **(FREE_DELTA[method] if free_delta else {})}


def plate(nx=NX, ny=NY, h=H, delta_max=DELTA_MAX, rule="linear") -> bp.Scene:
    """The calibration plate, with partial volumes by ``rule`` (``bp.find_bonds``)."""
    p = bp.grid_2d(nx * h, ny * h, h)
    material = bp.LPS(p, bp.find_bonds(p, delta_max, rule=rule), plane="stress")
    clamp = p.layer("left", delta_max)
    loads = [bp.Load(p.layer("right", h), (30.0, 10.0)), bp.Load(p.layer("top", h) & ~clamp, (0.0, 20.0))]
    return bp.Scene(material, [bp.Dirichlet.layer(p, "left", delta_max)], loads,
                    bp.Observation(p, p.x[~clamp]))


def names(free_delta: bool) -> tuple[str, ...]:
    return ("K", "G", "delta", "sigma") if free_delta else ("K", "G", "sigma")


def rule(free_delta: bool) -> str:
    return FREE_DELTA_RULE if free_delta else "linear"


@lru_cache(maxsize=None)
def scene_and_model(free_delta: bool = False, partial_volumes: str | None = None):
    """(scene, Pyro model, noise_scale) of the calibration plate; delta conditioned at
    DELTA_KNOWN unless ``free_delta``; partial volumes by ``partial_volumes`` (default
    ``rule(free_delta)``)."""
    scene = plate(rule=partial_volumes or rule(free_delta))
    with torch.no_grad():
        u = scene.observe(scene.solve({**NOMINAL, "delta": DELTA_KNOWN}))
    noise_scale = NOISE_FRACTION * float(u.abs().max())
    model = elastic_plate(scene, NOMINAL, noise_scale)
    if not free_delta:
        model = pyro.poutine.condition(model, data={"delta": torch.tensor(DELTA_KNOWN)})
    return scene, model, noise_scale


def prior_draw(model, seed: int, free_delta: bool = False) -> tuple[dict, torch.Tensor]:
    """(parameters, y) drawn from the model's joint prior with ``seed``."""
    pyro.set_rng_seed(seed)
    with torch.no_grad():
        trace = pyro.poutine.trace(model).get_trace()
    truth = {k: float(trace.nodes[k]["value"]) for k in names(free_delta)}
    return truth, trace.nodes["y"]["value"].detach().clone()


def fit_method(model, y, method: str, seed: int, options: dict):
    """One fit with ``options`` (see ``settings``); NUTS falls back to an adapted dense
    mass matrix when the Laplace Hessian at the MAP is not positive definite."""
    options = {k: v for k, v in options.items() if k != "rank_draws"}
    try:
        return fit(model, {"y": y}, method, seed=seed, progress=False, **options)
    except NotPositiveDefiniteHessian:
        if method != "nuts":
            raise
        options.update(mass_matrix_from=None, dense_mass=True, adapt_mass=True)
        return fit(model, {"y": y}, method, seed=seed, progress=False, **options)


def summarise(tree, truth: dict, rank_draws: int | None) -> dict:
    """Per parameter: posterior mean, sd, 90 % interval, whether it covers the truth and
    (given ``rank_draws``) the SBC rank of the truth among that many thinned draws."""
    out = {}
    for k in truth:
        draws = tree["posterior"][k].values.reshape(-1)
        lo, hi = central_interval(draws, 0.9)
        out[k] = {"mean": float(draws.mean()), "sd": float(draws.std()), "interval_90": [lo, hi],
                  "covered": bool(lo <= truth[k] <= hi)}
        if rank_draws:
            out[k]["rank"] = rank(truth[k], thin(draws, rank_draws))
    return out


def fingerprint(method: str, free_delta: bool = False) -> str:
    key = json.dumps({"scene": [NX, NY, H, DELTA_MAX, NOISE_FRACTION], "nominal": NOMINAL,
                      "settings": settings(method, free_delta),
                      "delta": "free" if free_delta else DELTA_KNOWN,
                      **({"rule": FREE_DELTA_RULE} if free_delta else {})}, sort_keys=True)
    return f"{method}-{hashlib.sha1(key.encode()).hexdigest()[:10]}"


def replication(method: str, i: int, free_delta: bool = False, root=None) -> dict:
    """Replication ``i`` of ``method``: loaded if its file exists, else fitted and written
    (under ``root``, default runs/calibration_reps)."""
    folder = Path(root or common.run_dir("calibration_reps")) / fingerprint(method, free_delta)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"rep_{i:04d}.json"
    if path.exists():
        return json.loads(path.read_text())
    _, model, _ = scene_and_model(free_delta)
    truth, y = prior_draw(model, 1000 + i, free_delta)
    options = settings(method, free_delta)
    start = time.perf_counter()
    try:
        tree = fit_method(model, y, method, i, options)
    except Exception as error:  # recorded, never dropped silently
        record = {"rep": i, "truth": truth, "failed": f"{type(error).__name__}: {error}"}
    else:
        record = {"rep": i, "truth": truth, "params": summarise(tree, truth, options.get("rank_draws")),
                  "fit_wall_time_s": float(tree.attrs["wall_time_s"]),
                  "grad_evals": int(tree.attrs["num_grad_evals"])}
        if "diverging" in tree["sample_stats"]:
            record["divergences"] = int(tree["sample_stats"]["diverging"].sum())
    record["wall_time_s"] = time.perf_counter() - start
    common.write_atomic(path, json.dumps(record))
    return record


def replications(method: str, n: int, free_delta: bool = False, root=None, log=print) -> list[dict]:
    """Replications 0..n-1 of ``method`` (resuming from the checkpoint files)."""
    out = []
    for i in range(n):
        r = replication(method, i, free_delta, root)
        out.append(r)
        if log:
            status = r.get("failed") or " ".join(f"{k}:{r['params'][k].get('rank', '')}"
                                                  f"{'+' if r['params'][k]['covered'] else '-'}"
                                                  for k in r["truth"])
            log(f"{method} rep {i:3d}  {r['wall_time_s']:6.1f} s  {status}", flush=True)
    return out


def successful(records: list[dict]) -> list[dict]:
    return [r for r in records if "failed" not in r]


def command_line(doc: str, unit: str) -> tuple[int, bool, bool]:
    """(n, free_delta, quick) from the command line shared by sbc.py and interval_coverage.py."""
    import argparse

    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"20 {unit} (smoke run)")
    parser.add_argument("--n", type=int, default=100, help=f"{unit} (default 100)")
    parser.add_argument("--free-delta", action="store_true", help="infer delta too (2-5x costlier)")
    args = parser.parse_args()
    return 20 if args.quick else args.n, args.free_delta, args.quick


def run_name(base: str, free_delta: bool, quick: bool) -> str:
    return base + ("_free_delta" if free_delta else "") + ("_quick" if quick else "")
