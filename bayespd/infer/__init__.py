"""Bayesian inference (Pyro): NUTS / HMC / SVI / Laplace fits stored as ArviZ-style ``xarray.DataTree``."""

from .checks import check_priors
from .correction import UnreliableCorrectionError, corrected_summary, importance_correction, laplace_importance
from .datatree import load, modes, save, summary, to_inference_data, young_intervals
from .fit import METHODS, fit, register
from .laplace import Laplace, NotPositiveDefiniteHessian
from .likelihoods import NoiseCovariance, StationaryMarginal, euler_maruyama_transition
from .mcmc import ChainDivergedError, CheckpointMismatchError
from .method import Draws, Method
from .priors import ScaledBeta
from .samplers import HMC, NUTS
from .svi import SVI
from .workers import MainGuardError, WorkerError

__all__ = ["fit", "NUTS", "HMC", "SVI", "Laplace", "Method", "Draws", "METHODS", "register",
           "to_inference_data", "save", "load", "summary", "modes", "young_intervals", "ScaledBeta", "check_priors",
           "NotPositiveDefiniteHessian", "ChainDivergedError", "NoiseCovariance", "StationaryMarginal",
           "euler_maruyama_transition", "importance_correction", "corrected_summary", "laplace_importance",
           "UnreliableCorrectionError", "CheckpointMismatchError", "WorkerError", "MainGuardError"]
