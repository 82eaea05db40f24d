"""The square of Turner 2015 §4 (Fig. 2), shared by tikhonov_constant.py, tikhonov_heterogeneous.py
and tests/inverse/test_least_squares.py: L = 1000, cells of size h with the centroids of the outer cells on
the edges (footnote 4: h = 100 gives 11 x 11 = 121 cells), the bottom edge (y = 0) fixed, a
force F = (1000, 1000) spread over the cells of the top edge (footnote 3), plane strain (eq 5).

The paper does not state the horizon; we take delta = 3 h of the calibrated model (300), and
keep the same physical horizon on finer data grids. It fixes "the bottom edge": one row of
cells, which we follow (not a layer one horizon thick).
"""
from __future__ import annotations

import numpy as np
import torch

import bayespd as bp

SIDE, H, FORCE = 1000.0, 100.0, (1000.0, 1000.0)
DELTA = 3 * H
K0, MU0 = 666.67, 400.0  # §4.1 (and k_0, mu_0 of eqs 26-27)
GAMMA_K, GAMMA_MU = 0.00025, 0.0002  # eqs 26-27


def square_scene(h: float = H, delta: float = DELTA, points=None, cell: float | None = None) -> bp.Scene:
    """The Fig. 2 problem observing ``points`` (default: every particle). The body is the square
    grown by cell/2 (default cell = h: an (SIDE/h + 1)^2 grid with centroids on the edges); the
    fixed and loaded regions are the bottom and top strips cell/2 deep. A finer grid of the same
    body passes cell = H: same body, same regions, only the discretisation changes."""
    cell = h if cell is None else cell
    p = bp.grid_2d(SIDE + cell, SIDE + cell, h, origin=(-cell / 2, -cell / 2))
    material = bp.LPS(p, bp.find_bonds(p, delta), plane="strain")
    observation = (bp.ParticleObservation(p, np.ones(p.n, dtype=bool)) if points is None
                   else bp.Observation(p, points))
    return bp.Scene(material, [bp.Dirichlet(p.x[:, 1] < cell / 2)],
                    [bp.Load(p.x[:, 1] > SIDE - cell / 2, FORCE)], observation)


def graded_moduli(x: np.ndarray) -> dict:
    """k(x), mu(x) of eqs 26-27 with r = ||x|| measured from the fixed corner (0, 0)."""
    r = np.linalg.norm(x, axis=1)
    return {"K": torch.as_tensor(K0 * (1 - GAMMA_K * r)), "G": torch.as_tensor(MU0 * (1 + GAMMA_MU * r))}


def noisy_fine_data(truth_of_x, points: np.ndarray, level: float = 0.01, seed: int = 0, refine: int = 2):
    """Displacements at ``points`` computed on a grid ``refine`` times finer (the same physical
    horizon; no inverse crime), plus Gaussian noise of sd ``level`` x max |u|.
    ``truth_of_x(x)`` gives the moduli at the fine particles. Returns (y, noise sd)."""
    fine = square_scene(H / refine, DELTA, points, cell=H)
    with torch.no_grad():
        clean = fine.observe(fine.solve(dict(truth_of_x(fine.particles.x), delta=DELTA)))
    sd = level * float(clean.abs().max())
    gen = torch.Generator().manual_seed(seed)
    return clean + sd * torch.randn(clean.shape, generator=gen), sd
