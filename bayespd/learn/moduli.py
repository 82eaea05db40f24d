"""The MD sheet's own long-wave 2D moduli from its sinusoidal loads (paper 004 eq 5.1).

A periodic sheet under the force density b = b_hat cos(k . x) e_a responds, in the long-wave limit,
with u = u_hat cos(k . x) e_a and (linear elasticity in 2D)

    (lambda + 2 mu) |k|^2 u_hat = b_hat   (e_a parallel to k: longitudinal),
    mu |k|^2 u_hat = b_hat                (e_a normal to k: transverse).

b_hat and u_hat are least-squares projections of the atoms' forces (per area: B / A_atom) and
displacements on cos(k . x); the longest waves of the box (n = 1 along one axis) give the moduli.
"""
from __future__ import annotations

import re

import numpy as np

CASE = re.compile(r"sin n1=(\d+) n2=(\d+) axis=(\d)")


def wave_modulus(x, U, B, box, n1: int, n2: int, axis: int) -> float:
    """b_hat / (|k|^2 u_hat) for one sinusoidal record frame (x (n, 2) reference positions in A,
    U (n, 2) displacements in A, B (n, 2) forces per atom in eV/A): a 2D modulus in eV/A^2."""
    box = np.asarray(box, float)
    k = 2 * np.pi * np.array([n1, n2]) / box
    c = np.cos(np.asarray(x) @ k)
    area_per_atom = box.prod() / len(c)
    u_hat = (U[:, axis] * c).sum() / (c * c).sum()
    b_hat = (B[:, axis] * c).sum() / (c * c).sum() / area_per_atom
    return float(b_hat / ((k @ k) * u_hat))


def long_wave_moduli(ds) -> dict:
    """lambda + 2 mu and mu (eV/A^2) of a static sinusoidal record (``bayespd.learn.md_files``), from
    its n = 1 waves along x and y (two longitudinal, two transverse: each value is their mean, and
    ``spread`` their relative half-difference)."""
    if "case" not in ds or not ds.attrs.get("periodic", 0):
        raise ValueError("long_wave_moduli needs the periodic sinusoidal training record (static_train), "
                         "whose frames name their load in 'case'")
    found = {"P": [], "mu": []}
    for f, name in enumerate(ds["case"].values):
        m = CASE.fullmatch(str(name))
        if not m:
            continue
        n1, n2, axis = map(int, m.groups())
        if (n1, n2) not in ((1, 0), (0, 1)):
            continue
        kind = "P" if (n1, n2)[axis] == 1 else "mu"
        found[kind].append(wave_modulus(ds["X"].values, ds["U"].values[f], ds["B"].values[f],
                                        ds.attrs["box"], n1, n2, axis))
    if not all(len(v) == 2 for v in found.values()):
        raise ValueError("the record lacks the n = 1 sinusoidal loads (sin n1=1 n2=0 / n1=0 n2=1, both axes)")
    out = {k: float(np.mean(v)) for k, v in found.items()}
    spread = {k: float(abs(v[0] - v[1]) / (v[0] + v[1])) for k, v in found.items()}
    return {"lambda_plus_2mu": out["P"], "mu": out["mu"], "lambda": out["P"] - 2 * out["mu"], "spread": spread}
