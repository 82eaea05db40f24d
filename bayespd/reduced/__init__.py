"""Reduced-order likelihoods (no Pyro): a POD reduced scene kept affine in the moduli and
piecewise-polynomial in delta, with an a-posteriori error estimate (``ReducedScene``), and the
approximation-error term of a model against a finer reference (``Discrepancy``)."""
from .discrepancy import Discrepancy, estimate_discrepancy
from .draws import gaussian_draws, posterior_draws, prior_draws
from .scene import ReducedScene, ToleranceMissed
from .trend import ElasticFeatures, LogFeatures

__all__ = ["ReducedScene", "ToleranceMissed", "Discrepancy", "estimate_discrepancy", "prior_draws", "posterior_draws", "gaussian_draws",
           "LogFeatures", "ElasticFeatures"]
