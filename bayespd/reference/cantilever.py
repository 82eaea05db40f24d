"""A 3D cantilever as a PD scene and its FE peer.

Box 40 x 8 x 8 mm (x along the beam, origin at a corner), E = 4000 MPa, nu = 0.3. The
clamp is the *volume* x <= ``CLAMP`` (a PD Dirichlet layer at least one horizon thick, as
Delorme 2018 §2.2.1 prescribes displacements on a layer V_u); the FE peer fixes every node in
the same volume, which for local elasticity is the same as clamping its face x = CLAMP.
The load is ``FORCE`` N in -z spread uniformly over the end layer x >= L - ``LOAD_DEPTH``
(a body force on V_f in both models).
"""
from __future__ import annotations

import numpy as np

import bayespd as bp
from bayespd.reference.fem import BodyLoad, FESolution, Region, Support, solve_box

LENGTH, WIDTH, DEPTH = 40.0, 8.0, 8.0  # mm
YOUNG, POISSON, FORCE = 4000.0, 0.3, 100.0  # MPa, -, N
CLAMP, LOAD_DEPTH = 4.0, 2.0  # mm: clamped volume, loaded end layer

CLAMPED = Region((0.0, 0.0, 0.0), (CLAMP, WIDTH, DEPTH))
LOADED = Region((LENGTH - LOAD_DEPTH, 0.0, 0.0), (LENGTH, WIDTH, DEPTH))


def params(delta: float) -> dict:
    """PD params {K, G, delta} of the cantilever material."""
    K, G = bp.moduli_from_young(YOUNG, POISSON)
    return {"K": float(K), "G": float(G), "delta": float(delta)}


def pd_scene(h: float, delta_max: float, points=None, **lps_options) -> bp.Scene:
    """3D LPS scene on a cell-centred cubic grid of spacing h (h must divide 2 mm)."""
    p = bp.grid_3d(LENGTH, WIDTH, DEPTH, h)
    material = bp.LPS(p, bp.find_bonds(p, delta_max), **lps_options)
    clamp = bp.Dirichlet(CLAMPED.contains(p.x), (0.0, 0.0, 0.0), depth=CLAMP)
    load = bp.Load(LOADED.contains(p.x), (0.0, 0.0, -FORCE))
    observation = None if points is None else bp.Observation(p, points)
    return bp.Scene(material, [clamp], [load], observation)


REFERENCE_MESH = {"h": 2.0, "order": 2, "grading": 4}  # 7e-5 from h = 1 with 5 levels (measured)
CHECK_MESH = {"h": 2.0, "order": 2, "grading": 3}


def fe_solution(h: float = 2.0, order: int = 2, grading: int = 4, stiffness=None) -> FESolution:
    """The FE peer on a hexahedral Q``order`` mesh of size h (``stiffness``: see solve_box)."""
    return solve_box((LENGTH, WIDTH, DEPTH), h, YOUNG, POISSON, [Support(CLAMPED, (0.0, 0.0, 0.0))],
                     [BodyLoad(LOADED, (0.0, 0.0, -FORCE))], order=order, plane=None,
                     grading=grading, stiffness=stiffness)


def away_mask(x: np.ndarray, margin: float) -> np.ndarray:
    """Points farther than ``margin`` from the clamped volume and the loaded layer."""
    return np.minimum(CLAMPED.distance(x), LOADED.distance(x)) > margin
