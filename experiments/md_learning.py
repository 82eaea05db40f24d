"""Two-phase learning of an LPS surrogate of the MD graphene sheet (paper 004 sec. 4-5, issue 28 parts 3-4).

Reads the records of experiments/md_graphene_data.py (runs/md_graphene_data/). Phase 1: coarse-grains
the periodic sinusoidal (train, eq 5.1) and disk (validation, Table 1) sheets onto a 20 x 20 periodic
grid (h ~ 5 A, plain cone average: no cracks), learns (lambda, mu, D) (D_k in R) for each horizon
of a sweep and keeps the horizon with the smallest validation error (Algorithm 1 step 4), and
compares the learned 2D moduli with the MD sheet's own long-wave moduli (bayespd.learn.moduli).
Phase 2: s0 of the smoothed damage (eq 3.10) by simulation: the dynamic PD forward run of the
fracture record (experiments/scenes/md_fracture.py, bayespd.learn.forward) with a non-negative kernel
refitted at the chosen horizon, s0 minimising its displacement error over the first half of the
record (bayespd.learn.discrepancy); ``--surface``: phase 2 with the free-surface-corrected LPS of
eq 3.18 (bayespd.learn.free_surface) in place of the exact-kinematics LPS; then part 4's tests: the
second half, the pulse run, the 3.17 A grid, with the crack-length histories; a grid posterior of
eq 3.10's s0 and width eta from the training frames' displacements and crack lengths, with 90 %
predictive bands under six noise models, the one reported chosen by leave-future-out
on the training frames; the same phase 2 (without the damage posterior) at the paper's horizon
delta = 4 h as a reported variant (``phase2_paper_horizon``). Bayes: the posterior of
models/md_dispersion.py (nested Laplace: tau and delta by quadrature, delta's grid with every kink of
the partial-volume and influence weights as a point; the measured compliance per wave, a
structured model error, with a measurement error from the training records' off-orbit response;
models/md_kernel.py's nodal iid likelihood beside it, ``bayes_nodal``), 90 % predictive bands on
the validation loads (Table 1) and on the unseen loads (sinusoids off the training orbits; their
model error from bayespd.learn.wave_gp's GP over k with an amplitude growing in |k| h, fitted to the
training orbits; the response no compliance holds as a white floor), on a second, blind set of
them (``md_loads.blind_cases``, fixed after that floor was sized on the first), and the
moduli intervals. Writes runs/md_learning[_surface]/metrics.json with every error and wall time.
``--quick``: one horizon, few iterations.
"""
from __future__ import annotations

import time

import numpy as np
import torch

from common import quick_seed_arguments, run_dir, write_metrics
from bayespd.scenes.md_fracture import DEGREE, damage_posterior, evaluate, scene
from md_graphene_data import RESOLUTION
from bayespd.influence import Bernstein
from bayespd.learn import md, md_files
from bayespd.infer import NotPositiveDefiniteHessian, fit
from bayespd.infer.nested import nested_laplace
from bayespd.learn.coarse_grain import coarse_grain
from bayespd.learn.discrepancy import learn_s0, relative_error
from bayespd.learn.dispersion import (common_offset_posterior, common_offset_prior, error_field, measured_compliance,
                                      off_orbit_response, orbit_error_posterior, orbit_errors_on_lattice,
                                      relative_compliance_error, shell_of, unheld_response, unheld_response_sd,
                                      wave_power_share)
from bayespd.learn.kernel import UnsolvableKernel, learn_kernel, lps_params, relative_errors
from bayespd.learn.kernel_shape import KernelShape
from bayespd.learn.moduli import long_wave_moduli
from bayespd.learn.wave_gp import draw_errors, fit_wave_gp, frame_extrapolation
from bayespd.learn.periodic import PeriodicSheet, periodic_bonds, periodic_grid
from bayespd.materials.lps import LPS
from bayespd.linalg.sparse import NotPositiveDefiniteError
from bayespd.models.md_dispersion import md_dispersion
from bayespd.models.md_kernel import md_kernel

