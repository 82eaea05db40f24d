"""Deterministic inversion baselines.

``tikhonov`` (the function; its module is ``least_squares``, so that the name
``bayespd.inverse.tikhonov`` is the function and nothing shadows it), ``vfm`` (the PD Virtual
Fields Method), ``vfm_defaults`` (the horizon and ramp chosen by the VFM residual) and
``vfm_noise`` (the noise-weighted closed form and its standard errors)."""
from bayespd.inverse.least_squares import TikhonovResult, tikhonov

__all__ = ["tikhonov", "TikhonovResult"]
