"""Delorme 2018 (PD Virtual Fields Method) reproduced on a scikit-fem three-point bending field.

FE peer: bayespd.reference.three_point_bending (Q2, h = 0.5 mm graded; pin + roller patches,
load as a body force on a top patch; plane stress, E = 4000, nu = 0.3), evaluated at the
particles of a PD grid (h = 0.5 mm): no inverse crime. Delorme 2018 used point supports; with
patches its eqs 27-28 are not admissible, so we use them cleared off the patches
(virtual_fields.bending_fields) and add interior bumps (virtual_fields.interior_bumps) that
see neither the free surfaces nor missing edge data.

Sections: m = delta/h study (Delorme 2018 Fig. 7) for both partial-volume ramps, with the
lattice's cubic anisotropy (``reference.lattice``), which sets the K error; Table 2 (closed form and Gauss-Newton from
the paper's starts), Table 3 (noise, Monte-Carlo interval per Sigma, the Cramer-Rao bound,
and the bias-variance trade-off of noise-optimal fields; then at h = 0.25 mm, the issue's
other spacing, where the same noise per displacement on 4x the particles cuts the sd 2-3x, with
noise-optimal fields kept off the edges), Table 4 (missing edge bands:
interior fields vs Tikhonov adjoint inversion). Writes
runs/vfm_three_point_bending/{metrics.json, vfm.png}.

    python experiments/vfm_three_point_bending.py [--quick]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

import common  # noqa: F401  (one torch thread; repository root on sys.path)
from common import run_dir, write_metrics

import bayespd as bp
from bayespd.linalg import sparse
from bayespd.inverse import tikhonov
from bayespd.inverse import virtual_fields as vf
from bayespd.inverse.vfm import (VirtualWork, identify, moduli_from_constants, moduli_sensitivities,
                                 noise_optimal_fields, optimise)
from bayespd.reference import three_point_bending as tpb
from bayespd.reference.lattice import lattice_stiffness

H = 0.5
FINE_H = 0.25  # Delorme 2018's finer spacing: Table 3 again with 4x the particles
FINE_CLEARANCES = [1.0, 1.5, 2.0, 3.0]  # mm from every edge where the noise-optimal fields stop
SIGMAS = [0.0, 0.5e-4, 1.0e-4, 1.5e-4, 2.0e-4, 2.5e-4]
BANDS = [0.0, 0.25, 0.5, 0.75, 1.0, 1.25]
STARTS = [(5000.0, 5000.0), (1098.722, 7031.443), (9845.479, 1797.806), (9881.218, 2116.642)]  # Table 2 #1, 2, 4, 8
SEED = 2024
RULES = ("linear", "smooth")  # partial-volume ramps (bayespd.bonds.partial_volume)


def fields(delta: float, which: str):
    """'paper': Delorme 2018's two fields cleared off the patches; 'interior': the first of them
    (it carries the load's work) plus 6 x 1 cells of interior bumps (2 delta + 1 mm clear of
    every edge); 'bumps': the interior bumps only (no data within 2 delta + 1 mm of an edge)."""
    paper = vf.bending_fields(tpb.LENGTH, tpb.WIDTH, tpb.SPAN, origin=(tpb.LENGTH / 2, 0),
                              clear_half_width=tpb.PATCH_WIDTH / 2, clear_depth=tpb.PATCH_DEPTH)
    bumps = vf.interior_bumps((0, 0), (tpb.LENGTH, tpb.WIDTH), (6, 1), 2 * delta + 1)
    return {"paper": paper, "interior": paper[:1] + bumps, "bumps": bumps}[which]


def errors(est: dict, truth: dict) -> dict:
    return {k: est[k] / truth[k] - 1 for k in ("K", "G")}


def setup(m: int, fe, which="interior", rule="linear", h=H):
    delta = m * h
    scene = tpb.pd_scene(h, delta, rule=rule)
    u = fe.at(scene.particles.x)
    t = time.perf_counter()
    work = VirtualWork(scene, fields(delta, which), {"delta": delta})
    return scene, torch.as_tensor(u), work, time.perf_counter() - t


def anisotropy(m: int, rule: str) -> float:
    """2 C66 / (C11 - C12) - 1 of the lattice tensor (0: isotropic; reference.lattice)."""
    K, G = bp.moduli_from_young(tpb.YOUNG, tpb.POISSON)
    C = lattice_stiffness(m, K, G, rule=rule)
    return float(2 * C[2, 2] / (C[0, 0] - C[0, 1]) - 1)


def m_study(fe, ms, rules):
    rows = []
    for rule in rules:
        for m in ms:
            delta = m * H
            scene, u, _, _ = setup(m, fe, "paper", rule)
            truth = tpb.params(delta)
            row = {"m": m, "delta": delta, "rule": rule, "lattice_anisotropy": anisotropy(m, rule)}
            for which in ("paper", "interior"):
                work = VirtualWork(scene, fields(delta, which), {"delta": delta})
                r = work.residual(u, {"K": torch.tensor(truth["K"]), "G": torch.tensor(truth["G"])})
                res = identify(work, u)
                row[which] = {"phi_at_truth": work.phi(r.detach()), "rel_error": errors(res.params, truth)}
            rows.append(row)
            print(f"  {rule} m={m}: lattice anisotropy {row['lattice_anisotropy']:+.4f}, phi(paper)="
                  f"{row['paper']['phi_at_truth']:.2e} phi(interior)={row['interior']['phi_at_truth']:.2e} "
                  f"err(interior) K={row['interior']['rel_error']['K']:+.4f} "
                  f"G={row['interior']['rel_error']['G']:+.4f}", flush=True)
    return rows


def table2(u, work, truth, starts):
    closed = identify(work, u)
    out = {"closed_form": {"estimates": closed.params, "rel_error": errors(closed.params, truth),
                           "phi": closed.phi, "evaluations": 0, "wall_time_s": closed.wall_time_s},
           "gauss_newton": []}
    for K0, G0 in starts:
        r = optimise(work, u, {"K": K0, "G": G0})
        out["gauss_newton"].append({"init": {"K": K0, "G": G0}, "estimates": r.params,
                                    "rel_error": errors(r.params, truth), "phi": r.phi,
                                    "evaluations": r.evaluations, "wall_time_s": r.wall_time_s})
        print(f"  GN from ({K0:.0f}, {G0:.0f}): {r.evaluations} evaluations, {r.wall_time_s:.1f} s, "
              f"K {r.params['K']:.3f} G {r.params['G']:.3f}", flush=True)
    return out


def noisy(u, sigma, rng):
    return u + sigma * torch.as_tensor(rng.standard_normal(tuple(u.shape)))


def cramer_rao(scene, truth) -> np.ndarray:
    """Relative sd of (K, G) per unit noise Sigma (1/mm) that no unbiased estimator from the
    displacements of every particle (iid N(0, Sigma^2) per free component) can beat: the
    square roots of diag (J^T J)^-1, the inverse Fisher information of the PD model at the
    truth, J = du/d(K, G) (``vfm.moduli_sensitivities``, exact)."""
    J = moduli_sensitivities(scene, truth)
    return np.sqrt(np.diag(np.linalg.inv(J.T @ J))) / np.array([truth["K"], truth["G"]])


def monte_carlo(work, u, truth, sigma, draws: int, rng) -> np.ndarray:
    """Relative (K, G) errors (draws, 2) of the closed form on u plus seeded iid noise on the
    free dofs (the supports are prescribed; two dot products per field and draw: W*_int is
    linear in u)."""
    A0 = work.internal_matrix(work.data(u)).numpy()
    b = -work.external.numpy()
    free = torch.as_tensor(~work.fixed_dofs)
    errs = []
    for _ in range(draws):
        g = sigma * torch.as_tensor(rng.standard_normal(tuple(u.shape))) * free
        a = np.linalg.lstsq(A0 + work.internal_matrix(g).numpy(), b, rcond=None)[0]
        K, G = moduli_from_constants(work.material, a[0], a[1])
        errs.append([K / truth["K"] - 1, G / truth["G"] - 1])
    return np.array(errs)


def table3(u, work, truth, draws: int, bound: np.ndarray):
    """Per Sigma: one seeded realisation (as the paper) and a Monte-Carlo interval over
    ``draws`` further seeded realisations, beside the Cramer-Rao sd ``bound`` * Sigma of any
    unbiased estimator."""
    rng = np.random.default_rng(SEED)
    rows = []
    for s in SIGMAS:
        one = identify(work, noisy(u, s, rng))
        errs = monte_carlo(work, u, truth, s, draws, rng)
        row = {"sigma": s, "estimates": one.params, "rel_error": errors(one.params, truth),
               "interval_95": {k: [float(np.percentile(errs[:, i], 2.5)), float(np.percentile(errs[:, i], 97.5))]
                               for i, k in enumerate("KG")},
               "max_abs_error_95": float(np.percentile(np.abs(errs).max(axis=1), 95)),
               "sd": {k: float(errs[:, i].std()) for i, k in enumerate("KG")},
               "cramer_rao_sd": {k: float(bound[i] * s) for i, k in enumerate("KG")}}
        rows.append(row)
        print(f"  Sigma={s:.1e}: K {row['rel_error']['K']:+.4f} G {row['rel_error']['G']:+.4f} "
              f"95% |err| <= {row['max_abs_error_95']:.4f}; sd K {row['sd']['K']:.4f} (Cramer-Rao "
              f"{row['cramer_rao_sd']['K']:.4f}), G {row['sd']['G']:.4f} ({row['cramer_rao_sd']['G']:.4f})", flush=True)
    return rows


def interior_weight(clear: float):
    """The C1 weight prod_a (1 - s_a^2)^2 over the beam, zero within ``clear`` of every edge
    (``virtual_fields.bump`` centred on the beam)."""
    inside = vf.bump((tpb.LENGTH / 2, tpb.WIDTH / 2), (tpb.LENGTH / 2 - clear, tpb.WIDTH / 2 - clear), 0)
    return lambda x: inside(x)[:, 0]


def noise_optimal_interior(scene, optimal, delta: float, clear: float) -> VirtualWork:
    """Delorme 2018 eq 27 (it carries the load's work) plus the noise-optimal fields times
    ``interior_weight(clear)``: they see neither the patches nor the free surfaces."""
    weight = interior_weight(clear)
    return VirtualWork(scene, fields(delta, "paper")[:1] + [vf.scaled(f, weight) for f in optimal], {"delta": delta})


def trade_off(name: str, work, u, truth, draws: int, rng) -> dict:
    """Bias (noise-free data), sd and 95 % bound on max(|K err|, |G err|) over ``draws``
    seeded realisations at the largest Sigma, for one field set."""
    errs = monte_carlo(work, u, truth, SIGMAS[-1], draws, rng)
    bias = errors(identify(work, u).params, truth)
    out = {"bias": bias, "sd": {k: float(errs[:, i].std()) for i, k in enumerate("KG")},
           "max_abs_error_95": float(np.percentile(np.abs(errs).max(axis=1), 95))}
    print(f"  {name}: bias K {bias['K']:+.4f} G {bias['G']:+.4f}, sd K {out['sd']['K']:.4f} "
          f"G {out['sd']['G']:.4f}, 95% |err| <= {out['max_abs_error_95']:.4f}", flush=True)
    return out


def field_sets(scene, u, work, truth, draws: int) -> dict:
    """At the largest Sigma, the bias-variance trade-off of three field sets: 'interior'
    (Table 2's), 'interior_noise_optimal' (Delorme 2018 eq 27 plus the noise-optimal fields
    multiplied by a C1 cut-off that vanishes 2 delta + 1 mm from every edge), and
    'noise_optimal' (those fields alone: one Gauss-Newton step of maximum likelihood on
    every displacement, bias included)."""
    delta = float(work.fixed["delta"])
    t0 = time.perf_counter()
    optimal = noise_optimal_fields(scene, {**identify(work, u).params, "delta": delta})
    sets = {"interior": work,
            "interior_noise_optimal": noise_optimal_interior(scene, optimal, delta, 2 * delta + 1),
            "noise_optimal": VirtualWork(scene, optimal, {"delta": delta})}
    made = time.perf_counter() - t0
    rng = np.random.default_rng(SEED + 1)
    out = {name: trade_off(name, w, u, truth, draws, rng) for name, w in sets.items()}
    out["fields_wall_time_s"] = made
    return out


def table3_fine(fe, m: int, rule: str, draws: int) -> dict:
    """Table 3 at h = FINE_H (same m and ramp): Delorme 2018 eq 27 plus the noise-optimal fields
    (made at the closed-form estimate of the interior fields) weighted to vanish
    ``clear`` from every edge. The clearances of FINE_CLEARANCES trade the model-form bias
    near the surfaces against noise (Monte-Carlo at the largest Sigma); the one with the
    smallest 95 % bound runs the whole table, beside this grid's Cramer-Rao bound."""
    t0 = time.perf_counter()
    delta = m * FINE_H
    scene, u, work, _ = setup(m, fe, rule=rule, h=FINE_H)
    truth = tpb.params(delta)
    bound = cramer_rao(scene, truth)
    optimal = noise_optimal_fields(scene, {**identify(work, u).params, "delta": delta})
    rng = np.random.default_rng(SEED + 2)
    sweep, works = [], {}
    for clear in FINE_CLEARANCES:
        works[clear] = w = noise_optimal_interior(scene, optimal, delta, clear)
        sweep.append({"clear_mm": clear, **trade_off(f"h={FINE_H} clear {clear} mm", w, u, truth, draws, rng)})
    best = min(sweep, key=lambda r: r["max_abs_error_95"])["clear_mm"]
    print(f"  h={FINE_H}, clear {best} mm, Cramer-Rao sd per mm of noise: K {bound[0]:.1f}, G {bound[1]:.1f}")
    rows = table3(u, works[best], truth, draws, bound)
    return {"h": FINE_H, "delta": delta, "particles": scene.particles.n, "clearance_sweep": sweep,
            "clear_mm": best, "table": rows, "cramer_rao_sd_per_mm": bound.tolist(),
            "wall_time_s": time.perf_counter() - t0}


def scale_from_one_solve(unit: torch.Tensor, ratio: float, obs: np.ndarray, y: torch.Tensor) -> dict:
    """(K, G) with K/G = ratio known: the LPS stiffness is homogeneous of degree one in (K, G),
    so u(c K1, c G1) = u(K1, G1) / c and the least-squares scale over the observed particles
    is closed form given ``unit``, the one forward solve at (K, G) = (ratio, 1)."""
    u1 = unit[torch.as_tensor(obs)]
    G = float((u1 * u1).sum() / (u1 * y).sum())
    return {"K": ratio * G, "G": G}


def table4(scene, u, work_interior, truth, m, rule, tikhonov_bands):
    """Missing edge bands: (a) the full field set refuses (needs edge data); (b) interior
    bumps only: no data within 2 delta + 1 mm of the edges, W*_ext = 0 -> the ratio K/G only;
    (c) that ratio plus the scale from one forward solve (``scale_from_one_solve``);
    (d) Tikhonov adjoint inversion of K and G, started from (c). (c) and (d) use the observed
    particles more than 2 delta from the support and load patches (where a 2D point-like
    patch load makes the local FE and nonlocal PD fields differ most)."""
    delta = m * H
    x = scene.particles.x
    bumps = VirtualWork(scene, fields(delta, "bumps"), {"delta": delta})
    away = tpb.away_mask(x, 2 * delta)
    rows, units = [], {}
    for band in BANDS:
        keep = bp.edge_mask(scene.particles, x, band)[:, 0] if band > 0 else np.ones(len(x), bool)
        data = u.clone()
        data[torch.as_tensor(~keep)] = float("nan")
        row = {"band_mm": band, "observed_particles": int(keep.sum())}
        try:
            r = identify(work_interior, data)
            row["vfm_all_fields"] = {"rel_error": errors(r.params, truth)}
        except ValueError as e:
            row["vfm_all_fields"] = {"refused": str(e)[:160]}
        A = bumps.internal_matrix(bumps.data(data)).numpy()
        # W*_ext = 0: A a = 0, a = (a_s, a_d) up to scale -> K/G from the null vector
        a = np.linalg.svd(A / np.abs(A).max(axis=0))[2][-1] / np.abs(A).max(axis=0)
        K, G = moduli_from_constants(scene.material, a[0] / a[1], 1.0)
        row["vfm_interior_bumps"] = {"K_over_G_rel_error": (K / G) / (truth["K"] / truth["G"]) - 1,
                                     "scale": "not identifiable: no field that needs no edge data does work on the load"}
        obs = np.flatnonzero(keep & away)
        t0 = time.perf_counter()
        ratio = K / G
        if ratio not in units:  # the interior fields need no edge data: usually one ratio
            units[ratio] = scene.solve({"K": ratio, "G": 1.0, "delta": delta}).detach()
        hybrid = scale_from_one_solve(units[ratio], ratio, obs, u[torch.as_tensor(obs)])
        row["vfm_ratio_plus_one_solve"] = {"estimates": hybrid, "rel_error": errors(hybrid, truth),
                                           "evaluations": 1, "wall_time_s": time.perf_counter() - t0}
        if band in tikhonov_bands:
            sc = tpb.pd_scene(H, delta, rule=rule)
            sc.observation = bp.ParticleObservation(sc.particles, obs)
            t = tikhonov(sc, u[torch.as_tensor(obs)], hybrid, fixed={"delta": delta},
                         bounds={k: (v / 10, 10 * v) for k, v in hybrid.items()},  # a decade each way
                         sigma=1e-4, gtol=1e-9, maxiter=100)
            row["tikhonov"] = {"estimates": t.params, "rel_error": errors(t.params, truth),
                               "evaluations": t.evaluations, "wall_time_s": t.wall_time_s}
        rows.append(row)
        hy = row["vfm_ratio_plus_one_solve"]["rel_error"]
        print(f"  band {band:.2f}: ratio err {row['vfm_interior_bumps']['K_over_G_rel_error']:+.4f}; "
              f"ratio + one solve K {hy['K']:+.4f} G {hy['G']:+.4f}"
              + (f"; Tikhonov K {row['tikhonov']['rel_error']['K']:+.4f} G {row['tikhonov']['rel_error']['G']:+.4f} "
                 f"({row['tikhonov']['evaluations']} solves, {row['tikhonov']['wall_time_s']:.0f} s)"
                 if "tikhonov" in row else ""), flush=True)
    return rows


def figure(out, ms_rows, t3, t3f, t4):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4.2), constrained_layout=True)
    for k, rule in enumerate(RULES):
        rows = [r for r in ms_rows if r["rule"] == rule]
        m = [r["m"] for r in rows]
        ax[0].semilogy(m, [r["interior"]["phi_at_truth"] for r in rows], "o-", color=f"C{k}",
                       label=f"Phi at truth (interior fields), {rule}")
        ax[0].semilogy(m, [abs(r["interior"]["rel_error"]["K"]) for r in rows], "s--", color=f"C{k}",
                       label=f"|K error| (interior), {rule}")
        ax[0].semilogy(m, [abs(r["lattice_anisotropy"]) for r in rows], ":", color=f"C{k}",
                       label=f"|lattice anisotropy|, {rule}")
    ax[0].set(xlabel="m = delta / h (h = 0.5 mm)", title="Delorme 2018 Fig. 7: residual vs m")
    ax[0].legend(fontsize=8)
    s = np.array([r["sigma"] for r in t3])
    series = [(t3, "K", "0.6", f"h = {H}, interior fields"), (t3f, "K", "C0", f"h = {FINE_H}, noise-optimal interior"),
              (t3f, "G", "C1", f"h = {FINE_H}, noise-optimal interior")]
    for j, (rows, k, color, name) in enumerate(series):
        x = s + (j - 1) * 3e-6
        ax[1].vlines(x, [100 * r["interval_95"][k][0] for r in rows], [100 * r["interval_95"][k][1] for r in rows],
                     color=color, alpha=0.6, label=f"{k}, {name}: 95 % Monte-Carlo interval")
        ax[1].plot(x, [100 * r["rel_error"][k] for r in rows], "o", color=color, ms=4)
    crb = 196 * np.array([r["cramer_rao_sd"]["K"] for r in t3f])
    ax[1].plot(s, crb, "k--", lw=1, label=f"K: Cramer-Rao 95 % at h = {FINE_H} (dots: one realisation)")
    ax[1].plot(s, -crb, "k--", lw=1)
    ax[1].axhspan(-0.7, 0.7, color="g", alpha=0.1, label="target +-0.7 %")
    ax[1].set(xlabel="noise Sigma (mm)", ylabel="relative error (%)", title="Table 3: noise")
    ax[1].legend(fontsize=8)
    b = [r["band_mm"] for r in t4]
    ax[2].plot(b, [100 * r["vfm_interior_bumps"]["K_over_G_rel_error"] for r in t4], "o-", label="VFM interior fields: K/G")
    for k, mark in (("K", "^-"), ("G", "v-")):
        ax[2].plot(b, [100 * r["vfm_ratio_plus_one_solve"]["rel_error"][k] for r in t4], mark,
                   label=f"VFM ratio + one solve: {k}")
    tb = [r for r in t4 if "tikhonov" in r]
    for k in "KG":
        ax[2].plot([r["band_mm"] for r in tb], [100 * r["tikhonov"]["rel_error"][k] for r in tb], "s--", label=f"Tikhonov {k}")
    ax[2].plot([0, .25, .5, .75, 1, 1.25], [0.63, 7.32, 11.26, 15.60, 20.36, 25.55], "k:", label="paper K (Table 4)")
    ax[2].set(xlabel="missing edge band (mm)", ylabel="relative error (%)", title="Table 4: missing edge data")
    ax[2].legend(fontsize=8)
    fig.savefig(out / "vfm.png", dpi=110)
    plt.close(fig)


