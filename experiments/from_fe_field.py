"""Tutorial: calibrate a plane-stress LPS model from a finite-element field, as a DIC user would.

For each of ``--materials`` random materials (E in [500, 100000] MPa, nu in [0.15, 0.45],
seeded) and geometry (the pin-roller beam of ``reference.three_point_bending``, the plate with a
hole of ``reference.plate_with_hole``): solve the scikit-fem peer, read it on a 1 mm grid, add
noise (``--noise`` x max |u|), write a DIC-like ``.npz`` grid, then *calibrate from the file*
(``calibrate``: the user's code, the same path as for a DIC file) by the VFM defaults
(``vfm_defaults.estimate``) and adjoint Tikhonov on E, nu (delta = 3 h). Writes
runs/from_fe_field/ (metrics.json, error_vs_time.png).

    python experiments/from_fe_field.py [--materials N] [--geometry beam|plate|both] [--noise 0 0.01] [--quick]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import common  # noqa: F401
from common import run_dir, write_metrics

import bayespd as bp
from bayespd.inverse import tikhonov
from bayespd.inverse.vfm_defaults import estimate
from bayespd.reference import plate_with_hole as ph, three_point_bending as tpb

H = 1.0  # mm: the DIC step
TARGETS = {"vfm_K": 0.005, "vfm_G": 0.005, "tikhonov_E": 0.02, "tikhonov_nu": 0.02}


def fe_field(geometry: str, E: float, nu: float):
    """(x, y, u, v) on the 1 mm grid of cell centres (NaN in the hole), from the FE peer."""
    if geometry == "beam":  # u scales as 1 / E in linear elasticity
        fe, scale, L, W, hole = tpb.fe_solution(0.5, nu=nu), tpb.YOUNG / E, tpb.LENGTH, tpb.WIDTH, None
    else:
        fe, scale, L, W = ph.fe_solution(0.5, young=E, nu=nu), 1.0, ph.PLATE.length, ph.PLATE.width
        hole = ph.PLATE
    x, y = np.arange(H / 2, L, H), np.arange(H / 2, W, H)
    pts = np.stack(np.meshgrid(x, y, indexing="xy"), -1).reshape(-1, 2)
    keep = np.ones(len(pts), bool) if hole is None else np.linalg.norm(pts - hole.centre, axis=1) > hole.radius
    u = np.full((len(pts), 2), np.nan)
    u[keep] = scale * fe.at(pts[keep])
    return x, y, u


# ---- the user's code: a DIC-like file in, K, G and E, nu out (the calibration part) ----
def calibrate(path, geometry: str, sigma: float):
    field = bp.read_field(path, order="xy", thickness=tpb.THICKNESS if geometry == "beam" else 1.0,
                          body=None if geometry == "beam" else
                          (lambda x: np.linalg.norm(x - ph.PLATE.centre, axis=1) > ph.PLATE.radius))
    p = field.particles
    if geometry == "beam":
        bcs = [bp.Dirichlet(tpb.PIN.contains(p.x), (0.0, 0.0)), bp.Dirichlet(tpb.ROLLER.contains(p.x), (None, 0.0))]
        loads = [bp.Load(tpb.LOAD.contains(p.x), (0.0, -tpb.FORCE))]
    else:
        bcs = [bp.Dirichlet(ph.PLATE.clamped.contains(p.x), (0.0, 0.0))]
        loads = [bp.Load(ph.PLATE.loaded.contains(p.x), (ph.PLATE.force, 0.0))]
    scene = bp.Scene(bp.LPS(p, bp.find_bonds(p, 5 * p.h), plane="stress"), bcs, loads, field.observation)
    u = np.full((p.n, 2), np.nan)
    u[field.observation.index[:, 0].numpy()[field.valid[:, 0]]] = field.y[field.valid[:, 0]]
    t0 = time.perf_counter()
    vfm = estimate(scene, u, sigma=sigma or None, ms=(2, 3, 4) if geometry == "beam" else (2, 3))
    t1 = time.perf_counter()
    start = {"K": vfm.params["K"], "G": vfm.params["G"]}  # a VFM start, as a user would
    scene3 = bp.Scene(bp.LPS(p, bp.find_bonds(p, 3 * p.h), plane="stress"), bcs, loads, field.observation)
    scale = sigma or 0.01 * np.nanmax(np.abs(field.y))  # the objective's scale when noise-free
    tik = tikhonov(scene3, field.y, start, fixed={"delta": 3 * p.h}, mask=field.mask, sigma=scale,
                   bounds={k: (v / 10, v * 10) for k, v in start.items()})
    t2 = time.perf_counter()
    E_v, nu_v = bp.young_from_moduli(vfm.params["K"], vfm.params["G"])
    E_t, nu_t = bp.young_from_moduli(tik.params["K"], tik.params["G"])
    return {"vfm": {"K": vfm.params["K"], "G": vfm.params["G"], "E": float(E_v), "nu": float(nu_v),
                    "m": vfm.extra["m"], "rule": vfm.extra["rule"], "wall_time_s": t1 - t0},
            "tikhonov": {"K": tik.params["K"], "G": tik.params["G"], "E": float(E_t), "nu": float(nu_t),
                         "converged": tik.converged, "reason": tik.reason, "wall_time_s": t2 - t1}}
# ---- end of the user's code ----


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--materials", type=int, default=20)
    ap.add_argument("--geometry", choices=["beam", "plate", "both"], default="both")
    ap.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.01])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    n = 2 if args.quick else args.materials
    rng = np.random.default_rng(args.seed)
    materials = [(float(rng.uniform(500, 100000)), float(rng.uniform(0.15, 0.45))) for _ in range(n)]
    geometries = ["beam", "plate"] if args.geometry == "both" else [args.geometry]
    out, rows, start = run_dir("from_fe_field"), [], time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for geometry in geometries:
            for i, (E, nu) in enumerate(materials):
                x, y, u = fe_field(geometry, E, nu)
                for level in args.noise:
                    sigma = level * float(np.nanmax(np.abs(u)))
                    noisy = u + sigma * np.random.default_rng(1000 * i + 7).standard_normal(u.shape)
                    path = Path(tmp) / f"{geometry}_{i}.npz"
                    np.savez(path, x=x, y=y, u=noisy[:, 0].reshape(len(y), len(x)), v=noisy[:, 1].reshape(len(y), len(x)))
                    K, G = bp.moduli_from_young(E, nu)
                    truth = {"E": E, "nu": nu, "K": float(K), "G": float(G)}
                    res = calibrate(path, geometry, sigma)
                    for method in res:
                        res[method]["rel_error"] = {k: res[method][k] / truth[k] - 1 for k in truth}
                    rows.append({"geometry": geometry, "noise": level, "truth": truth, **res})
                    print(geometry, level, f"E={E:.0f} nu={nu:.3f}",
                          {m: {k: round(v, 4) for k, v in res[m]["rel_error"].items()} for m in res}, flush=True)
    worst = {k: max(abs(r[k.split("_")[0]]["rel_error"][k.split("_")[1]]) for r in rows) for k in TARGETS}
    targets = {k: {"value": worst[k], "target": t, "passed": bool(worst[k] <= t)} for k, t in TARGETS.items()}
    write_metrics("from_fe_field", {"wall_time_s": time.perf_counter() - start, "targets": targets,
                                    "settings": {"materials": n, "geometries": geometries, "noise": args.noise,
                                                 "seed": args.seed, "h_data": H, "fe_h": 0.5},
                                    "runs": rows})
    plot(rows, out / "error_vs_time.png")


def plot(rows, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, (method, keys) in zip(axes, [("vfm", ("K", "G")), ("tikhonov", ("E", "nu"))]):
        for k, mark in zip(keys, "os"):
            ax.scatter([r[method]["wall_time_s"] for r in rows], [abs(r[method]["rel_error"][k]) for r in rows],
                       marker=mark, label=k)
        ax.axhline(TARGETS[f"{method}_{keys[0]}"], color="k", ls="--", lw=0.8)
        ax.set(xscale="log", yscale="log", xlabel="wall time (s)", ylabel="|relative error|", title=method)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
