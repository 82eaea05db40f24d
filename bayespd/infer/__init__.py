"""Bayesian inference (Pyro): NUTS / SVI fits stored as ArviZ-style ``xarray.DataTree``."""

from .datatree import load, save, summary, to_inference_data
from .fit import fit
from .priors import ScaledBeta

__all__ = ["fit", "to_inference_data", "save", "load", "summary", "ScaledBeta"]
