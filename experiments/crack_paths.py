"""Crack-path distribution of a pre-notched plate in mode I tension under Brownian forcing
(Dodwell 2019 eq 4): a deterministic quasi-static run (You 2023 §5.2) gives the straight crack;
stochastic realisations give a damage-probability map, crack paths and crack lengths.
Writes runs/crack_paths/ (metrics.json, realisations.nc, PNG figures).

    python experiments/crack_paths.py [--quick] [--realisations N]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import scipy.sparse.linalg as sla
import torch

import common  # noqa: F401  (one torch thread, repository root on sys.path)
from common import run_dir, write_metrics

import bayespd as bp
from bayespd.linalg import sparse
from bayespd.atomic import atomic_path
from bayespd.damage import CriticalStretch, crack_length, crack_path
from bayespd.solvers import white_noise
from bayespd.solvers.fracture import StochasticFracture
from bayespd.solvers.body import LoadedBody
from bayespd.solvers.quasistatic import quasi_static

SIDE, H, M = 40.0, 1.0, 3  # plate side and spacing (mm), horizon delta = M h
E, G0 = 3000.0, 0.5  # MPa (bond-based plane stress: E = K, nu = 1/3), fracture energy N/mm
DELTA = M * H
S0 = float(np.sqrt(4 * np.pi * G0 / (9 * E * DELTA)))  # 2D PMB critical stretch (plane stress)
Y_NOTCH = SIDE / 2
LIGAMENT = SIDE / 2  # from the notch tip to the right edge
THRESHOLD = 0.4  # phi above which a particle counts as cracked (damage-probability map)
PATH_THRESHOLD = 0.3  # for tracing paths: faces of a straight crack have phi = 0.44 (delta = 3h),
# the next rows 0.25; on a kinked crack the faces drop to 0.3-0.4 and 0.4 cuts the path apart
SIGMA, RELAX, DT = 1500.0, 1e4, 1.0  # noise scale, M dt lambda_min(A), time step
PARAMS = {"K": E, "delta": DELTA}


def plate() -> bp.Scene:
    """Notch from the left edge to the centre (between particle rows); bottom layer clamped,
    top layer pulled up by lambda mm; the critical stretch S0 and white noise C = SIGMA^2 I."""
    p = bp.grid_2d(SIDE, SIDE, H)
    bonds = bp.precrack(p, bp.find_bonds(p, DELTA), [[0.0, Y_NOTCH], [SIDE / 2, Y_NOTCH]])
    bcs = [bp.Dirichlet.layer(p, "bottom", DELTA), bp.Dirichlet.layer(p, "top", DELTA, (0.0, 1.0))]
    return bp.Scene(bp.BondBased(p, bonds), bcs, damage=CriticalStretch(S0),
                    noise=lambda dofs: white_noise(SIGMA, len(dofs)))


def ramp(scene: bp.Scene, body: LoadedBody, steps: int) -> np.ndarray:
    """Top displacements up to twice the elastic estimate of initiation, s0 / max s(u at 1 mm)."""
    u1 = quasi_static(scene, PARAMS, [1e-3]).u / 1e-3
    initiation = S0 / float(body.kinematics.stretch(u1).max())
    return np.linspace(2 / steps, 2.0, steps) * initiation


def mobility(body: LoadedBody) -> float:
    """M = sigma^2 / eta with M dt lambda_min(A) = RELAX: one step relaxes the elastic field
    (lambda_min by shift-invert Lanczos from a fixed start vector, so a run repeats to the bit)."""
    intact = torch.ones(body.n_bonds)
    A = body.operator(intact, body.active(intact))
    v0 = np.ones(A.shape[0])
    return RELAX / (DT * float(sla.eigsh(A, k=1, sigma=0, v0=v0, return_eigenvectors=False)[0]))


def deviation(path: np.ndarray) -> float:
    return float(np.abs(path[:, 1] - Y_NOTCH).max()) if len(path) else float("nan")


def failure_load(loads: np.ndarray, lengths: np.ndarray) -> float:
    """The load at which the crack has grown through half the ligament (the reaction under
    Brownian forcing is too noisy for its peak to locate failure)."""
    k = np.flatnonzero(np.asarray(lengths) >= LIGAMENT / 2)
    return float(loads[k[0]]) if len(k) else float("nan")


def summary(run, seed: int, wall: float) -> dict:
    k, f = run.peak, run.first_failure
    return {"seed": seed, "wall_time_s": wall, "steps": len(run.t),
            "failure_load_mm": failure_load(run.load_factor, run.crack_length),
            "peak_reaction_N": float(run.reaction[k, 1]), "peak_reaction_load_mm": float(run.load_factor[k]),
            "first_failure_time": None if f is None else float(run.t[f]),
            "first_failure_load_mm": None if f is None else float(run.load_factor[f]),
            "crack_length_mm": crack_length(run.path), "max_deviation_mm": deviation(run.path)}


def stats(a: np.ndarray) -> dict:
    return {"mean": float(a.mean()), "sd": float(a.std()), "min": float(a.min()), "max": float(a.max())}


def padded(arrays, fill=np.nan) -> np.ndarray:
    """Stack arrays of different first lengths, padding with ``fill``."""
    n = max(len(a) for a in arrays)
    out = np.full((len(arrays), n, *np.shape(arrays[0])[1:]), fill, dtype=float)
    for i, a in enumerate(arrays):
        out[i, :len(a)] = a
    return out


def save(out, body, qs, qs_path, qs_lengths, runs, rows, probability):
    import xarray as xr
    seeds = [r["seed"] for r in rows]
    comp = ["x", "y"]
    ds = xr.Dataset(
        {"position": (("particle", "component"), body.particles.x),
         "probability": ("particle", probability),
         "phi": (("realisation", "particle"), np.stack([r.phi for r in runs])),
         "t": (("realisation", "step"), padded([r.t for r in runs])),
         "load_mm": (("realisation", "step"), padded([r.load_factor for r in runs])),
         "reaction_N": (("realisation", "step", "component"), padded([r.reaction for r in runs])),
         "broken": (("realisation", "step"), padded([r.broken for r in runs], -1).astype(np.int64)),
         "crack_length_mm": (("realisation", "step"), padded([r.crack_length for r in runs])),
         "path": (("realisation", "point", "component"), padded([r.path for r in runs])),
         **{k: ("realisation", np.array([np.nan if r[k] is None else r[k] for r in rows], dtype=float))
            for k in rows[0] if k != "seed"},
         "qs_load_mm": ("qs_step", qs.load_factors),
         "qs_reaction_N": (("qs_step", "component"), qs.reaction),
         "qs_broken": ("qs_step", qs.broken),
         "qs_crack_length_mm": ("qs_step", qs_lengths),
         "qs_phi": ("particle", qs.damage[-1]),
         "qs_path": (("qs_point", "component"), qs_path)},
        coords={"realisation": seeds, "component": comp},
        attrs={"description": "crack paths of a notched plate under Brownian forcing (Dodwell 2019 eq 4)",
               "units": "mm, N", "threshold": THRESHOLD, "path_threshold": PATH_THRESHOLD})
    with atomic_path(out / "realisations.nc") as tmp:
        ds.to_netcdf(tmp, engine="h5netcdf")


def figures(out, body, qs, qs_path, qs_lengths, runs, probability):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = round(SIDE / H)
    fig, ax = plt.subplots(figsize=(6, 5), constrained_layout=True)
    im = ax.imshow(probability.reshape(n, n), origin="lower", extent=(0, SIDE, 0, SIDE), cmap="magma_r", vmin=0, vmax=1)
    ax.plot([0, SIDE / 2], [Y_NOTCH, Y_NOTCH], "c-", lw=2, label="notch")
    ax.set(title=f"P(phi > {THRESHOLD}) over {len(runs)} realisations", xlabel="x (mm)", ylabel="y (mm)")
    ax.legend(loc="lower left")
    fig.colorbar(im, ax=ax)
    fig.savefig(out / "damage_probability.png", dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    for r in runs:
        ax.plot(r.path[:, 0], r.path[:, 1], "-", color="tab:red", alpha=0.35, lw=1)
    ax.plot(qs_path[:, 0], qs_path[:, 1], "k-", lw=2.5, label="deterministic (quasi-static)")
    ax.plot([0, SIDE / 2], [Y_NOTCH, Y_NOTCH], "c-", lw=2, label="notch")
    ax.set(xlim=(0, SIDE), ylim=(Y_NOTCH - 6, Y_NOTCH + 6), xlabel="x (mm)", ylabel="y (mm)",
           title=f"crack paths ({len(runs)} realisations, red)")
    ax.legend(loc="upper left")
    fig.savefig(out / "crack_paths.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), constrained_layout=True)
    axes[0].hist([crack_length(r.path) for r in runs], bins=15, color="tab:red", alpha=0.8)
    axes[0].axvline(crack_length(qs_path), color="k", lw=2, label="deterministic")
    axes[0].set(xlabel="final crack length (mm)", ylabel="realisations", title="crack length")
    axes[0].legend()
    axes[1].hist([failure_load(r.load_factor, r.crack_length) for r in runs], bins=15, color="tab:blue", alpha=0.8)
    axes[1].axvline(failure_load(qs.load_factors, qs_lengths), color="k", lw=2, label="deterministic")
    axes[1].set(xlabel="top displacement when the crack passes half the ligament (mm)", title="failure load")
    axes[1].legend()
    fig.savefig(out / "crack_length_histogram.png", dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4), constrained_layout=True)
    for r in runs[:10]:
        ax.plot(r.load_factor, r.reaction[:, 1], "-", color="tab:red", alpha=0.3, lw=0.8)
    ax.plot(qs.load_factors, qs.reaction[:, 1], "k.-", lw=2, label="quasi-static")
    ax.set(xlabel="top displacement (mm)", ylabel="reaction on the top layer (N)",
           title="load-displacement (red: first 10 realisations)")
    ax.legend()
    fig.savefig(out / "load_displacement.png", dpi=110)
    plt.close(fig)


def main(quick: bool, realisations: int | None):
    out = run_dir("crack_paths")
    start = time.perf_counter()
    n_real = realisations or (4 if quick else 50)
    scene = plate()
    body = scene.at(PARAMS)
    lams = ramp(scene, body, 30 if quick else 50)

    t0 = time.perf_counter()
    qs = quasi_static(scene, PARAMS, lams)
    qs_wall = time.perf_counter() - t0
    qs_path = crack_path(body.particles, qs.damage[-1], PATH_THRESHOLD)
    qs_lengths = np.array([crack_length(crack_path(body.particles, phi, PATH_THRESHOLD)) for phi in qs.damage])

    mob = mobility(body)
    eta = SIGMA**2 / mob
    driver = StochasticFracture(scene, PARAMS, eta)
    runs, rows, errors = [], [], []
    for seed in range(n_real):
        t0 = time.perf_counter()
        try:
            run = driver.run(lams, DT, seed=seed, path_threshold=PATH_THRESHOLD)
        except RuntimeError as e:  # record a failed realisation, never hide it
            errors.append({"seed": seed, "error": str(e)})
            continue
        runs.append(run)
        rows.append(summary(run, seed, time.perf_counter() - t0))
        print(f"realisation {seed}: {rows[-1]['steps']} steps, failure at {rows[-1]['failure_load_mm']:.4f} mm, "
              f"crack {rows[-1]['crack_length_mm']:.1f} mm, deviation {rows[-1]['max_deviation_mm']:.2f} mm, "
              f"{rows[-1]['wall_time_s']:.1f} s", flush=True)
    probability = np.mean([r.phi > THRESHOLD for r in runs], axis=0)
    save(out, body, qs, qs_path, qs_lengths, runs, rows, probability)
    figures(out, body, qs, qs_path, qs_lengths, runs, probability)

    dev = np.array([r["max_deviation_mm"] for r in rows])
    length = np.array([r["crack_length_mm"] for r in rows])
    fail = np.array([r["failure_load_mm"] for r in rows])
    uncertain = int(np.sum((probability > 0.05) & (probability < 0.95)))
    wall = time.perf_counter() - start
    budget = 60.0 if quick else 600.0
    qs_dev, qs_len = deviation(qs_path), crack_length(qs_path)
    targets = {
        "deterministic_crack_straight_mm": {"value": qs_dev, "target": 2 * H, "passed": qs_dev <= 2 * H},
        "deterministic_crack_through_ligament_mm": {"value": qs_len, "target": 0.9 * LIGAMENT,
                                                    "passed": qs_len >= 0.9 * LIGAMENT},
        "stochastic_deviation_spread_mm": {"value": float(dev.std()), "target": "> 0", "passed": bool(dev.std() > 0)},
        "uncertain_particles": {"value": uncertain, "target": "> 0 with 0.05 < P < 0.95", "passed": uncertain > 0},
        "failed_realisations": {"value": len(errors), "target": 0, "passed": not errors},
        "wall_time_s": {"value": wall, "target": budget, "passed": wall < budget},
    }
    metrics = {
        "wall_time_s": wall, "targets": targets,
        "deterministic": {"wall_time_s": qs_wall, "failure_load_mm": failure_load(lams, qs_lengths),
                          "peak_reaction_N": float(qs.reaction[qs.peak, 1]),
                          "peak_reaction_load_mm": float(lams[qs.peak]),
                          "first_failure_load_mm": float(lams[qs.first_failure]),
                          "crack_length_mm": qs_len, "max_deviation_mm": qs_dev,
                          "broken_bonds": int(qs.broken[-1]), "equilibria_solved": int(qs.resolves.sum())},
        "stochastic": {"realisations": len(runs),
                       "wall_time_s_per_realisation": stats(np.array([r["wall_time_s"] for r in rows])),
                       "failure_load_mm": stats(fail), "crack_length_mm": stats(length), "max_deviation_mm": stats(dev),
                       "peak_reaction_N": stats(np.array([r["peak_reaction_N"] for r in rows]))},
        "realisations": rows, "errors": errors,
        "settings": {"quick": quick, "side_mm": SIDE, "h_mm": H, "delta_mm": DELTA, "particles": body.particles.n,
                     "bonds": body.n_bonds, "material": "bond-based PMB, plane stress", "E_MPa": E, "G0_N_per_mm": G0,
                     "s0": S0, "load_steps": len(lams), "top_displacement_max_mm": float(lams[-1]),
                     "noise": "white, C = sigma^2 I on the free dofs", "sigma": SIGMA, "mobility": mob, "eta": eta,
                     "dt": DT, "M_dt_lambda_min": RELAX, "random_force_per_dof_N": float(np.sqrt(2 / DT) * SIGMA / mob),
                     "theta": 1.0, "hold_while_breaking": True, "damage_threshold": THRESHOLD,
                     "path_threshold": PATH_THRESHOLD,
                     "seeds": list(range(n_real)), "backend": sparse.default_backend()}}
    write_metrics("crack_paths", metrics)
    print(f"deterministic: failure at {failure_load(lams, qs_lengths):.4f} mm, crack {qs_len:.1f} mm, "
          f"deviation {qs_dev:.2f} mm ({qs_wall:.1f} s)")
    print(f"stochastic ({len(runs)}): failure {fail.mean():.4f} +- {fail.std():.4f} mm, crack {length.mean():.1f} "
          f"+- {length.std():.1f} mm, deviation {dev.mean():.2f} +- {dev.std():.2f} mm; "
          f"{sum(t['passed'] for t in targets.values())}/{len(targets)} targets; total {wall:.1f} s; wrote {out}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="4 realisations and 30 load steps (smoke run)")
    parser.add_argument("--realisations", type=int, default=None, help="number of realisations (default 50)")
    args = parser.parse_args()
    main(args.quick, args.realisations)