def target(value, bound):
    return {"value": value, "target": bound, "passed": bool(value is not None and value <= bound)}


def main(quick: bool):
    out = run_dir("vfm_three_point_bending")
    start = time.perf_counter()
    fe = tpb.fe_solution(**tpb.REFERENCE_MESH)
    print(f"FE Q2 reference: {fe.n_dofs} dofs, {fe.wall_time_s:.1f} s")
    ms = [2, 3, 4, 5, 6] if quick else [2, 3, 4, 5, 6, 7, 8]
    print("m study (h = 0.5 mm)")
    ms_rows = m_study(fe, ms, RULES)
    best = min(ms_rows, key=lambda r: r["interior"]["phi_at_truth"])  # Delorme 2018's rule, over both ramps
    m, rule = best["m"], best["rule"]
    print(f"m = {m}, {rule} partial volumes (smallest Phi at the FE moduli: the paper's rule)")
    scene, u, work, basis_s = setup(m, fe, rule=rule)
    truth = tpb.params(m * H)
    print("Table 2")
    t2 = table2(u, work, truth, STARTS[:2] if quick else STARTS)
    t2["closed_form"]["basis_wall_time_s"] = basis_s
    t2["paper_fields"] = {"rel_error": errors(identify(VirtualWork(scene, fields(m * H, "paper"),
                                                                   {"delta": m * H}), u).params, truth)}
    print(f"  closed form {t2['closed_form']['rel_error']} (paper's two fields: {t2['paper_fields']['rel_error']})")
    print("Table 3")
    t0 = time.perf_counter()
    bound = cramer_rao(scene, truth)
    print(f"  Cramer-Rao sd per mm of noise: K {bound[0]:.1f}, G {bound[1]:.1f} ({time.perf_counter() - t0:.0f} s)")
    t3 = table3(u, work, truth, 200 if quick else 1000, bound)
    print(f"Field sets at Sigma = {SIGMAS[-1]:g}")
    sets = field_sets(scene, u, work, truth, 200 if quick else 1000)
    print(f"Table 3 at h = {FINE_H} mm")
    fine = table3_fine(fe, m, rule, 200 if quick else 1000)
    t3f = fine["table"]
    floor_95 = 1.96 * fine["cramer_rao_sd_per_mm"][0] * SIGMAS[-1]
    print("Table 4")
    t4 = table4(scene, u, work, truth, m, rule, [0.5])
    cf = t2["closed_form"]["rel_error"]
    at05 = next(r for r in t4 if r["band_mm"] == 0.5)
    wall = time.perf_counter() - start
    targets = {
        "table2_K_rel_error": target(abs(cf["K"]), 0.003),
        "table2_G_rel_error": target(abs(cf["G"]), 0.003),
        "table2_optimiser_agrees": target(max(abs(g["estimates"][k] / t2["closed_form"]["estimates"][k] - 1)
                                              for g in t2["gauss_newton"] for k in "KG"), 1e-6),
        "table3_max_abs_error": target(max(abs(r["rel_error"][k]) for r in t3f for k in "KG"), 0.007),
        "table3_max_abs_error_95": target(max(r["max_abs_error_95"] for r in t3f), 0.007),
        # an unbiased estimator's 95 % interval at the largest Sigma is at least +-1.96 sd_CR wide
        "table3_cramer_rao_95_K_at_max_sigma": {"value": floor_95, "target": 0.007, "passed": bool(floor_95 <= 0.007),
                                                "meaning": "no unbiased estimator from these data can have a 95 % "
                                                           "K error bound below this (target feasible iff passed)"},
        "table4_K_error_band_0.5_tikhonov": target(abs(at05["tikhonov"]["rel_error"]["K"]), 0.03),
        "table4_K_error_band_0.5_vfm_ratio_plus_one_solve": target(abs(at05["vfm_ratio_plus_one_solve"]["rel_error"]["K"]), 0.03),
        "table4_K_over_G_error_band_0.5_vfm_interior": target(abs(at05["vfm_interior_bumps"]["K_over_G_rel_error"]), 0.03),
    }
    metrics = {
        "wall_time_s": wall,
        "settings": {"quick": quick, "h": H, "m": m, "rule": rule, "delta": m * H, "fe_mesh": tpb.REFERENCE_MESH,
                     "fe_dofs": fe.n_dofs, "particles": scene.particles.n, "seed": SEED,
                     "supports": "pin + roller patches (4 x 2 mm), load as body force on a 4 x 2 mm top patch",
                     "fields": "interior = Delorme 2018 eq 27 cleared off the patches + 12 interior bumps; "
                               "paper = eqs 27-28 cleared off the patches",
                     "truth": {"K": truth["K"], "G": truth["G"]}, "backend": sparse.default_backend()},
        "targets": targets,
        "m_study": ms_rows, "table2": t2, "table3": t3, "table3_field_sets": sets, "table3_fine": fine, "table4": t4,
        "table3_h0.5": {"max_abs_error": max(abs(r["rel_error"][k]) for r in t3 for k in "KG"),
                        "max_abs_error_95": max(r["max_abs_error_95"] for r in t3),
                        "best_field_set_95": min(v["max_abs_error_95"] for k, v in sets.items() if k != "fields_wall_time_s")},
        "methods": {"vfm_closed_form": {"wall_time_s": t2["closed_form"]["wall_time_s"] + basis_s,
                                        "estimates": t2["closed_form"]["estimates"]},
                    "vfm_gauss_newton": {"wall_time_s": t2["gauss_newton"][0]["wall_time_s"],
                                         "estimates": t2["gauss_newton"][0]["estimates"]}},
    }
    write_metrics("vfm_three_point_bending", metrics)
    figure(out, ms_rows, t3, t3f, t4)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer m values, starts and draws")
    main(parser.parse_args().quick)
