"""Bayesian inference (Pyro): NUTS / HMC / SVI / Laplace fits stored as ArviZ-style ``xarray.DataTree``."""

from .datatree import load, modes, save, summary, to_inference_data
from .fit import fit
from .laplace import NotPositiveDefiniteHessian
from .mcmc import ChainDivergedError
from .priors import ScaledBeta

__all__ = ["fit", "to_inference_data", "save", "load", "summary", "modes", "ScaledBeta",
           "NotPositiveDefiniteHessian", "ChainDivergedError"]
