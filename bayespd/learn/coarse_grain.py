"""WENO-type coarse graining of particle data onto grid nodes (You et al., paper 004, eqs 2.1-2.12).

Plain (eq 2.4): the cone tau(x_i, X) = max(0, R - |X - x_i|), normalised over the nodes for each
particle, omega_i(X) = tau(x_i, X) / sum_j tau(x_j, X), so every particle's mass is shared out
exactly (sum_i rho_i A = sum M). Density and force density per node area ``A`` (eqs 2.2, 2.10-2.11)
and the mass-weighted displacement (eqs 2.3, 2.12):

    rho_i = sum_e w_ie M_e / A,   b_i = sum_e w_ie B_e / A,   u_i = sum_e w_ie M_e U_e / sum_e w_ie M_e,

and the coarse-grained reference position x_i* = sum_e w_ie M_e X_e / sum_e w_ie M_e: a
normalised average reproduces an affine field exactly at x_i* (not at the node, which it matches
only where the particle lattice is symmetric about it).

WENO (eq 2.5): w_ie = tau_ie alpha_ie / sum_j tau_je alpha_je with the smoothness indicator
(eqs 2.6-2.9): the particles near x_i are projected on the segment x_i -> X_e, giving pairs
(d_k, U_k) (distance along the segment, displacement component along it) for the projections that
fall on the segment; alpha = min over splits of the two-line least-squares error divided by the
one-line error. The paper minimises over "all combinations" of two subsets; its Fig. 2 splits at a
position d, which is what is done here (sorted by d, every split leaving ``min_side`` points a
side). The paper projects every particle within R of x_i (``band=None``); then a segment oblique
to a crack sees both faces at the same d and alpha stays near 1 (measured: median 0.97 across a
straight jump). ``band`` keeps only the particles within ``band`` of the segment's line; about
0.75 particle spacings with ``min_side=2`` cut the error next to a jump about 6x below the plain
average's (tests/learn/test_coarse_grain.py), the paper's whole-disk rule only 5 %. ``resolution`` (A) is added to both errors as n r^2: a field whose
variation along the segment is below it counts as smooth (alpha -> 1), and 0/0 cannot occur. MD
fields carry lattice-scale structure (sublattice shifts, waves): there about 0.03 A is needed
(measured in experiments/md_graphene_data.py); the default suits smooth synthetic fields.

Positions may be periodic (``box``): every particle-node vector is then the minimum image.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from bayespd.validate import count, finite, positive


@dataclass
class CoarseGrained:
    """Per frame (F) and node (m): reference position ``x`` (F, m, 2), density ``rho`` (F, m) in
    mass per area, displacement ``u`` (F, m, 2), force density ``b`` (F, m, 2) per area, and the
    smallest smoothness indicator among each node's particles ``alpha_min`` (F, m) (1 for plain)."""
    nodes: np.ndarray
    x: np.ndarray
    rho: np.ndarray
    u: np.ndarray
    b: np.ndarray
    alpha_min: np.ndarray


def _families(nodes, X, radius, box):
    """Per node: the particle indices within ``radius`` and their vectors X_e - x_i (min image)."""
    tree = cKDTree(np.mod(X, box) if box is not None else X, boxsize=box)
    query = np.mod(nodes, box) if box is not None else nodes
    out = []
    for i, idx in enumerate(tree.query_ball_point(query, radius)):
        idx = np.asarray(idx, dtype=np.int64)
        v = X[idx] - nodes[i]
        if box is not None:
            v -= np.round(v / box) * box
        out.append((idx, v))
    return out


def smoothness(v: np.ndarray, U: np.ndarray, band: float | None = None, min_side: int = 2,
               resolution: float = 1e-4) -> np.ndarray:
    """Eqs 2.6-2.9 for one node: alpha (n,) for the segments to each of its n particles, given the
    particle vectors ``v`` (n, 2) from the node and their displacements ``U`` (n, 2)."""
    length = np.linalg.norm(v, axis=1)
    e = v / np.where(length > 0, length, 1.0)[:, None]
    d = e @ v.T                                   # (segment, particle): distance along the segment
    uu = e @ U.T                                  # displacement component along it
    tol = 1e-9 * max(float(length.max()), 1.0)  # the end particle is on its own segment despite rounding
    keep = (d >= -tol) & (d <= length[:, None] + tol)
    if band is not None:
        perp = np.abs(e[:, 0:1] * v[None, :, 1] - e[:, 1:2] * v[None, :, 0])
        keep &= perp <= band
    n = keep.sum(axis=1)
    order = np.argsort(np.where(keep, d, np.inf), axis=1)
    d = np.take_along_axis(d, order, 1)
    uu = np.take_along_axis(uu, order, 1)
    w = np.take_along_axis(keep, order, 1).astype(float)
    nn = np.maximum(n, 1)[:, None]
    d = (d - (np.where(w > 0, d, 0.0).sum(1, keepdims=True) / nn)) * w  # centred: less cancellation
    uu = (uu - (np.where(w > 0, uu, 0.0).sum(1, keepdims=True) / nn)) * w
    sums = [np.cumsum(a, axis=1) for a in (w, d, d * d, uu, d * uu, uu * uu)]
    total = [s[:, -1:] for s in sums]
    prefix = _line_error(*sums)
    suffix = _line_error(*(t - s for t, s in zip(total, sums)))
    eps0 = _line_error(*total)[:, 0]
    j = np.arange(1, v.shape[0] + 1)[None, :]
    valid = (j >= min_side) & (j <= n[:, None] - min_side)
    best = np.where(valid, prefix + suffix, np.inf).min(axis=1)
    floor = n * resolution ** 2
    alpha = (best + floor) / (eps0 + floor)
    return np.where(n >= 2 * min_side, np.clip(alpha, 0.0, 1.0), 1.0)


