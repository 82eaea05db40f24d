"""Solvers: explicit dynamics (velocity Verlet), overdamped Langevin dynamics (Dodwell 2019 eq 4)
with white or spatially correlated (Karhunen-Loeve) noise, quasi-static load stepping with bond
breaking (You 2023 §5.2) and the stochastic fracture driver."""
from bayespd.solvers.dynamics import (NumericalInstabilityError, Trajectory, critical_time_step,
                                      lumped_mass, stable_time_step, velocity_verlet)
from bayespd.solvers.langevin import Langevin
from bayespd.solvers.linear import LinearForce, largest_eigenvalue, linear_elastic
from bayespd.solvers.noise import Covariance, KLCovariance, karhunen_loeve, white_noise
from bayespd.solvers.body import LoadedBody
from bayespd.solvers.quasistatic import QuasiStaticResult, equilibrium, quasi_static
from bayespd.solvers.fracture import Realisation, StochasticFracture

__all__ = [
    "NumericalInstabilityError", "Trajectory", "critical_time_step", "lumped_mass",
    "stable_time_step", "velocity_verlet", "Langevin", "LinearForce", "largest_eigenvalue",
    "linear_elastic", "Covariance", "KLCovariance", "karhunen_loeve", "white_noise",
    "LoadedBody", "QuasiStaticResult", "equilibrium", "quasi_static", "Realisation", "StochasticFracture",
]
