"""Turner 2015 §5 (eq 28, Figs. 10, 11): invert the load F_y from observed crack apertures.

The paper makes the observations with a critical-stretch damage model (s0 = 0.001) in the
forward problem, and inverts "based on the displacement of the material points without having
to accommodate the damage model" (§1): the inverse model is the linear PD operator of the body
with its fracture as observed (bonds broken in the data removed), whose apertures are linear in
F_y. We do the same: data from quasi-static load stepping with bond breaking
(``bayespd.solvers.quasistatic``), inversion with a static linear ``Scene`` on the bonds left
intact (the "known crack" model). As an ablation we also invert with only the initial crack a.

Fig. 10 is not in the text: we take a 5 x 5 mm plate (plane strain, t = 1 mm), an edge crack
a = 1 mm from the left edge at mid-height, h = 0.1 mm, delta = 3h, the bottom strip 2 delta
deep fixed and F_y spread over the top strip 2 delta deep; k = 66.7 GPa, mu = 40 GPa (MPa, mm, N).
Apertures h = u_y(above) - u_y(below) of the particle pairs facing each other across the crack.
Bonds start to break near 107 N here and the crack runs unstably near 119 N (force control),
so the loads span 20-116 N, the last three with crack growth. Nothing breaks below 100 N
(0 broken bonds at 101.8 N in a 5 N-step ramp), so each load is reached in one step when
F_y <= 100 N and by RAMP steps from 100 N above.

    python experiments/tikhonov_aperture.py
"""
from __future__ import annotations

import time

import numpy as np
import torch

from common import run_dir, write_metrics

import bayespd as bp
from bayespd import linalg
from bayespd.damage import CriticalStretch
from bayespd.inverse.least_squares import tikhonov
from bayespd.solvers.quasistatic import quasi_static
from bayespd.linalg.sparse import ConvergenceError

SIDE, THICK, A, Y_CRACK = 5.0, 1.0, 1.0, 2.5
H, DELTA, S0 = 0.1, 0.3, 1e-3
MODULI = {"K": 66700.0, "G": 40000.0}
LOADS = np.array([20.0, 40.0, 60.0, 80.0, 100.0, 110.0, 113.0, 116.0])
# On the h/2 grid bonds already break at 100 N (the fracture load depends on h at fixed delta)
# and one forward run at 110 N took over 5 minutes on the shared 2-core machine: the
# fine-data study stops at 100 N.
FINE_LOADS = LOADS[LOADS <= 100.0]
RAMP, ELASTIC_LIMIT = 6, 100.0  # load steps from ELASTIC_LIMIT to each F_y above it
START = 50.0  # initial guess of F_y (N)
TARGET = 0.01
FACE_X = np.arange(0.05, A, 0.1)  # aperture stations along the initial crack
linalg.set_defaults(factor_threads=1)  # measured: threaded CHOLMOD crawls on a shared 2-core machine


def plate(h: float, crack_tip: float = A):
    p = bp.grid_2d(SIDE, SIDE, h, thickness=THICK)
    bonds = bp.precrack(p, bp.find_bonds(p, DELTA), [[-h, Y_CRACK], [crack_tip, Y_CRACK]])
    return p, bonds


def regions(p):
    return [bp.Dirichlet.layer(p, "bottom", 2 * DELTA)], [bp.Load(p.layer("top", 2 * DELTA), (0.0, 1.0))]


def aperture_points(h: float) -> np.ndarray:
    """(n, 2, 2): for each station, the points h/2 above and below the crack line."""
    return np.stack([np.stack([FACE_X, np.full_like(FACE_X, Y_CRACK + s * H / 2)], 1) for s in (1, -1)], 1)


def aperture_operator(p, pts) -> bp.OpeningObservation:
    """u_y(above) - u_y(below) at each station: eq 28's scalar aperture."""
    return bp.OpeningObservation(p, pts[:, 0], pts[:, 1], component=1)


def fracture(h: float, F: float):
    """Quasi-static ramp to F with critical-stretch breaking: (particles, bonds, intact, u)."""
    p, bonds = plate(h)
    material = bp.LPS(p, bonds, plane="strain")
    dirichlet, loads = regions(p)
    scene = bp.Scene(material, dirichlet, loads, damage=CriticalStretch(S0))
    steps = [F] if F <= ELASTIC_LIMIT else np.linspace(ELASTIC_LIMIT, F, RAMP)
    res = quasi_static(scene, dict(MODULI, delta=DELTA), steps)
    if res.separated:
        raise ConvergenceError(f"the plate separated at F_y = {F}")
    return p, bonds, res.intact.numpy(), res.u


def inverse_scene(p, bonds, observation) -> bp.Scene:
    dirichlet, loads = regions(p)
    return bp.Scene(bp.LPS(p, bonds, plane="strain"), dirichlet, loads, observation)


def invert(scene, y):
    """F_y by eq 28 (aperture misfit, psi = 0), on log F_y from START; sigma only scales J."""
    return tikhonov(scene, y, {"load": START}, fixed=dict(MODULI, delta=DELTA),
                    sigma=float(y[:, 1].abs().max()) * 1e-3, gtol=1e-8)