def _line_error(s0, sd, sdd, su, sdu, suu):
    """Least-squares error of the best line through points given by their running sums."""
    s0 = np.maximum(s0, 1e-300)
    var_d = sdd - sd * sd / s0
    cov = sdu - sd * su / s0
    slope_part = np.where(var_d > 1e-12 * np.maximum(sdd, 1e-300), cov * cov / np.where(var_d > 0, var_d, 1.0), 0.0)
    return np.maximum(suu - su * su / s0 - slope_part, 0.0)


def coarse_grain(nodes, X, M, U, B, radius: float, area: float, weno: bool = True, box=None,
                 band: float | None = None, min_side: int = 2, resolution: float = 1e-4) -> CoarseGrained:
    """Coarse-grain particles (reference positions ``X`` (n, 2), masses ``M`` (n,), displacements
    ``U`` and forces ``B`` (F, n, 2)) onto ``nodes`` (m, 2) with cone radius ``radius`` and node
    area ``area`` (h^2 on a grid of spacing h); ``weno=False`` is the plain average (eq 2.4)."""
    nodes, X, M = (np.asarray(a, float) for a in (nodes, X, M))
    U, B = np.asarray(U, float), np.asarray(B, float)
    positive("radius", radius, "pass the cone radius R in the units of X (a few grid spacings)")
    positive("area", area, "pass the area per node (h^2)")
    count("min_side", min_side, 1, "pass at least 1 point a side")
    for name, a in (("X", X), ("M", M), ("U", U), ("B", B), ("nodes", nodes)):
        finite(name, a, "drop or repair the NaN entries first")
    if U.ndim != 3 or U.shape[1:] != X.shape or B.shape != U.shape:
        raise ValueError(f"U and B must be (frames, {len(X)}, 2) like X; got {U.shape} and {B.shape}")
    box = None if box is None else np.asarray(box, float)
    families = _families(nodes, X, radius, box)
    empty = [i for i, (idx, _) in enumerate(families) if idx.size == 0]
    if empty:
        raise ValueError(f"{len(empty)} node(s) have no particle within R = {radius:g}, e.g. node {empty[0]} at "
                         f"{nodes[empty[0]]}: raise radius or keep the nodes inside the particle cloud")
    rows = np.concatenate([np.full(idx.size, i) for i, (idx, _) in enumerate(families)])
    cols = np.concatenate([idx for idx, _ in families])
    tau = np.concatenate([radius - np.linalg.norm(v, axis=1) for _, v in families])
    frames = U.shape[0]
    out = {k: [] for k in ("x", "rho", "u", "b", "alpha_min")}
    for f in range(frames):
        if weno:
            alpha = np.concatenate([smoothness(v, U[f][idx], band, min_side, resolution) for idx, v in families])
        else:
            alpha = np.ones_like(tau)
        weight = tau * alpha
        per_particle = np.bincount(cols, weight, minlength=len(X))
        w = weight / np.where(per_particle[cols] > 0, per_particle[cols], 1.0)
        wm = w * M[cols]
        mass = np.bincount(rows, wm, minlength=len(nodes))
        if (mass <= 0).any():
            i = int(np.flatnonzero(mass <= 0)[0])
            raise ValueError(f"node {i} at {nodes[i]} has no weight left (every particle near it is across a "
                             "discontinuity): raise radius or drop the node")
        vec = np.concatenate([v for _, v in families])
        avg = lambda values: np.stack([np.bincount(rows, wm * values[:, c], minlength=len(nodes)) for c in (0, 1)], 1)
        out["x"].append(nodes + avg(vec) / mass[:, None])
        out["u"].append(avg(U[f][cols]) / mass[:, None])
        out["rho"].append(mass / area)
        out["b"].append(np.stack([np.bincount(rows, w * B[f][cols, c], minlength=len(nodes)) for c in (0, 1)], 1) / area)
        out["alpha_min"].append(np.minimum.reduceat(alpha, np.r_[0, np.cumsum([idx.size for idx, _ in families])[:-1]]))
    return CoarseGrained(nodes, *(np.stack(out[k]) for k in ("x", "rho", "u", "b", "alpha_min")))
