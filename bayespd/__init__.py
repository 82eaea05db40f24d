"""bayespd: calibrate peridynamic models of solids and fracture with honest uncertainty.

The numerical core (this package minus ``bayespd.infer`` and the installed ``bayespd.models``)
never imports Pyro. ``__all__`` is the public API that the README's example and ``models/`` use.
"""
import torch

torch.set_default_dtype(torch.float64)

from bayespd.discretize import Particles, from_points, grid_2d, grid_3d  # noqa: E402
from bayespd.bonds import Bonds, check_horizon, find_bonds, precrack  # noqa: E402
from bayespd.influence import Bernstein, Conical, Constant, Gaussian  # noqa: E402
from bayespd.materials import LPS, BondBased, ConicalBondBased, moduli_from_young, young_from_moduli  # noqa: E402
from bayespd.boundary import Constraints, Dirichlet, Load  # noqa: E402
from bayespd.observe import (GridObservation, Observation, OpeningObservation, ParticleObservation,  # noqa: E402
                             edge_mask, finite_mask, grid_points, model_data)
from bayespd.dic import frame_data, read_dice  # noqa: E402
from bayespd.fields import Field, from_grid_field, from_point_field  # noqa: E402
from bayespd.field_files import read_field  # noqa: E402
from bayespd.rigid import RigidNuisance  # noqa: E402
from bayespd.supports import point_load, point_support, roller, traction  # noqa: E402
from bayespd.symmetry import SymmetryPlane  # noqa: E402
from bayespd.vtk import Series as VTKSeries, write_pvd, write_vtu  # noqa: E402
from bayespd.meshes import from_mesh  # noqa: E402
from bayespd.gmrf import GMRF  # noqa: E402
from bayespd.nonlinear import NonlinearBonds  # noqa: E402
from bayespd.problem import Scene  # noqa: E402
from bayespd.held import Held  # noqa: E402
from bayespd.learn.kernel import lps_params, solvability_penalty  # noqa: E402
from bayespd.learn.kernel_shape import KernelShape  # noqa: E402
from bayespd.learn.dispersion import relative_compliance_error, shell_of  # noqa: E402
from bayespd.linalg.adjoint import solve  # noqa: E402
from bayespd.linalg.sparse import ConvergenceError, NotPositiveDefiniteError  # noqa: E402
from bayespd.reduced import (Discrepancy, ElasticFeatures, LogFeatures, ReducedScene,  # noqa: E402
                             estimate_discrepancy, gaussian_draws, posterior_draws, prior_draws)

__all__ = [
    "Particles", "grid_2d", "grid_3d", "from_points", "from_mesh", "Bonds", "find_bonds", "check_horizon",
    "precrack",
    "Constant", "Conical", "Gaussian", "Bernstein", "LPS", "BondBased", "ConicalBondBased",
    "moduli_from_young", "young_from_moduli",
    "Constraints", "Dirichlet", "Load", "NonlinearBonds", "GMRF", "Observation", "OpeningObservation", "ParticleObservation", "GridObservation", "grid_points",
    "edge_mask", "finite_mask", "model_data", "read_dice", "frame_data",
    "Field", "from_grid_field", "from_point_field", "read_field", "RigidNuisance",
    "point_support", "roller", "point_load", "traction", "SymmetryPlane", "write_vtu", "write_pvd",
    "VTKSeries", "Scene", "Held", "NotPositiveDefiniteError", "ConvergenceError", "solve",
    "ReducedScene", "Discrepancy", "estimate_discrepancy", "prior_draws", "posterior_draws", "gaussian_draws", "LogFeatures",
    "ElasticFeatures", "lps_params", "solvability_penalty", "KernelShape", "relative_compliance_error", "shell_of",
]
