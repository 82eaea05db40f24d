"""bayespd: calibrate peridynamic models of solids and fracture with honest uncertainty.

The numerical core (this package minus ``bayespd.infer``) never imports Pyro.
"""
import torch

torch.set_default_dtype(torch.float64)

from bayespd.discretize import Particles, from_points, grid_2d, grid_3d  # noqa: E402
from bayespd.bonds import Bonds, find_bonds  # noqa: E402
from bayespd.materials import LPS, BondBased, moduli_from_young  # noqa: E402
from bayespd.boundary import Dirichlet, Load  # noqa: E402
from bayespd.observe import Observation  # noqa: E402
from bayespd.problem import Scene  # noqa: E402
from bayespd.sparse import NotPositiveDefiniteError, solve  # noqa: E402

__all__ = [
    "Particles", "grid_2d", "grid_3d", "from_points", "Bonds", "find_bonds", "LPS", "BondBased", "moduli_from_young",
    "Dirichlet", "Load", "Observation", "Scene", "NotPositiveDefiniteError", "solve",
]
