"""Does the surface correction help calibration? Tikhonov (adjoint, L-BFGS-B) of K and G
against scikit-fem plane-stress fields of the three-point-bending beam
(bayespd.reference.three_point_bending, Q2 FE at h_FE = 0.5 mm), for several nu, both
partial-volume ramps, with and without bp.LPS(..., surface_correction=True).

Data: the FE displacement at every free particle of a PD grid (h = 1 mm, delta = 3 h), no
noise: the errors are the PD model's against the continuum, i.e. what a calibration
against measured (continuum) fields inherits. E and nu by bp.young_from_moduli.
Writes runs/surface_correction_tikhonov/metrics.json.

    python experiments/surface_correction_tikhonov.py [--h 1.0] [--m 3]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

import common  # noqa: F401  (one torch thread; repository root on sys.path)
from common import write_metrics

import bayespd as bp
from bayespd.inverse import tikhonov
from bayespd.reference import three_point_bending as tpb

NUS = (0.2, 0.3, 0.37)
RULES = ("linear", "smooth")


def calibrate(fe, h: float, m: int, rule: str, correction: bool, truth: dict) -> dict:
    delta = m * h
    scene = tpb.pd_scene(h, delta, rule=rule, surface_correction=correction)
    x = scene.particles.x
    scene.observation = bp.ParticleObservation(scene.particles, np.arange(scene.particles.n))
    y = torch.as_tensor(fe.at(x))
    start = {"K": 0.5 * truth["K"], "G": 2.0 * truth["G"]}
    res = tikhonov(scene, y, start, fixed={"delta": delta}, sigma=1e-3,
                   bounds={k: (v / 10, 10 * v) for k, v in truth.items() if k in start})  # a decade
    E, nu = (float(v) for v in bp.young_from_moduli(res.params["K"], res.params["G"], plane="stress"))
    return {"rule": rule, "surface_correction": correction, "estimates": res.params,
            "rel_error": {"K": res.params["K"] / truth["K"] - 1, "G": res.params["G"] / truth["G"] - 1,
                          "E": E / tpb.YOUNG - 1},
            "nu": nu, "converged": res.converged, "reason": res.reason, "evaluations": res.evaluations,
            "wall_time_s": res.wall_time_s}


def main(h: float, m: int):
    t0 = time.perf_counter()
    rows = []
    for nu in NUS:
        fe = tpb.fe_solution(**tpb.REFERENCE_MESH, nu=nu)
        truth = tpb.params(m * h, nu)
        for rule in RULES:
            for correction in (False, True):
                row = dict(calibrate(fe, h, m, rule, correction, truth), true_nu=nu)
                rows.append(row)
                e = row["rel_error"]
                print(f"nu={nu} {rule:6s} correction={correction!s:5s}: K {100 * e['K']:+6.2f} % "
                      f"G {100 * e['G']:+6.2f} % E {100 * e['E']:+6.2f} % nu {row['nu']:.3f} "
                      f"({row['evaluations']} solves, {row['wall_time_s']:.0f} s, converged={row['converged']})",
                      flush=True)
    worst = {c: max(abs(r["rel_error"][k]) for r in rows if r["surface_correction"] == c for k in ("K", "G"))
             for c in (False, True)}
    write_metrics("surface_correction_tikhonov", {
        "wall_time_s": time.perf_counter() - t0,
        "settings": {"h": h, "m": m, "nus": NUS, "rules": RULES, "fe_mesh": tpb.REFERENCE_MESH, "data": "FE at every particle, no noise"},
        "targets": {"correction_helps": {"value": worst[True], "target": worst[False], "passed": bool(worst[True] < worst[False])}},
        "rows": rows})


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--h", type=float, default=1.0)
    parser.add_argument("--m", type=int, default=3)
    args = parser.parse_args()
    main(args.h, args.m)
