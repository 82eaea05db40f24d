"""Verification of the LPS forward model against a converged finite-element peer (issue 3):
Delorme 2018's three-point bending beam (2D plane stress, §4.1/§6.1) and a 3D cantilever.

Errors are relative L2 norms of u_PD - u_FE at the PD particles farther than MARGIN from the
load and support regions. Two FE peers per problem: the isotropic solid (the physics), and
the same problem with the effective tensor C_m of the PD lattice at fixed m (the limit a
fixed-m PD model converges to as delta -> 0; see bayespd.reference.lattice). Writes
runs/fe_convergence/metrics.json and convergence.png.

    python experiments/fe_convergence.py [--quick]
"""
from __future__ import annotations

import argparse
import ctypes
import gc
import time

import numpy as np

import common  # noqa: F401  (one torch thread; repository root on sys.path)
from common import run_dir, write_metrics

import bayespd as bp
from bayespd.linalg import sparse
from bayespd.reference import (cantilever, isotropic_stiffness, lattice_stiffness, observed_order,
                               pd_versus_fe, relative_l2, three_point_bending)

MARGIN = 4.0  # mm kept clear of every load and support region
FULL = {"beam_m3": [2.0, 1.0, 0.5, 0.25], "beam_delta2": [(1.0, 2), (2 / 3, 3), (0.5, 4)],
        "beam_m3_surface": [2.0, 1.0, 0.5], "cantilever_m2": [1.0, 2 / 3, 0.5],
        "cantilever_m2_surface": [1.0, 2 / 3, 0.5]}
QUICK = {"beam_m3": [2.0, 1.0, 0.5], "beam_delta2": [(1.0, 2), (2 / 3, 3)],
         "beam_m3_surface": [2.0, 1.0], "cantilever_m2": [1.0],
         "cantilever_m2_surface": [1.0, 2 / 3]}
ANISOTROPY_M = {2: [2, 3, 4, 5, 6, 8, 10, 12, 16], 3: [2, 3, 4]}


def moduli(problem):
    p = problem.params(1.0)
    return p["K"], p["G"]


def fe_peers(problem, ms, dim, check_points):
    """Isotropic FE reference, its self-change against the check mesh, lattice peers per m."""
    K, G = moduli(problem)
    iso = problem.fe_solution(**problem.REFERENCE_MESH)
    check = problem.fe_solution(**problem.CHECK_MESH)
    lattice = {m: problem.fe_solution(**problem.REFERENCE_MESH,
                                      stiffness=lattice_stiffness(m, K, G, dim=dim)) for m in ms}
    ref = iso.at(check_points)
    info = {"reference_mesh": problem.REFERENCE_MESH, "check_mesh": problem.CHECK_MESH,
            "reference_dofs": iso.n_dofs, "check_dofs": check.n_dofs,
            "self_change": relative_l2(check.at(check_points), ref),
            "fe_wall_time_s": {"reference": iso.wall_time_s, "check": check.wall_time_s,
                               **{f"lattice_m{m}": fe.wall_time_s for m, fe in lattice.items()}}}
    return iso, lattice, info


def run_series(problem, pairs, iso, lattice, **lps_options):
    rows = []
    for h, m in pairs:
        row = pd_versus_fe(problem, h, m, {"iso": iso, "lattice": lattice[m]}, MARGIN, **lps_options)
        rows.append(row)
        print(f"  h={h:.3f} m={m} delta={row['delta']:.2f} N={row['n_particles']:6d} "
              f"err_iso={row['errors']['iso']:.4f} err_lattice={row['errors']['lattice']:.4f} "
              f"({row['pd_wall_time_s']:.1f} s)", flush=True)
    return rows


def orders(rows, x_key="delta"):
    """Rates p with error ~ delta^p (x_key "delta") or error ~ m^-p (x_key "m"): positive
    means converging. Least squares over the series, and per refinement step."""
    x = [r[x_key] for r in rows]
    sign = -1.0 if x_key == "m" else 1.0
    out = {}
    for ref in ("iso", "lattice"):
        e = [r["errors"][ref] for r in rows]
        out[ref] = {"least_squares": sign * observed_order(x, e) if len(rows) > 1 else None,
                    "steps": [sign * float(np.log(e[k] / e[k + 1]) / np.log(x[k] / x[k + 1]))
                              for k in range(len(rows) - 1)]}
    return out