NAME = "md_learning"
DATA = run_dir("md_graphene_data") / "records"
NODES = 20        # a side: h = 5.04 x 4.90 A on the 100.9 x 98.0 A periodic box
HORIZONS = (1.5, 2.0, 2.5)  # delta / h swept (3 h: 5.8 % validation error, see docs/results.md)
INFLATION = np.round(np.arange(0.5, 20.0, 0.05), 2)  # band widening factors tried for a calibrated coverage
PAPER_HORIZON = 4.0  # delta / h of the paper's fracture tests (20 A on its 5 A grid): phase 2's reported variant
MODULI_TOLERANCE = 0.05
H, FINE = 5.0, 3.17  # A: the coarse grids of the fracture records (md_graphene_data.py)
S0_BOUNDS = (0.01, 1.0)
SHELLS = (0.5, 1.0, 1.5)  # |k| h edges of the model error's shells (training waves: |k| h 0.31-2.22)
TAU_GRID = np.geomspace(0.00125, 0.32, 9)  # tau, the common offset's scale: 0.125-32 %, steps of 2 (its log marginal spans ~10 steps of 2)
DELTA_GRID = np.linspace(10.5, 12.7, 23)  # A: delta's quadrature, the sheet's kinks added (end weights reported)
DELTA_GRID_QUICK = np.linspace(9.5, 10.3, 5)  # the quick run's (its sheet's delta_max is 2.5 h = 12.4 A)
# the paper's time-averaged relative errors (displacement, damage), sec. 5.2-5.3
PAPER = {"extrapolation": (0.27, 0.09), "pulse": (0.58, 0.15), "grid_3.17A": (0.19, 0.30)}


def record(kind: str, margin: float = 10.0):
    paths = sorted(DATA.glob(f"{kind}-*.nc"))
    if not paths:
        raise FileNotFoundError(f"no {kind} record in {DATA}: run experiments/md_graphene_data.py first")
    return md_files.read_md(paths[0], margin)


def coarse(ds, particles, out, name):
    """Nodal forces and displacements (loads, N, 2) of a periodic record, cached in ``out``."""
    path = out / f"coarse_{name}.npz"
    if not path.exists():
        cg = coarse_grain(particles.x, ds["X"].values, ds["M"].values, ds["U"].values, ds["B"].values,
                          2 * particles.h, float(particles.volume[0]), weno=False, box=ds.attrs["box"])
        np.savez(path, u=cg.u, b=cg.b, rho=cg.rho)
    z = np.load(path)
    return torch.as_tensor(z["b"] * particles.volume[0]), torch.as_tensor(z["u"])


def phase_one(quick: bool, out):
    train, val = record("static_train"), record("static_validation")
    box = train.attrs["box"]
    particles = periodic_grid(box, NODES)
    h = particles.h
    (f_train, u_train), (f_val, u_val) = coarse(train, particles, out, "train"), coarse(val, particles, out, "validation")
    horizons = HORIZONS[1:2] if quick else HORIZONS
    bonds = periodic_bonds(particles, box, 1.25 * max(horizons) * h)  # room for the posterior over delta
    sheet = PeriodicSheet(LPS(particles, bonds, plane="strain", influence=Bernstein(DEGREE)), box)
    sweep = []
    for ratio in horizons:
        fit = learn_kernel(sheet, f_train, u_train, ratio * h, maxiter=10 if quick else 300)  # D_k in R (eq 4.2)
        t = time.perf_counter()
        val_err = relative_errors(sheet, fit.params(), f_val, u_val, spectral=False).detach().numpy()
        train_err = relative_errors(sheet, fit.params(), f_train, u_train).detach().numpy()
        sweep.append({"delta_over_h": ratio, "delta_A": ratio * h, "lambda": fit.lam, "mu": fit.mu, "D": fit.D,
                      "coercivity": fit.coercivity, "train_rel_error_mean": float(train_err.mean()),
                      "validation_rel_error_mean": float(val_err.mean()), "validation_rel_error": val_err,
                      "iterations": fit.iterations, "converged": fit.converged, "message": fit.message,
                      "fit_wall_time_s": fit.wall_time_s, "validation_wall_time_s": time.perf_counter() - t})
        print({k: v for k, v in sweep[-1].items() if k != "validation_rel_error"}, flush=True)
    best = min(sweep, key=lambda s: s["validation_rel_error_mean"])
    # phase 2's damaged LPS needs a non-negative kernel (bayespd.learn.kernel): refit one at delta*
    fit = learn_kernel(sheet, f_train, u_train, best["delta_A"], positive_kernel=True, maxiter=10 if quick else 300)
    val_err = relative_errors(sheet, fit.params(), f_val, u_val).detach().numpy()
    non_negative = {"lambda": fit.lam, "mu": fit.mu, "D": fit.D, "delta_A": fit.delta, "misfit": fit.misfit,
                    "validation_rel_error_mean": float(val_err.mean()), "fit_wall_time_s": fit.wall_time_s}
    md = long_wave_moduli(train)
    learned = {"lambda_plus_2mu": best["lambda"] + 2 * best["mu"], "mu": best["mu"]}
    rel = {k: abs(learned[k] - md[k]) / md[k] for k in learned}
    data = {"sheet": sheet, "train": (f_train, u_train), "validation": (f_val, u_val),
            "unseen": coarse(record("static_unseen"), particles, out, "unseen"),
            "blind": coarse(record("static_blind"), particles, out, "blind")}
    return {"h_A": h, "box_A": box, "sweep": sweep, "best": best, "non_negative_at_best": non_negative,
            "md_moduli_eV_per_A2": md,
            "learned_moduli_eV_per_A2": learned, "moduli_rel_error": rel}, data


