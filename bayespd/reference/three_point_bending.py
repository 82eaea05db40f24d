"""Delorme 2018's three-point bending beam (§4.1, §6.1) as a PD scene and its FE peer.

Beam L x W x t = 128 x 32 x 12.7 mm, origin at the bottom-left corner, supports S = 96 mm
apart symmetric about mid-span, F = 1000 N down at the top of mid-span, E = 4000 MPa,
nu = 0.3, plane stress. Delorme 2018 loads one FE node and fixes the support nodes; its PD model
applies loads and displacements on thin material layers V_f, V_u (eq 11). Here both models
use the same fixed-size patches (``PATCH_WIDTH`` x ``PATCH_DEPTH``): a *pin* (u = 0) under
the left support, a *roller* (u_y = 0) under the right one (pinning both supports makes an
arching force whose size depends on the mesh, see shared/notes/reference-problems.md), and
the load as a uniform body force over a patch at the top of mid-span. The PD model then
converges, as delta -> 0, to exactly the FE problem, which is not singular at the patches.
Patches are thinner than delta at coarse resolutions by design: a fixed physical patch keeps
the continuum problem the same at every h (the patch is a support, not a boundary layer).
"""
from __future__ import annotations

import numpy as np

import bayespd as bp
from bayespd.reference.fem import BodyLoad, FESolution, Region, Support, solve_box

LENGTH, WIDTH, THICKNESS, SPAN = 128.0, 32.0, 12.7, 96.0  # mm
FORCE, YOUNG, POISSON = 1000.0, 4000.0, 0.3  # N, MPa, -
PATCH_WIDTH, PATCH_DEPTH = 4.0, 2.0  # mm: support and load patches (multiples of 2/3 and 0.5)

_X_PIN, _X_ROLLER, _X_LOAD = (LENGTH - SPAN) / 2, (LENGTH + SPAN) / 2, LENGTH / 2


def _patch(x_centre: float, y_lo: float) -> Region:
    return Region((x_centre - PATCH_WIDTH / 2, y_lo), (x_centre + PATCH_WIDTH / 2, y_lo + PATCH_DEPTH))


PIN = _patch(_X_PIN, 0.0)
ROLLER = _patch(_X_ROLLER, 0.0)
LOAD = _patch(_X_LOAD, WIDTH - PATCH_DEPTH)


def params(delta: float, nu: float = POISSON) -> dict:
    """PD params {K, G, delta} of the beam material (Delorme 2018 §6.1: K = 3333.33, G = 1538.46
    at nu = 0.3; K is the 3D bulk modulus, as bp.LPS takes it in plane stress too)."""
    K, G = bp.moduli_from_young(YOUNG, nu)
    return {"K": float(K), "G": float(G), "delta": float(delta)}


def pd_scene(h: float, delta_max: float, points=None, rule: str = "linear", **lps_options) -> bp.Scene:
    """LPS plane-stress scene on a cell-centred grid of spacing h (h must divide 2 mm).

    A particle belongs to a patch when its cell centre lies in the patch; with h dividing the
    patch corners, the union of those cells is the patch itself. ``rule``: the bonds'
    partial-volume ramp; ``lps_options`` go to ``bp.LPS`` (e.g. ``surface_correction=True``).
    """
    p = bp.grid_2d(LENGTH, WIDTH, h, thickness=THICKNESS)
    material = bp.LPS(p, bp.find_bonds(p, delta_max, rule), plane="stress", **lps_options)
    dirichlet = [bp.Dirichlet(PIN.contains(p.x), (0.0, 0.0)),
                 bp.Dirichlet(ROLLER.contains(p.x), (None, 0.0))]
    loads = [bp.Load(LOAD.contains(p.x), (0.0, -FORCE))]
    observation = None if points is None else bp.Observation(p, points)
    return bp.Scene(material, dirichlet, loads, observation)


REFERENCE_MESH = {"h": 0.5, "order": 2, "grading": 6}  # changes < 2e-5 from h = 1 (measured)
CHECK_MESH = {"h": 1.0, "order": 2, "grading": 6}


def fe_solution(h: float = 0.5, order: int = 2, grading: int = 6, stiffness=None,
                nu: float = POISSON) -> FESolution:
    """The FE peer on a Q``order`` mesh of size h graded toward the support patches: the same
    pin, roller and load patches (``stiffness``: an anisotropic Voigt tensor, see solve_box;
    ``nu``: Poisson's ratio, E = YOUNG)."""
    return solve_box((LENGTH, WIDTH), h, YOUNG, nu,
                     [Support(PIN, (0.0, 0.0)), Support(ROLLER, (None, 0.0))],
                     [BodyLoad(LOAD, (0.0, -FORCE))], order=order, plane="stress",
                     thickness=THICKNESS, grading=grading, stiffness=stiffness)


def away_mask(x: np.ndarray, margin: float) -> np.ndarray:
    """Points farther than ``margin`` from every support and load patch (comparison region)."""
    return np.min([r.distance(x) for r in (PIN, ROLLER, LOAD)], axis=0) > margin
