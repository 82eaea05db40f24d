"""PD against FE: relative L2 error at the PD particles away from loads and supports, and
observed convergence orders (least-squares slopes on log-log axes)."""
from __future__ import annotations

import time

import numpy as np
import torch


def relative_l2(u: np.ndarray, reference: np.ndarray) -> float:
    """||u - u_ref|| / ||u_ref|| over all points and components (uniform cells: a discrete L2)."""
    return float(np.linalg.norm(u - reference) / np.linalg.norm(reference))


def observed_order(x, errors) -> float:
    """Least-squares slope of log(error) against log(x) (x = delta, or m)."""
    slope, _ = np.polyfit(np.log(np.asarray(x, float)), np.log(np.asarray(errors, float)), 1)
    return float(slope)


def pd_versus_fe(problem, h: float, m: float, references: dict, margin: float, **lps_options) -> dict:
    """Solve ``problem``'s PD scene at spacing h and delta = m h; its relative L2 error against
    each FE solution in ``references`` at the particles farther than ``margin`` from the
    problem's load and support regions (``problem.away_mask``).

    ``problem`` is a module such as ``three_point_bending`` or ``cantilever``.
    """
    delta = m * h
    start = time.perf_counter()
    scene = problem.pd_scene(h, delta, **lps_options)
    built = time.perf_counter()
    with torch.no_grad():
        u = scene.solve(problem.params(delta)).numpy()
    solved = time.perf_counter()
    x = scene.particles.x
    keep = problem.away_mask(x, margin)
    errors = {name: relative_l2(u[keep], fe.at(x[keep])) for name, fe in references.items()}
    return {"h": h, "m": m, "delta": delta, "n_particles": scene.particles.n,
            "n_compared": int(keep.sum()), "pd_wall_time_s": solved - start,
            "pd_build_s": built - start, "pd_solve_s": solved - built, "errors": errors}
