"""Deterministic inversion baselines."""
from bayespd.inverse.tikhonov import TikhonovResult, tikhonov

__all__ = ["tikhonov", "TikhonovResult"]