def coarse_pulse(out, nodes, h):
    """The pulse record WENO-coarse-grained onto ``nodes`` as md_graphene_data does the fracture
    record (cached in ``out``)."""
    path = out / "coarse_pulse_h5_weno.npz"
    if not path.exists():
        ds = record("pulse", margin=20.0)
        cg = coarse_grain(nodes, ds["X"].values, ds["M"].values, ds["U"].values, ds["B"].values, 2 * h, h * h,
                          weno=True, band=0.75 * md.A0, resolution=RESOLUTION)
        np.savez(path, nodes=nodes, u=cg.u, rho=cg.rho, b=cg.b, time=ds["time"].values)
    return np.load(path)


def phase_two(kernel, quick, out, surface: bool, diagnostics: bool = True):
    """s0 by simulation (bayespd.learn.discrepancy) on the first half of the fracture record (5 A
    WENO grid), then the paper's tests: (i) the second half, (ii) the pulse run, (iii) the 3.17 A
    grid with delta and s0 rescaled (paper sec. 5.3: delta / h fixed, s0 ~ delta^-1/2);
    ``diagnostics``: also the pre-crack operator comparison and the grid posterior of (s0, eta)."""
    source = run_dir("md_graphene_data")
    z, fracture = np.load(source / "coarse_h5_weno.npz"), record("fracture")
    sc = scene(z, fracture, kernel, H, pulled=True, surface=surface)
    half = (len(sc.time) + 1) // 2
    free = ~sc.fixed
    intact = int(np.flatnonzero(~np.isnan(sc.tip))[0])  # frames before the first MD bond breaks
    pre_crack = {}
    for name, corrected in (("exact_kinematics_lps", False), ("free_surface_eq3_18", True)) if diagnostics else ():
        t = time.perf_counter()
        run = scene(z, fracture, kernel, H, pulled=True, surface=corrected).run(None, intact)
        pre_crack[name] = {"displacement_rel_error": relative_error(run.u, sc.u[:intact], free),
                           "wall_time_s": time.perf_counter() - t}
    if diagnostics:
        print({"pre_crack_frames": intact, **pre_crack}, flush=True)

    def discrepancy(s0):
        return relative_error(sc.run(s0, half).u, sc.u[:half], free)

    found = learn_s0(discrepancy, bounds=S0_BOUNDS, xatol=0.2 if quick else 0.02)
    print({"s0": found.s0, "error": found.error, "intact": found.error_intact}, flush=True)
    tests = {"extrapolation": evaluate(sc, found.s0, slice(half, None)),
             "extrapolation_no_damage": evaluate(sc, None, slice(half, None))}
    t = time.perf_counter()
    zp = coarse_pulse(out, z["nodes"], H)
    pulse_cg = time.perf_counter() - t
    pulse = scene(zp, record("pulse", margin=20.0), kernel, H, pulled=False, surface=surface)
    tests["pulse"] = evaluate(pulse, found.s0)
    tests["pulse"]["coarse_graining_wall_time_s"] = pulse_cg
    fine = {**kernel, "delta_A": kernel["delta_A"] * FINE / H}
    s0_fine = float(found.s0 * np.sqrt(H / FINE))
    finer = scene(np.load(source / "coarse_h3.17_weno.npz"), fracture, fine, FINE, pulled=True, surface=surface)
    tests["grid_3.17A"] = evaluate(finer, s0_fine)
    for name, test in tests.items():
        print(name, {k: v for k, v in test.items() if not k.startswith("crack") and not k.endswith("diagnosis")}, flush=True)
    posterior = None
    if diagnostics:
        t = time.perf_counter()
        posterior = damage_posterior(sc, half, S0_BOUNDS, draws=40 if quick else 200,
                                     others={"pulse": (pulse, 1.0), "grid_3.17A": (finer, np.sqrt(H / FINE))})
        posterior["wall_time_s"] = time.perf_counter() - t
        print({k: {a: b for a, b in v.items() if not a.startswith(("crack", "log_evidence"))}
               for k, v in posterior.items() if isinstance(v, dict)}, "chosen:", posterior["chosen"], flush=True)
    return {"s0": found.s0, "training_displacement_rel_error": found.error,
            "training_displacement_rel_error_no_damage": found.error_intact,
            "evaluations": [{"s0": s, "error": e} for s, e in found.evaluations], "fit_wall_time_s": found.wall_time_s,
            "training_frames": half, "free_nodes": int(free.sum()), "kernel": kernel, "surface_eq3_18": surface,
            "pre_crack_frames": intact, "pre_crack_no_damage": pre_crack or None, "s0_3.17A": s0_fine,
            "tests": tests, "damage_posterior": posterior}


