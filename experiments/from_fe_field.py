"""Tutorial: calibrate a plane-stress LPS model from a finite-element field, as a DIC user would.

For each of ``--materials`` random materials (E in [500, 100000] MPa, nu in [0.15, 0.45],
seeded) and geometry (the pin-roller beam of ``reference.three_point_bending`` on a 1 mm grid,
the plate with a hole of ``reference.plate_with_hole`` on a 0.5 mm grid): solve the scikit-fem
peer (Q2, h_FE = 0.5 mm beam, 0.25 mm plate: ``FE_DATA``), read it on the grid, add noise
(``--noise`` x max |u|, per entry), write a DIC-like ``.npz`` grid, then *calibrate from the
file* by the user's code (``read``, ``scene_of``, ``vfm``, ``fit_tikhonov``, ``calibrate``: 40
non-blank lines between the markers, the same path as for a DIC file):

* VFM defaults (``vfm_defaults.estimate`` of ``Field.on_particles``);
* adjoint Tikhonov of K, G at delta = 3 h, started at the VFM estimate (bounds two decades each
  way), the plain LPS on a reduced scene (``bp.ReducedScene.from_sampler``: 16 draws of
  LogNormal(log VFM estimate, 0.5), 32 where 16 miss the tolerance; delta held at 3 h by
  ``bp.Held``) with its misfit weighted by the approximation-error term below
  (``tikhonov(..., discrepancy=term, sigma=noise sd)``: the default for measured data);
* Laplace (``bp.fit(..., "laplace")``) on the same reduced scene (priors LogNormal(log Tikhonov
  estimate, 0.5)) with the
  approximation-error term of the plain LPS against the FE peer (``fe_error_term``: 16 FE
  solves at h_FE = ``FE_TERM`` (1 mm beam, 0.5 mm plate: coarser than the data's) over nu in
  [0.15, 0.45], plus the peer's own mesh error, h_FE against 2 h_FE; once per geometry):
  posterior mean and 90 % intervals of E and nu, and its MAP (``map``: the Tikhonov estimate
  whose misfit is weighted by the noise and the term's covariance, with the weak priors).

The experiment's own code wraps it (``run_case``): each step's wall time, the reduced model's
rank and error estimate, and the comparisons: (unless ``--no-corrected``) Tikhonov on the
surface-corrected LPS, full scene, plain misfit; ``--vfm-only --vfm pd`` the VFM by the PD
virtual work of before issue 30 (``vfm_pd``).

Writes runs/from_fe_field[_beam|_plate|_quick]/ (metrics.json with per-target pass/fail, rewritten
after every case; error_vs_time.png). A VFM that finds no positive (K, G) counts as failed.

    python experiments/from_fe_field.py [--materials N] [--geometry beam|plate|both] [--noise 0 0.01] [--quick] [--no-corrected]
                                        [--vfm-only] [--vfm local|pd]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from contextlib import contextmanager, nullcontext
from pathlib import Path

import numpy as np
import torch

import common  # noqa: F401
from common import run_dir, write_metrics

import bayespd as bp
from bayespd.infer import fit, modes, young_intervals
from bayespd.inverse import tikhonov
from bayespd.inverse.vfm_defaults import estimate, load_field
from bayespd.inverse.virtual_fields import interior_bumps
from bayespd.models.elastic_plate import elastic_plate
from bayespd.reference import plate_with_hole as ph, three_point_bending as tpb

GRID = {"beam": 1.0, "plate": 0.5}  # mm: the DIC step
FE_DATA = {"beam": 0.5, "plate": 0.25}  # mm: the FE mesh of the data, finer than the term's two meshes
FE_TERM = {"beam": 1.0, "plate": 0.5}  # mm: the term's FE peer (and its mesh error: the peer at twice this h)
TERM_NUS = np.linspace(0.15, 0.45, 16)  # the term's design: the range of nu
TARGETS = {"vfm_K": 0.005, "vfm_G": 0.005, "tikhonov_E": 0.02, "tikhonov_nu": 0.02,
           "tikhonov_corrected_E": 0.02, "tikhonov_corrected_nu": 0.02, "laplace_E": 0.02, "laplace_nu": 0.02,
           "map_E": 0.02, "map_nu": 0.02}
METHODS = ("vfm", "tikhonov", "tikhonov_corrected", "laplace", "map")  # map: the MAP of the Laplace's model


def fe_error_term(fe_at, scene, nus, inside, young: float = 4000.0, fe_coarse=None) -> bp.Discrepancy:
    """The approximation-error term (Kaipio & Somersalo 2007): the relative error of ``scene``
    (delta held: ``bp.Held``) against the FE peer ``fe_at(young, nu, points)`` on a design of
    Poisson ratios ``nus`` (smooth trend in log(G / K)); at the observation points ``inside(points)``
    leaves out (a hole: masked data) the error is 0. With ``fe_coarse`` (the peer on a mesh twice
    as coarse) the peer's own discretisation error, fe_at - fe_coarse at each design point, is
    added as an independent zero-mean component (``Discrepancy.with_errors``: a bound for the
    peer's error against any finer mesh, the data's included)."""
    points = scene.observation.points.numpy() if torch.is_tensor(scene.observation.points) \
        else np.asarray(scene.observation.points)
    draws = [dict(zip(("K", "G"), map(float, bp.moduli_from_young(young, nu)))) for nu in nus]
    keep = torch.as_tensor(inside(points))
    predicted, mesh_errors = [], []

    def reference(params):
        E, nu = map(float, bp.young_from_moduli(params["K"], params["G"]))
        predicted.append(scene.predict(params))  # the model's, returned by ``model`` next: one PD solve per draw
        u, fine = predicted[-1].clone(), torch.as_tensor(fe_at(E, nu, points[keep.numpy()]))
        u[keep] = fine
        if fe_coarse is not None:
            error = torch.zeros_like(u)
            error[keep] = fine - torch.as_tensor(fe_coarse(E, nu, points[keep.numpy()]))
            mesh_errors.append(error.reshape(-1) / predicted[-1].square().mean().sqrt())
        return u

    with torch.no_grad():
        term = bp.estimate_discrepancy(reference, lambda params: predicted.pop(), draws, dependence="smooth",
                                       features=bp.ElasticFeatures(with_delta=False), relative=True,
                                       explained=0.9999, points=scene.observation.points)
    return term if fe_coarse is None else term.with_errors(torch.stack(mesh_errors), spread=True)


def fe_at(geometry: str, E: float, nu: float, points, h_fe: float | None = None) -> np.ndarray:
    """The FE peer's displacements (points, 2) on the mesh of size ``h_fe`` (default: the data's);
    under prescribed loads u scales as 1 / E, so one solve per nu serves every E."""
    h_fe = h_fe or FE_DATA[geometry]
    fe = tpb.fe_solution(h_fe, nu=nu) if geometry == "beam" else ph.fe_solution(h_fe, young=ph.YOUNG, nu=nu)
    return (tpb.YOUNG if geometry == "beam" else ph.YOUNG) / E * fe.at(points)


def fe_grid(geometry: str, E: float, nu: float):
    """(x, y, u) on the DIC grid of cell centres (NaN in the hole), from the FE peer."""
    h = GRID[geometry]
    L, W = (tpb.LENGTH, tpb.WIDTH) if geometry == "beam" else (ph.PLATE.length, ph.PLATE.width)
    x, y = np.arange(h / 2, L, h), np.arange(h / 2, W, h)
    pts = np.stack(np.meshgrid(x, y, indexing="xy"), -1).reshape(-1, 2)
    keep = in_body(geometry, pts)
    u = np.full((len(pts), 2), np.nan)
    u[keep] = fe_at(geometry, E, nu, pts[keep])
    return x, y, u


def in_body(geometry: str, x):
    return np.ones(len(x), bool) if geometry == "beam" else np.linalg.norm(x - ph.PLATE.centre, axis=1) > ph.PLATE.radius


# ---- the user's code: a DIC-like file in, K, G and E, nu out ----
def read(path, geometry: str):
    return bp.read_field(path, order="xy", thickness=tpb.THICKNESS if geometry == "beam" else 1.0,
                         body=lambda x: in_body(geometry, x))


def scene_of(field, geometry: str, delta: float, surface: bool = False):
    p = field.particles
    if geometry == "beam":
        bcs = [bp.Dirichlet(tpb.PIN.contains(p.x), (0.0, 0.0)), bp.Dirichlet(tpb.ROLLER.contains(p.x), (None, 0.0))]
        loads = [bp.Load(tpb.LOAD.contains(p.x), (0.0, -tpb.FORCE))]
    else:
        bcs = [bp.Dirichlet(ph.PLATE.clamped.contains(p.x), (0.0, 0.0))]
        loads = [bp.Load(ph.PLATE.loaded.contains(p.x), (ph.PLATE.force, 0.0))]
    return bp.Scene(bp.LPS(p, bp.find_bonds(p, delta), plane="stress", surface_correction=surface), bcs, loads,
                    field.observation)


def vfm(field, scene, sigma: float, **options) -> dict:
    """K, G (and se) by the VFM defaults; E = 1e4, nu = 0.3 where they find no positive moduli."""
    try:
        res = estimate(scene, field.on_particles(), sigma=sigma or None, **options)
        return {**res.params, "se": res.extra.get("se")}
    except ValueError as error:
        return {**dict(zip(("K", "G"), map(float, bp.moduli_from_young(1e4, 0.3)))), "failed": str(error)}


def fit_tikhonov(scene, field, start: dict, **options) -> dict:
    tik = tikhonov(scene, field.y, {k: start[k] for k in "KG"}, fixed={"delta": 3 * field.particles.h},
                   mask=field.mask, bounds={k: (start[k] / 100, start[k] * 100) for k in "KG"}, **options)
    return {**tik.params, "converged": tik.converged, "reason": tik.reason}


def calibrate(field, geometry: str, sigma: float, term=None, seed: int = 0, timer=nullcontext) -> dict:
    """VFM, then Tikhonov and Laplace with the error term ``term`` on one reduced scene; ``timer(step)``: a context."""
    delta, top = 3 * field.particles.h, float(np.nanmax(np.abs(field.y)))
    with timer("vfm"):
        out = {"vfm": vfm(field, plain := scene_of(field, geometry, delta), sigma)}
    with timer("tikhonov"):
        priors = elastic_plate(bp.Held(plain, delta=delta), out["vfm"], 0.05 * top).priors
        draws = lambda n: [{**d, "delta": delta} for d in bp.prior_draws(priors, n, seed, ["K", "G"])]  # noqa: E731
        reduced = bp.Held(bp.ReducedScene.from_sampler(plain, draws, 0.01 * max(sigma, 1e-5 * top),
                                                       delta_range=(delta * (1 - 1e-6), delta)), delta=delta)
        out["tikhonov"] = fit_tikhonov(reduced, field, out["vfm"], discrepancy=term, sigma=sigma)
    with timer("laplace"):
        tree = fit(elastic_plate(reduced, out["tikhonov"], 0.05 * top, discrepancy=term), field.data(), "laplace",
                   num_samples=1000, seed=seed, progress=False, predictive=False)
    return {**out, "laplace": young_intervals(tree), "map": {k: float(modes(tree).loc[0, k]) for k in "KG"},
            "tree": tree, "reduced": reduced}
# ---- end of the user's code ----


def run_case(path, geometry: str, sigma: float, term, seed: int, methods=METHODS, vfm_work: str = "local") -> dict:
    """The user's ``read`` and ``calibrate`` with each step's wall time (the MAP's is the Laplace's: its own
    search) and the reduced model's rank and its largest error estimate over the posterior draws, or
    (``methods == ("vfm",)``) its VFM alone (``vfm_work="pd"``: by the PD work, ``vfm_pd``); plus the
    surface-corrected Tikhonov when in ``methods`` (full scene, plain misfit, from the same VFM estimate)."""
    field, times = read(path, geometry), {}

    @contextmanager
    def timer(step):
        t0 = time.perf_counter()
        yield
        times[step] = time.perf_counter() - t0

    if methods == ("vfm",):
        with timer("vfm"):
            res = {"vfm": vfm_pd(field, geometry, sigma) if vfm_work == "pd"
                   else vfm(field, scene_of(field, geometry, 3 * field.particles.h), sigma)}
    else:
        res = calibrate(field, geometry, sigma, term, seed, timer)
        estimates = res.pop("tree")["sample_stats"]["reduced_error_estimate"].values
        res["laplace"].update(rank=res.pop("reduced").scene.rank, error_estimate_max=float(np.nanmax(estimates)))
        times["map"] = times["laplace"]
    if "tikhonov_corrected" in methods:
        with timer("tikhonov_corrected"):
            res["tikhonov_corrected"] = fit_tikhonov(scene_of(field, geometry, 3 * field.particles.h, True), field,
                                                     res["vfm"], sigma=sigma or 0.01 * float(np.nanmax(np.abs(field.y))))
    return {m: {**r, "wall_time_s": float(times[m])} for m, r in res.items()}


def vfm_pd(field, geometry: str, sigma: float) -> dict:
    """The VFM by the PD virtual work as before issue 30's local work (delta = 5 h, m chosen by the
    residual; for the plate, whose default bumps all meet the hole, the clamp or the load, the load
    field and bumps clear of them by 3.5 mm)."""
    sc = scene_of(field, geometry, 5 * field.particles.h)
    fields = None if geometry == "beam" else [load_field(sc)] + interior_bumps((6.5, 0), (15.5, 20), (1, 4), 3.5) \
        + interior_bumps((24.5, 0), (37.5, 20), (2, 4), 3.5)
    return vfm(field, sc, sigma, fields=fields, work="pd", ms=(2, 3, 4) if geometry == "beam" else (2, 3))


def error_term(path, geometry: str):
    """The plain LPS's approximation-error term against the FE peer at h_FE = FE_TERM, with the
    peer's own mesh error (against h_FE = 2 FE_TERM), and its wall time (once per geometry: every
    material shares the grid)."""
    t0 = time.perf_counter()
    field = read(path, geometry)
    scene = bp.Held(scene_of(field, geometry, 3 * field.particles.h), delta=3 * field.particles.h)
    h = FE_TERM[geometry]
    term = fe_error_term(lambda E, nu, x: fe_at(geometry, E, nu, x, h), scene, TERM_NUS, lambda x: in_body(geometry, x),
                         fe_coarse=lambda E, nu, x: fe_at(geometry, E, nu, x, 2 * h))
    return term, time.perf_counter() - t0


def score(res: dict, truth: dict) -> None:
    """Adds E, nu and the relative errors to every method's result (Laplace: its mean)."""
    for method, r in res.items():
        if method == "laplace":
            r["rel_error"] = {k: r[k]["mean"] / truth[k] - 1 for k in ("E", "nu")}
            r["covers"] = {k: r[k]["interval_90"][0] <= truth[k] <= r[k]["interval_90"][1] for k in ("E", "nu")}
            r["rel_width"] = {k: float(np.diff(r[k]["interval_90"])[0]) / truth[k] for k in ("E", "nu")}
            continue
        E, nu = bp.young_from_moduli(r["K"], r["G"])
        r.update(E=float(E), nu=float(nu))
        r["rel_error"] = {k: float("inf") if "failed" in r else r[k] / truth[k] - 1 for k in truth}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--materials", type=int, default=20)
    ap.add_argument("--geometry", choices=["beam", "plate", "both"], default="both")
    ap.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.01])
    ap.add_argument("--quick", action="store_true", help="one material, the plate only")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-corrected", action="store_true", help="skip the Tikhonov with the surface correction")
    ap.add_argument("--vfm-only", action="store_true", help="the VFM alone (no Tikhonov, no Bayesian fit, no error term)")
    ap.add_argument("--vfm", choices=["local", "pd"], default="local", help="the VFM's virtual work (pd: before issue 30's fix)")
    args = ap.parse_args()
    if args.vfm == "pd" and not args.vfm_only:
        ap.error("--vfm pd compares the VFM alone (the user's calibrate runs the defaults): add --vfm-only")
    methods = ("vfm",) if args.vfm_only else tuple(m for m in METHODS if not (args.no_corrected and m == "tikhonov_corrected"))
    n = 1 if args.quick else args.materials
    rng = np.random.default_rng(args.seed)
    materials = [(float(rng.uniform(500, 100000)), float(rng.uniform(0.15, 0.45))) for _ in range(n)]
    geometries = ["plate"] if args.quick else ["beam", "plate"] if args.geometry == "both" else [args.geometry]
    name = "from_fe_field" + ("_quick" if args.quick else "" if args.geometry == "both" else f"_{args.geometry}") \
        + ("_vfm" if args.vfm_only else "") + ("_pdwork" if args.vfm == "pd" else "")
    out, rows, terms, start = run_dir(name), [], {}, time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for i, (E, nu) in enumerate(materials):  # material-major: a partial run covers both geometries
            for geometry in geometries:
                t0 = time.perf_counter()
                x, y, u = fe_grid(geometry, E, nu)
                data_s = time.perf_counter() - t0
                for level in args.noise:
                    sigma = level * float(np.nanmax(np.abs(u)))
                    noisy = u + sigma * np.random.default_rng(1000 * i + 7).standard_normal(u.shape)
                    path = Path(tmp) / f"{geometry}_{i}.npz"
                    np.savez(path, x=x, y=y, u=noisy[:, 0].reshape(len(y), len(x)), v=noisy[:, 1].reshape(len(y), len(x)))
                    if geometry not in terms and not args.vfm_only:
                        terms[geometry] = error_term(path, geometry)
                        print(f"{geometry}: error term in {terms[geometry][1]:.1f} s, rank {terms[geometry][0].rank}, "
                              f"relative rms {terms[geometry][0].rms:.3g}", flush=True)
                    K, G = bp.moduli_from_young(E, nu)
                    truth = {"E": E, "nu": nu, "K": float(K), "G": float(G)}
                    res = run_case(path, geometry, sigma, terms.get(geometry, (None,))[0], args.seed + i, methods,
                                   args.vfm)
                    score(res, truth)
                    rows.append({"geometry": geometry, "material": i, "noise": level, "truth": truth,
                                 "fe_data_s": data_s, **res})
                    print(geometry, level, f"E={E:.0f} nu={nu:.3f}", {m: {k: f"{v:+.4f}" for k, v in res[m]["rel_error"].items()}
                                                                      for m in res},
                          "covers", res.get("laplace", {}).get("covers"), {m: round(res[m]["wall_time_s"], 1) for m in res},
                          flush=True)
                    write_metrics(name, summary(rows, args, n, geometries, terms, time.perf_counter() - start, methods))
    plot(rows, out / "error_vs_time.png", methods)