def crack_tip(p, bonds, intact) -> float:
    """Furthest x of the broken bonds crossing the crack line (the observed crack's tip)."""
    yi, yj = p.x[bonds.i, 1], p.x[bonds.j, 1]
    cross = (intact < 0.5) & ((yi - Y_CRACK) * (yj - Y_CRACK) < 0)
    return float(max(A, 0.5 * (p.x[bonds.i, 0] + p.x[bonds.j, 0])[cross].max(initial=A)))


def same_grid():
    rows, pts = [], aperture_points(H)
    for F in LOADS:
        p, bonds, intact, u = fracture(H, F)
        obs = aperture_operator(p, pts)
        y = obs(u)
        known = invert(inverse_scene(p, bonds.without(intact < 0.5), obs), y)
        initial = invert(inverse_scene(p, bonds, obs), y)
        rows.append({"F_y": F, "broken_bonds": int((intact < 0.5).sum()), "max_aperture": float(y[:, 1].max()),
                     "known_crack": {"F_y": known.params["load"], "rel_error": abs(known.params["load"] / F - 1),
                                     "wall_time_s": known.wall_time_s, "iterations": known.iterations},
                     "initial_crack_only": {"F_y": initial.params["load"],
                                            "rel_error": abs(initial.params["load"] / F - 1)}})
        print(f"F_y {F:6.1f}  broken {rows[-1]['broken_bonds']:4d}  known crack "
              f"{rows[-1]['known_crack']['rel_error']:.2e}  initial crack only "
              f"{rows[-1]['initial_crack_only']['rel_error']:.2e}", flush=True)
    return rows


def noisy_fine(seed: int = 0):
    """Data from h = 0.05 (same horizon) with bond breaking, 1 % noise; the coarse model knows
    the crack geometry (tip from the fine damage), not the fine broken-bond set."""
    rows, gen, pts = [], torch.Generator().manual_seed(seed), aperture_points(H)
    for F in FINE_LOADS:
        try:
            pf, bf, intact, u = fracture(H / 2, F)
        except ConvergenceError as e:
            rows.append({"F_y": F, "skipped": f"fine-grid forward run failed: {e}"})
            print(f"fine + noise F_y {F:6.1f}: skipped ({e})", flush=True)
            continue
        clean = aperture_operator(pf, pts)(u)
        sd = 0.01 * float(clean[:, 1].abs().max())
        y = clean + sd * torch.randn(clean.shape, generator=gen)
        tip = crack_tip(pf, bf, intact)
        p, bonds = plate(H, tip)
        scene = inverse_scene(p, bonds, aperture_operator(p, pts))
        res, exact = invert(scene, y), invert(scene, clean).params["load"]
        rows.append({"F_y": F, "noise_sd": sd, "crack_tip_x": tip, "fine_broken_bonds": int((intact < 0.5).sum()),
                     "estimate": res.params["load"], "rel_error": abs(res.params["load"] / F - 1),
                     "noise_free_estimate": exact, "noise_free_rel_error": abs(exact / F - 1)})
        print(f"fine + noise F_y {F:6.1f}: {rows[-1]['rel_error']:.3f} (noise-free "
              f"{rows[-1]['noise_free_rel_error']:.3f}, tip {tip:.2f})", flush=True)
    return rows


def figure(out, rows, fine):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4.2), constrained_layout=True)
    F = [r["F_y"] for r in rows]
    ax.plot(F, F, "k-", lw=0.8, label="exact")
    ax.plot(F, [r["known_crack"]["F_y"] for r in rows], "o", label="known crack (same grid)")
    ax.plot(F, [r["initial_crack_only"]["F_y"] for r in rows], "x", label="initial crack only")
    ok = [r for r in fine if "estimate" in r]
    ax.plot([r["F_y"] for r in ok], [r["estimate"] for r in ok], "s", mfc="none",
            label="fine data + 1 % noise")
    ax.set_xlabel("exact F_y (N)")
    ax.set_ylabel("inverted F_y (N)")
    ax.set_title("§5 load from crack aperture (cf. Fig. 11)")
    ax.legend(fontsize=8)
    fig.savefig(out / "load_inversion.png", dpi=110)
    plt.close(fig)


def main():
    out = run_dir("tikhonov_aperture")
    start = time.perf_counter()
    rows = same_grid()
    fine = noisy_fine()
    figure(out, rows, fine)
    worst = max(r["known_crack"]["rel_error"] for r in rows)
    metrics = {"targets": {"max_rel_error_known_crack": {"value": worst, "target": TARGET, "passed": worst <= TARGET}},
               "loads": rows, "noisy_fine_data": fine,
               "settings": {"side": SIDE, "thickness": THICK, "a": A, "h": H, "delta": DELTA, "s0": S0,
                            "moduli_MPa": MODULI, "plane": "strain", "start_F_y": START,
                            "ramp": f"one step to F_y <= {ELASTIC_LIMIT} N, else {RAMP} steps from it",
                            "stations": len(FACE_X),
                            "forward": "quasi-static with critical-stretch bond breaking (data)",
                            "inverse": "linear static PD on the bonds left intact (fracture as observed)"}}
    metrics["wall_time_s"] = time.perf_counter() - start
    path = write_metrics("tikhonov_aperture", metrics)
    print(f"max relative error (known crack) {worst:.2e}; wrote {path}")


if __name__ == "__main__":
    main()