def paper_horizon(data, quick, out):
    """Phase 2 at the paper's horizon delta = 4 h (a reported variant; the default stays the validated
    delta*): phase 1's non-negative kernel refitted at 4 h on the training loads, s0 learned on the
    first half exactly as the default, then tests (i)-(iii) (the 3.17 A grid at 4 x 3.17 A)."""
    sheet = data["sheet"]
    particles, h = sheet.material.particles, sheet.material.particles.h
    delta = PAPER_HORIZON * h
    t = time.perf_counter()
    wide = PeriodicSheet(LPS(particles, periodic_bonds(particles, sheet.box, delta), plane="strain",
                             influence=Bernstein(DEGREE)), sheet.box)
    bonds_wall = time.perf_counter() - t
    (f_train, u_train), (f_val, u_val) = data["train"], data["validation"]
    fit = learn_kernel(wide, f_train, u_train, delta, positive_kernel=True, maxiter=10 if quick else 300)
    kernel = {"lambda": fit.lam, "mu": fit.mu, "D": fit.D, "delta_A": fit.delta, "misfit": fit.misfit,
              "train_rel_error_mean": float(relative_errors(wide, fit.params(), f_train, u_train).detach().mean()),
              "validation_rel_error_mean": float(relative_errors(wide, fit.params(), f_val, u_val).detach().mean()),
              "fit_wall_time_s": fit.wall_time_s, "bonds_wall_time_s": bonds_wall, "iterations": fit.iterations}
    print({"paper_horizon_kernel": kernel}, flush=True)
    t = time.perf_counter()
    two = phase_two(kernel, quick, out, surface=False, diagnostics=False)
    two["wall_time_s_total"] = time.perf_counter() - t
    return {"delta_over_h": PAPER_HORIZON, **two}


def kernel_init(best, plane: KernelShape) -> dict:
    """Start values of the kernel sites at the phase-1 fit ``best``."""
    return {"lam_plus_mu": best["lambda"] + best["mu"], "mu": best["mu"], "delta": best["delta_A"],
            "shape": plane.coordinates(best["D"])}


def compliance_model(best, data):
    """models/md_dispersion.py on the training records: (model, {"C": measured compliances}, start
    values at the phase-1 fit ``best``, (orbits, off-diagonal flags, off-orbit response, sigma_m))."""
    sheet = data["sheet"]
    f, u = data["train"]
    y = sheet.zero_mean(u)
    n = int(round(np.sqrt(sheet.n)))
    modes, C, off = measured_compliance(f, y, n)
    harmonics = off_orbit_response(f, y, n)
    sigma_m = float(harmonics.pow(2).mean().sqrt())  # the rms response no compliance holds
    model = md_dispersion(sheet, modes * 2 * np.pi / sheet.box, off, SHELLS, nominal=best["mu"], measurement=sigma_m)
    init = {**kernel_init(best, KernelShape(sheet.material.influence)),
            "s": np.full(len(SHELLS) + 1, best["train_rel_error_mean"]), "tau": best["train_rel_error_mean"]}
    return model, {"C": C}, init, (modes, off, harmonics, sigma_m)


def quadrature_grids(sheet, quick: bool = False) -> dict:
    """The nested Laplace's grids: tau's, and delta's with every kink of the sheet's weights in its range."""
    delta = DELTA_GRID_QUICK if quick else DELTA_GRID
    return {"tau": TAU_GRID, "delta": np.union1d(delta, sheet.material.bonds.kinks(delta[0], delta[-1]))}


