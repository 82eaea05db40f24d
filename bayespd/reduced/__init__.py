"""Reduced-order models of a Scene and discretisation-error terms (no Pyro)."""
from .discrepancy import Discrepancy, estimate_discrepancy, prior_draws

__all__ = ["Discrepancy", "estimate_discrepancy", "prior_draws"]