def summary(rows, args, n, geometries, terms, wall, methods=METHODS) -> dict:
    """metrics.json: the worst error per target (pass/fail), Laplace coverage and width, times."""
    chosen = {k: t for k, t in TARGETS.items() if k.rsplit("_", 1)[0] in methods}
    worst = {k: max(abs(r[k.rsplit("_", 1)[0]]["rel_error"][k.rsplit("_", 1)[1]]) for r in rows) for k in chosen}
    targets = {k: {"value": worst[k] if np.isfinite(worst[k]) else "failed on some case", "target": t,
                   "passed": bool(worst[k] <= t)} for k, t in chosen.items()}
    for k in ("E", "nu") if "laplace" in methods else ():
        covered = [r["laplace"]["covers"][k] for r in rows]
        targets[f"laplace_{k}_covers"] = {"value": float(np.mean(covered)), "count": f"{sum(covered)} of {len(rows)}",
                                          "target": "every 90 % interval covers the FE truth",
                                          "passed": bool(all(covered))}
    return {"wall_time_s": wall, "targets": targets,
            "laplace_median_rel_width": {k: float(np.median([r["laplace"]["rel_width"][k] for r in rows]))
                                         for k in ("E", "nu") if "laplace" in methods},
            "worst_by_case": worst_by_case(rows, methods),
            "median_wall_time_s": {m: float(np.median([r[m]["wall_time_s"] for r in rows])) for m in methods},
            "error_terms": {g: {"wall_time_s": t, "rank": term.rank, "rms_relative": term.rms, "fe_h": FE_TERM[g],
                                "fe_h_mesh_error": 2 * FE_TERM[g],
                                "design_nu": TERM_NUS.tolist()} for g, (term, t) in terms.items()},
            "settings": {"materials": n, "geometries": geometries, "noise": args.noise, "seed": args.seed,
                         "grid_h": GRID, "fe_h_data": FE_DATA, "delta_over_h": 3, "quick": args.quick,
                         "vfm_work": args.vfm, "methods": list(methods)},
            "runs": rows}