def bayes(best, data, md_moduli, quick, structured=True):
    """Posterior of models/md_dispersion.py (``structured``: one relative compliance error
    per orbit of the training waves on shells of |k| h plus an offset common to all, from the
    measured compliance, with a measurement error sigma_m fixed from the training records'
    off-orbit response) or of models/md_kernel.py (nodal iid relative noise) at the phase-1 fit;
    90 % predictive bands on the validation loads (Table 1's disks) and on the unseen and blind loads
    (sinusoids on waves the training set lacks): parameter draws + the model's error term (the
    structured model's common offset drawn from its conditional posterior given the draw and the
    training compliances, plus the predicted record's own measurement error; at the waves without a
    training orbit the error drawn from bayespd.learn.wave_gp's GP (amplitude growing in |k| h)
    conditional given the training orbits', widened by its frame test, on the training waves the
    shells' draw; plus the response no compliance holds, white, of the size of the training records'
    part beyond their measured compliance on the shells of |k| h the load excites
    (``unheld_response_sd``); for comparison the same
    without that floor, the stationary GP widened by its own frame test (the previous default), the
    shells' draw everywhere, the offset from its prior N(0, tau^2), the training waves' own model
    errors fixed at their conditional given the draw's measured ones, and the growing GP everywhere
    as fitted); their node coverage and width; whether the 90 %
    intervals of the 2D moduli hold the MD sheet's."""
    sheet = data["sheet"]
    f, u = data["train"]
    y = sheet.zero_mean(u)
    n, h = int(round(np.sqrt(sheet.n))), sheet.material.particles.h
    plane = KernelShape(sheet.material.influence)
    if structured:
        model, observed, init, (modes, off, harmonics, sigma_m) = compliance_model(best, data)
        C, names = observed["C"], ("s", "tau")
    else:
        model = md_kernel(sheet, f, y.pow(2).mean((1, 2)).sqrt(), nominal=best["mu"], positive_kernel=False)
        init = {**kernel_init(best, plane), "sigma": best["train_rel_error_mean"]}
        observed, names = {"y": y}, ("sigma",)
    t = time.perf_counter()
    if structured:  # tau, the scale of one 3-number offset, barely informed (its joint MAP collapses), and delta,
        # on which the potential is kinked (its conditional posterior peaks on a kink), by quadrature
        nested = nested_laplace(model, observed, quadrature_grids(sheet, quick), init, 40 if quick else 200, seed=0,
                                log=("tau",))
        draws = dict(nested["draws"])
        nested.pop("draws")
    else:
        tree = fit(model, observed, "laplace", num_samples=40 if quick else 200, seed=0, progress=False,
                   predictive=False, observed=next(iter(observed)),
                   init_values={k: torch.as_tensor(v) for k, v in init.items()})
        post = tree["posterior"]
        draws = {k: post[k].values.reshape(-1, *post[k].shape[2:]) for k in ("lam_plus_mu", "mu", "delta", "shape", *names)}
    wall = time.perf_counter() - t
    draws["D"] = plane.coefficients(torch.as_tensor(draws["shape"])).numpy()
    draws["lambda"] = draws["lam_plus_mu"] - draws["mu"]
    draws["lambda_plus_2mu"] = draws["lam_plus_mu"] + draws["mu"]
    sets = {name: (fv, sheet.zero_mean(uv).numpy()) for name, (fv, uv) in
            (("validation", data["validation"]), ("unseen", data["unseen"]), ("blind", data["blind"]))}
    fv = torch.cat([fs for fs, _ in sets.values()])
    yv = np.concatenate([ys for _, ys in sets.values()])
    sv = np.sqrt((yv**2).mean((1, 2)))
    k_all = sheet.wavevectors
    shell = shell_of(k_all.numpy(), h, SHELLS)
    rng, generator = np.random.default_rng(0), torch.Generator().manual_seed(0)
    compare = torch.Generator().manual_seed(1)  # the comparison bands' own stream: the default's draws do not depend on them
    if structured:
        k_train = torch.as_tensor(modes * 2 * np.pi / sheet.box)
        train_shell = shell_of(k_train.numpy(), h, SHELLS)
        gp, stationary, gp_wall = _wave_gp(sheet, draws, modes, k_train, C, off, train_shell, sigma_m)
        quadrant = np.array([(i, j) for i in range(n // 2 + 1) for j in range(n // 2 + 1) if i or j])
        k_quadrant, waves = torch.as_tensor(quadrant * 2 * np.pi / sheet.box), torch.Generator().manual_seed(2)
        new = ~(quadrant[:, None] == modes[None]).all(-1).any(1)  # the waves without a training orbit
        unheld = unheld_response_sd(f, y, fv, shell, n, len(SHELLS) + 1)  # training records only
    pred, bare, still, shells, fresh, pinned, smooth, inadmissible = [], [], [], [], [], [], [], 0
    t = time.perf_counter()
    for k in range(len(draws["mu"])):  # every draw: the 5-95 % quantiles of n draws hold a new draw of the same law
        # with probability (q95 - q05 order positions) / (n + 1): 0.891 for n = 200, 0.865 for the 50 used before
        p = lps_params(draws["lambda"][k], draws["mu"][k], draws["D"][k], draws["delta"][k])
        try:
            with torch.no_grad():
                mean = sheet.spectral_solve(p, fv).numpy()
                if structured:  # the model error of the dispersion: a relative compliance error per wavevector
                    s_k, tau_k = torch.as_tensor(draws["s"][k]), float(draws["tau"][k])
                    S_all = sheet.symbol(p, k_all)
                    Delta, _ = relative_compliance_error(sheet.symbol(p, k_train), C)
                    total = (s_k[train_shell] ** 2 + sigma_m**2).sqrt()
                    offset = common_offset_posterior(Delta, total, tau_k, off).sample(generator)
                    shells.append(mean + error_field(S_all, fv, s_k[shell], offset, n, generator, measurement=sigma_m).numpy())
                    field = offset + draw_errors(gp["gp"], k_train * h, Delta - offset, off, sigma_m, k_quadrant[new] * h,
                                                 waves, gp["inflation"])  # off the training orbits: the GP, widened as its frame test says
                    error = error_field(S_all, fv, s_k[shell], offset, n, waves, measurement=sigma_m,
                                        known=orbit_errors_on_lattice(quadrant[new], field, n)).numpy()
                    bare.append(mean + error)
                    error = unheld_response(torch.as_tensor(mean + error), unheld, waves).numpy() - mean
                    field = offset + draw_errors(stationary["gp"], k_train * h, Delta - offset, off, sigma_m,
                                                 k_quadrant[new] * h, compare, stationary["inflation"])
                    still.append(mean + error_field(S_all, fv, s_k[shell], offset, n, compare, measurement=sigma_m,
                                                    known=orbit_errors_on_lattice(quadrant[new], field, n)).numpy())
                    fresh.append(mean + error_field(S_all, fv, s_k[shell], common_offset_prior(tau_k).sample(compare),
                                                    n, compare, measurement=sigma_m).numpy())
                    known = orbit_error_posterior(Delta, s_k[train_shell], sigma_m, offset).sample(compare)
                    pinned.append(mean + error_field(S_all, fv, s_k[shell], offset, n, compare, measurement=sigma_m,
                                                     known=orbit_errors_on_lattice(modes, known, n)).numpy())
                    field = offset + draw_errors(gp["gp"], k_train * h, Delta - offset, off, sigma_m, k_quadrant * h, waves)
                    smooth.append(mean + error_field(S_all, fv, s_k[shell], offset, n, waves, measurement=sigma_m,
                                                     known=orbit_errors_on_lattice(quadrant, field, n)).numpy())
                else:
                    error = draws["sigma"][k] * sv[:, None, None] * rng.standard_normal(mean.shape)
        except (ValueError, NotPositiveDefiniteError):  # a Gaussian draw outside the admissible kernels
            inadmissible += 1
            continue
        pred.append(mean + error)
    predictive_wall = time.perf_counter() - t

    def band(samples, rows):  # node coverage (pooled, per load) and mean width / load RMS of the 90 % band on ``rows``,
        # and the factor about the median by which the band would have to widen to hold 80 % and 90 % of the nodes
        lo, mid, hi = np.quantile(np.array(samples)[:, rows], [0.05, 0.5, 0.95], axis=0)
        y_, s_ = yv[rows], sv[rows]
        widen = {}
        for target in (0.8, 0.9):
            held = [c for c in INFLATION if ((y_ >= mid - c * (mid - lo)) & (y_ <= mid + c * (hi - mid))).all(-1).mean()
                    >= target]
            widen[f"widening_for_{target:.0%}"] = held[0] if held else None
        inside = ((y_ >= lo) & (y_ <= hi)).all(-1)
        return {"node_coverage": float(inside.mean()), "load_node_coverage": inside.mean(1).tolist(),
                "width_rel": float(((hi - lo) / s_[:, None, None]).mean()), **widen}

    at, bands, ranges = 0, {}, {}
    for name, (fs, _) in sets.items():
        rows = ranges[name] = slice(at, at + len(fs))
        at += len(fs)
        bands[name] = {"default": band(pred, rows)}
        if structured:
            bands[name] |= {"no_unheld_response": band(bare, rows), "stationary_gp": band(still, rows),
                            "shells": band(shells, rows), "prior_offset": band(fresh, rows),
                            "training_waves_known": band(pinned, rows), "wave_gp": band(smooth, rows),
                            **_training_wave_share(fs, yv[rows], np.array(pinned)[:, rows], modes, n)}
    summary = {k: {"mean": np.mean(v, 0).tolist(), "sd": np.std(v, 0).tolist(), "q05": np.quantile(v, 0.05, 0).tolist(),
                   "q95": np.quantile(v, 0.95, 0).tolist()} for k, v in draws.items() if k not in ("shape", "D")}
    covers = {k: bool(summary[k]["q05"] <= md_moduli[k] <= summary[k]["q95"]) for k in ("lambda_plus_2mu", "mu")}
    return {"method": ("nested Laplace: tau (log grid) and delta (grid with its kinks) by quadrature, the rest Laplace "
                       "given them" if structured else "laplace (exact Hessian at the MAP)"),
            "quadrature": nested if structured else None,
            "likelihood": ("measured compliance per orbit: relative error per shell of |k| h + common offset "
                           "+ measurement error" if structured else "nodal iid relative noise"),
            "measurement_error": {"sd": sigma_m, "off_orbit_response": harmonics.tolist(),
                                  "off_orbit_response_median": float(harmonics.median())} if structured else None,
            "unheld_response_sd": {name: unheld[rows].tolist() for name, rows in ranges.items()} if structured else None,
            "wave_gp": {"growing": _gp_summary(gp), "stationary": _gp_summary(stationary),
                        "log_evidence_growing_minus_stationary": gp["gp"].log_marginal - stationary["gp"].log_marginal,
                        "fit_wall_time_s": gp_wall} if structured else None,
            "shells_kh": SHELLS if structured else None, "wall_time_s": wall, "predictive_wall_time_s": predictive_wall,
            "draws": len(draws["mu"]), "posterior": summary,
            "validation_band90_node_coverage": bands["validation"]["default"]["node_coverage"],
            "validation_band90_width_rel": bands["validation"]["default"]["width_rel"], "bands90": bands,
            "moduli_interval90_covers_md": covers, "predictive_draws": len(pred), "inadmissible_draws": inadmissible}


FRAMES = 3  # the frame tests pooled: the outer 3 frames of training orbits (the inner sets: 8, 15, 24 orbits)


def _wave_gp(sheet, draws, modes, k_train, C, off, train_shell, sigma_m):
    """bayespd.learn.wave_gp's GPs fitted to the training orbits' relative errors, less their common
    offset, at the posterior mean of the parameters: the growing one (the default) and the
    stationary one (the previous default), each with the widening one lattice step of
    extrapolation needs inside the training set (the rms z-score of the outer ``FRAMES`` frames,
    pooled, each under the GP conditioned on the orbits inside it: the growing GP with its
    hyperparameters from every frame, as the inner frames alone show no growth (max(n1, n2) <= 3
    and <= 4: g -> 0 or +1.6 nats); the stationary GP refitted to the inner orbits as before,
    outermost frame only); and the wall time."""
    t = time.perf_counter()
    mean = {k: np.mean(np.asarray(draws[k]), 0) for k in ("lambda", "mu", "D", "delta", "s", "tau")}
    Delta, _ = relative_compliance_error(sheet.symbol(lps_params(mean["lambda"], mean["mu"], mean["D"], mean["delta"]),
                                                      k_train), C)
    total = (torch.as_tensor(mean["s"])[train_shell] ** 2 + sigma_m**2).sqrt()
    offset = common_offset_posterior(Delta, total, float(mean["tau"]), off).mean
    kh, error = k_train * sheet.material.particles.h, Delta - offset
    gp = fit_wave_gp(kh, error, off, sigma_m, growing=True)
    last = int(modes.max())
    z = {f: frame_extrapolation(modes, kh, error, off, sigma_m, True, f, gp) for f in range(last - FRAMES + 1, last + 1)}
    growing = {"gp": gp, "inflation": float(torch.cat(list(z.values())).pow(2).mean().sqrt()),
               "frame_z_rms": {f: float(v.pow(2).mean().sqrt()) for f, v in z.items()}}
    z = frame_extrapolation(modes, kh, error, off, sigma_m)
    rms = float(z.pow(2).mean().sqrt())
    stationary = {"gp": fit_wave_gp(kh, error, off, sigma_m), "inflation": rms, "frame_z_rms": {last: rms}}
    return growing, stationary, time.perf_counter() - t


def _gp_summary(fitted):
    """A fitted GP's hyperparameters, log evidence, frame z-scores and widening for metrics.json."""
    return {**fitted["gp"]._asdict(), "frame_extrapolation_z_rms": fitted["frame_z_rms"],
            "widening": fitted["inflation"]}


def _training_wave_share(forces, y, pinned, modes, n):
    """What loads share with the training waves: each load's power on the training orbits' lattice
    wavevectors, and the relative error of the mean prediction with those waves' model errors fixed
    (there it is about the measured compliance times the load, whatever the draw)."""
    mean = pinned.mean(0)
    error = np.sqrt(((mean - y) ** 2).sum((1, 2)) / (y**2).sum((1, 2)))
    return {"load_power_share_training_waves": wave_power_share(forces, modes, n).tolist(),
            "measured_compliance_rel_error": error.tolist(), "measured_compliance_rel_error_mean": float(error.mean())}


def main():
    args = quick_seed_arguments(__doc__, "one horizon, 10 iterations",
                                {"--surface": "phase 2 with the free-surface-corrected LPS (eq 3.18)"})
    torch.manual_seed(args.seed)
    start = time.perf_counter()
    run_name = NAME + ("_surface" if args.surface else "") + ("_quick" if args.quick else "")
    out = run_dir(run_name)
    one, data = phase_one(args.quick, out)
    t = time.perf_counter()
    two = phase_two(one["non_negative_at_best"], args.quick, out, args.surface)
    two["wall_time_s_total"] = time.perf_counter() - t
    variant = paper_horizon(data, args.quick, out) if not args.surface else None
    posteriors = {}
    for name, structured in (("bayes", True), ("bayes_nodal", False)):
        try:
            posteriors[name] = bayes(one["best"], data, one["md_moduli_eV_per_A2"], args.quick, structured)
        except (UnsolvableKernel, NotPositiveDefiniteHessian) as error:  # the MAP search stepped onto a kernel
            # with m <= 0, or found no positive-definite mode: recorded, not raised (docs/results.md)
            posteriors[name] = {"failed": str(error), "validation_band90_node_coverage": None,
                                "moduli_interval90_covers_md": {}}
        print(name, posteriors[name], flush=True)
    posterior = posteriors["bayes"]
    targets = {f"moduli_{k}_within_5pct": {"value": v, "target": MODULI_TOLERANCE, "passed": v <= MODULI_TOLERANCE}
               for k, v in one["moduli_rel_error"].items()}
    cover = posterior["validation_band90_node_coverage"]
    targets["validation_band90_covers_80pct_nodes"] = {"value": cover, "target": 0.8,
                                                       "passed": cover is not None and cover >= 0.8}
    for name in ("unseen", "blind"):  # blind: loads fixed after the unseen bands' model error was sized on the unseen set
        cover = posterior.get("bands90", {}).get(name, {}).get("default", {}).get("node_coverage")
        targets[f"{name}_band90_covers_80pct_nodes"] = {"value": cover, "target": 0.8,
                                                        "passed": cover is not None and cover >= 0.8}
    for k in ("lambda_plus_2mu", "mu"):
        covered = posterior["moduli_interval90_covers_md"].get(k)
        targets[f"moduli_{k}_interval90_covers_md"] = {"value": covered, "target": True, "passed": bool(covered)}
    if posterior.get("quadrature"):  # the grids of tau and delta hold the posterior: little weight at their ends
        ends = max(max(m["end_weights"]) for m in posterior["quadrature"]["marginals"].values())
        targets["quadrature_end_weights_below_1pct"] = {"value": ends, "target": 0.01, "passed": ends <= 0.01}
    inside = S0_BOUNDS[0] * 1.05 < two["s0"] < S0_BOUNDS[1] / 1.05
    targets["s0_interior_minimum"] = {"value": two["s0"], "target": f"inside {S0_BOUNDS}", "passed": inside}
    damage = two["damage_posterior"]
    if damage:  # the noise model chosen on the training frames alone (leave-future-out); the others are in metrics.json
        chosen = damage[damage["chosen"]]
        for value, target in ((chosen["extrapolation_band90_node_frame_coverage"], "displacement_band90_covers_80pct_node_frames"),
                              (chosen["pulse"]["band90_node_frame_coverage"], "pulse_displacement_band90_covers_80pct_node_frames"),
                              (chosen["grid_3.17A"]["band90_node_frame_coverage"],
                               "grid_3.17A_displacement_band90_covers_80pct_node_frames"),
                              (chosen["crack_length_md_inside_band_share_of_forecast_frames"],
                               "crack_length_forecast_band90_covers_md_80pct_frames")):
            targets[target] = {"value": value, "target": 0.8, "passed": value >= 0.8, "noise_model": damage["chosen"]}
    for test, (disp, dmg) in PAPER.items():
        e = two["tests"][test]["frames" if test == "extrapolation" else "whole_record"]
        for kind, paper in (("displacement", disp), ("damage", dmg)):
            v = e[f"{kind}_rel_error" if kind == "displacement" else "damage_eq54_rel_error"]
            targets[f"{test}_{kind}_error_vs_paper"] = {"value": v, "target": paper,
                                                         "passed": v is not None and v <= paper}
    write_metrics(run_name, {
        "wall_time_s": time.perf_counter() - start, "phase1": one, "phase2": two, "phase2_paper_horizon": variant,
        **posteriors,
        "targets": targets,
        "settings": {"surface_eq3_18": args.surface, "nodes": NODES, "degree": DEGREE, "alpha": 0.0, "horizons_over_h": HORIZONS,
                     "coarse_graining": "plain cone, R = 2h, periodic", "plane": "strain, thickness 1 (2D moduli)"}})


if __name__ == "__main__":
    main()
