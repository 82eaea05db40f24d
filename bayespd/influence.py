"""Influence functions omega(r, delta) weighting each bond of a family.

Each is differentiable in delta and in its own parameters, and gives its radial moments
M_k(delta) = int_0^delta omega(r) r^k dr in closed form, which the materials use to calibrate
their constants with the same weights (so the bulk response does not depend on the choice):
LPS absorbs omega into the weighted volume m (Turner 2015 eq 9), bond-based divides its
micromodulus by int omega r dV (see ``BondBased.micromodulus``).

A learnable influence function names its parameters in ``param_names``; they are passed in
the same ``params`` dict as the moduli (e.g. ``{"K": ..., "G": ..., "D": ..., "delta": ...}``).
"""
from __future__ import annotations

import math

import torch
from scipy.special import gamma, gammainc


class Influence:
    """The interface: ``omega(r, delta, params)`` per bond and ``moment(k, delta, params)``
    = int_0^delta omega(r) r^k dr; ``param_names`` lists learnable parameters."""

    param_names: tuple[str, ...] = ()


class Constant(Influence):
    """omega = 1."""

    def __call__(self, r: torch.Tensor, delta, params: dict) -> torch.Tensor:
        return torch.ones_like(r)

    def moment(self, k: int, delta, params: dict) -> torch.Tensor:
        return torch.as_tensor(delta) ** (k + 1) / (k + 1)


class Conical(Influence):
    """omega = 1 - r / delta."""

    def __call__(self, r, delta, params):
        return 1 - r / delta

    def moment(self, k, delta, params):
        return torch.as_tensor(delta) ** (k + 1) * (1 / (k + 1) - 1 / (k + 2))


class Gaussian(Influence):
    """omega = exp(-(r / (width delta))^2), truncated at r = delta."""

    def __init__(self, width: float = 0.5):
        if not width > 0:
            raise ValueError("Gaussian width (a fraction of delta) must be positive")
        self.width = float(width)

    def __call__(self, r, delta, params):
        return torch.exp(-(r / (self.width * delta)) ** 2)

    def moment(self, k, delta, params):
        # r = width delta sqrt(t): (width delta)^(k+1) / 2 * lower_gamma((k+1)/2, 1/width^2)
        a = (k + 1) / 2
        shape = self.width ** (k + 1) / 2 * gamma(a) * gammainc(a, self.width**-2)
        return torch.as_tensor(delta) ** (k + 1) * shape


def _powers(x: torch.Tensor, degree: int) -> torch.Tensor:
    """[x^0, ..., x^degree] along the last axis by products: finite derivatives of every order at
    x = 0, where x**k with a tensor exponent k = 0 has 0 * inf = NaN ones."""
    return torch.cumprod(torch.cat([torch.ones_like(x), x.expand(*x.shape[:-1], degree)], -1), -1)


class Bernstein(Influence):
    """omega = sum_k D_k r^-alpha B_{k,P}(r / delta) (You 2023 eqs 4.2-4.3) with learnable
    coefficients ``params["D"]`` (P + 1 values). Only the shape of omega matters: the
    material constants are calibrated with it, so D is identifiable up to a common scale.
    """

    param_names = ("D",)

    def __init__(self, degree: int, alpha: float = 0.0):
        if degree < 0 or int(degree) != degree:
            raise ValueError("Bernstein degree P must be a non-negative integer")
        if not alpha < 3:
            raise ValueError("the singularity order alpha must be below 3 (You 2023 eq 4.4)")
        self.degree, self.alpha = int(degree), float(alpha)
        k = torch.arange(self.degree + 1, dtype=torch.get_default_dtype())
        self._k = k
        self._binom = torch.tensor([math.comb(self.degree, int(i)) for i in k])

    def _coefficients(self, params) -> torch.Tensor:
        if "D" not in params:
            raise ValueError(f"the Bernstein influence function needs params['D'] "
                             f"({self.degree + 1} coefficients)")
        D = torch.as_tensor(params["D"])
        if D.shape != (self.degree + 1,) or not bool(torch.all(torch.isfinite(D))):
            raise ValueError(f"params['D'] must hold {self.degree + 1} finite coefficients")
        return D

    def __call__(self, r, delta, params):
        D = self._coefficients(params)
        # bonds up to delta + h/2 carry a partial volume: they take the value at r = delta (the
        # polynomials themselves change sign beyond 1, which could cancel m = sum omega |xi|^2 V)
        rho = torch.clamp(r / delta, max=1.0)[:, None]
        basis = self._binom * _powers(rho, self.degree) * _powers(1 - rho, self.degree).flip(-1)
        return (basis @ D) / r**self.alpha

    def moment(self, k, delta, params):
        # int_0^delta r^(k-alpha) B_{j,P}(r/delta) dr = delta^(k+1-alpha) C(P,j) B(j+k-alpha+1, P-j+1)
        D = self._coefficients(params)
        a, b = self._k + k - self.alpha + 1, self.degree - self._k + 1
        beta = torch.exp(torch.lgamma(a) + torch.lgamma(b) - torch.lgamma(a + b))
        return torch.as_tensor(delta) ** (k + 1 - self.alpha) * (self._binom * beta * D).sum()