def anisotropy(dim, plane="stress"):
    K, G = moduli(three_point_bending)
    C = isotropic_stiffness(three_point_bending.YOUNG, three_point_bending.POISSON, dim, plane)
    ms = ANISOTROPY_M[dim]
    a = [float(np.linalg.norm(lattice_stiffness(m, K, G, dim=dim, plane=plane) - C) / np.linalg.norm(C))
         for m in ms]
    return {"m": ms, "relative_tensor_error": a, "order_in_m": -observed_order(ms, a)}


def target(value, bound, below=True):
    ok = value is not None and (value <= bound if below else value >= bound)
    return {"value": value, "target": bound, "passed": bool(ok)}


def figure(out, series):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.4), constrained_layout=True)
    styles = {"iso": "-o", "lattice": "--s"}
    for ax, keys, title in ((axes[0], ["beam_m3", "beam_m3_surface"], "2D three-point bending, m = 3"),
                            (axes[1], ["cantilever_m2", "cantilever_m2_surface"], "3D cantilever, m = 2")):
        for key in keys:
            rows = series[key]
            d = [r["delta"] for r in rows]
            for ref, st in styles.items():
                ax.loglog(d, [r["errors"][ref] for r in rows], st, label=f"{key} vs {ref} FE")
        d = np.array([r["delta"] for r in series[keys[0]]])
        e0 = series[keys[0]][0]["errors"]["lattice"]
        ax.loglog(d, e0 * d / d[0], ":k", label="slope 1")
        ax.set(xlabel="horizon delta (mm)", ylabel="relative L2 error", title=title)
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.legend(fontsize=7)
    ax = axes[2]
    for key, rows in series.items():
        ax.loglog([r["pd_wall_time_s"] for r in rows], [r["errors"]["iso"] for r in rows], "o-", label=key)
    ax.set(xlabel="PD build + solve time (s)", ylabel="relative L2 error vs isotropic FE",
           title="error against run time")
    ax.legend(fontsize=7)
    fig.savefig(out / "convergence.png", dpi=110)
    plt.close(fig)


