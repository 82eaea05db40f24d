"""Reduced-order likelihoods: a POD basis with the operator kept affine in the moduli and
splined in delta (``ReducedScene``), with an a-posteriori error estimate."""

from .scene import ReducedScene

__all__ = ["ReducedScene"]