def worst_by_case(rows, methods) -> dict:
    """The worst |relative error| of each method's estimates per geometry and noise level, and the
    number of failed (no positive moduli) cases."""
    out = {}
    for key in sorted({(r["geometry"], r["noise"]) for r in rows}):
        case = [r for r in rows if (r["geometry"], r["noise"]) == key]
        out[f"{key[0]}_noise_{key[1]:g}"] = {
            m: {**{k: max(abs(r[m]["rel_error"][k]) for r in case) for k in case[0][m]["rel_error"]},
                "failed": sum("failed" in r[m] for r in case)} for m in methods}
    return out


def plot(rows, path, methods=METHODS):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(methods), figsize=(4 * len(methods), 3.6), sharey=True, squeeze=False)
    axes = axes[0]
    for ax, method in zip(axes, methods):
        for k, mark in zip(("E", "nu", "K", "G"), "os^v"):
            pts = [(r[method]["wall_time_s"], abs(r[method]["rel_error"][k])) for r in rows
                   if np.isfinite(r[method]["rel_error"].get(k, np.nan))]  # not absent, not a failed VFM
            if pts:
                ax.scatter(*zip(*pts), marker=mark, label=k)
        ax.axhline(TARGETS.get(f"{method}_K", 0.02), color="k", ls="--", lw=0.8)
        ax.set(xscale="log", yscale="log", xlabel="wall time (s)", title=method.replace("_", " "))
        ax.legend(fontsize=7)
    axes[0].set_ylabel("|relative error|")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