def return_freed_arrays_to_the_os(threshold: int = 1 << 20) -> None:
    """glibc only (elsewhere nothing): allocate every block of ``threshold`` bytes or more by
    mmap, so that a freed array goes back to the OS. By default glibc raises that threshold
    to 32 MB after the first large free, and the arrays of one FE or PD phase below it stay
    in the heap, fragmented, under the next phase (benchmarks/README.md, issue 31)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return
    libc.mallopt(-3, threshold)  # M_MMAP_THRESHOLD; a set value also ends the dynamic raise


def main(quick: bool):
    return_freed_arrays_to_the_os()
    out = run_dir("fe_convergence")
    start = time.perf_counter()
    plan = QUICK if quick else FULL
    beam, cant = three_point_bending, cantilever

    print("three-point bending (2D plane stress)")
    h_fine = min(plan["beam_m3"])
    g = bp.grid_2d(beam.LENGTH, beam.WIDTH, h_fine)
    ms = sorted({3} | {m for _, m in plan["beam_delta2"]})
    beam_iso, beam_lat, beam_fe = fe_peers(beam, ms, 2, g.x[beam.away_mask(g.x, MARGIN)])
    print(f"  FE Q2 reference {beam_fe['reference_dofs']} dofs; change from the check mesh "
          f"{beam_fe['self_change']:.1e}")
    series = {"beam_m3": run_series(beam, [(h, 3) for h in plan["beam_m3"]], beam_iso, beam_lat),
              "beam_delta2": run_series(beam, plan["beam_delta2"], beam_iso, beam_lat)}
    print("  with surface correction")
    series["beam_m3_surface"] = run_series(beam, [(h, 3) for h in plan["beam_m3_surface"]],
                                           beam_iso, beam_lat, surface_correction=True)

    del beam_iso, beam_lat, g  # the 2D FE fields and grid: not under the 3D phase's peak
    gc.collect()
    print("3D cantilever")
    g3 = bp.grid_3d(cant.LENGTH, cant.WIDTH, cant.DEPTH, min(plan["cantilever_m2_surface"]))
    cant_iso, cant_lat, cant_fe = fe_peers(cant, [2], 3, g3.x[cant.away_mask(g3.x, MARGIN)])
    print(f"  FE Q2 reference {cant_fe['reference_dofs']} dofs; change from the check mesh "
          f"{cant_fe['self_change']:.1e}")
    series["cantilever_m2"] = run_series(cant, [(h, 2) for h in plan["cantilever_m2"]], cant_iso, cant_lat)
    print("  with surface correction")
    series["cantilever_m2_surface"] = run_series(cant, [(h, 2) for h in plan["cantilever_m2_surface"]],
                                                 cant_iso, cant_lat, surface_correction=True)

    observed = {k: orders(v, "m" if k == "beam_delta2" else "delta") for k, v in series.items()}
    lattice_anisotropy = {"2d_plane_stress": anisotropy(2), "3d": anisotropy(3)}
    figure(out, series)

    at = {r["h"]: r for r in series["beam_m3"]}
    wall = time.perf_counter() - start
    cant_sc = series["cantilever_m2_surface"]
    targets = {
        "beam_error_h0.5_m3": target(at[0.5]["errors"]["iso"] if 0.5 in at else None, 0.03),
        "beam_fe_self_change": target(beam_fe["self_change"], 1e-4),
        "cantilever_fe_self_change": target(cant_fe["self_change"], 1e-4),
        "beam_order_vs_lattice_fe_m3": target(observed["beam_m3"]["lattice"]["least_squares"], 0.8, below=False),
        "cantilever_order_surface_corrected_m2": target(
            observed["cantilever_m2_surface"]["lattice"]["least_squares"], 0.8, below=False),
        "cantilever_error_finest_surface_corrected": target(cant_sc[-1]["errors"]["iso"], 0.03),
        "wall_time_s": target(wall, 300.0),
    }
    metrics = {
        "wall_time_s": wall,
        "settings": {"quick": quick, "margin_mm": MARGIN, "plan": plan,
                     "beam": {"L": beam.LENGTH, "W": beam.WIDTH, "t": beam.THICKNESS, "S": beam.SPAN,
                              "F": beam.FORCE, "E": beam.YOUNG, "nu": beam.POISSON,
                              "patch_mm": [beam.PATCH_WIDTH, beam.PATCH_DEPTH],
                              "supports": "pin (u = 0) and roller (u_y = 0) patches; load as a "
                                          "body force on a top patch, same in PD and FE"},
                     "cantilever": {"size": [cant.LENGTH, cant.WIDTH, cant.DEPTH], "E": cant.YOUNG,
                                    "nu": cant.POISSON, "F": cant.FORCE, "clamped_volume_x": cant.CLAMP,
                                    "load_layer": cant.LOAD_DEPTH},
                     "backend": sparse.default_backend()},
        "targets": targets,
        "fe": {"beam": beam_fe, "cantilever": cant_fe},
        "series": series,
        "orders": observed,
        "lattice_anisotropy": lattice_anisotropy,
        "notes": ("Errors vs the isotropic FE level off at the lattice anisotropy of fixed m "
                  "(|C_m - C| / |C|, see lattice_anisotropy); errors vs the lattice FE C_m show "
                  "the part that vanishes with delta. Plain LPS near a free surface is stiffer "
                  "along it (truncated families): in the slender cantilever this first-order "
                  "term is large at the delta/depth reachable in 3D, so plain LPS is "
                  "pre-asymptotic there; the surface-corrected LPS removes it and converges "
                  "to the lattice peer at about first order or better. In the deep 2D beam the "
                  "correction does not help (2.3 % against 1.1 % at h = 0.5, m = 3): there the "
                  "free-surface layer is thin relative to the section and the energy-based "
                  "factors, exact only for uniaxial probes, over-correct the bending field."),
    }
    write_metrics("fe_convergence", metrics)
    print("\norders (least squares):")
    for k, v in observed.items():
        print(f"  {k:24s} vs iso {v['iso']['least_squares']}  vs lattice {v['lattice']['least_squares']}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer resolutions (about a minute)")
    main(parser.parse_args().quick)
