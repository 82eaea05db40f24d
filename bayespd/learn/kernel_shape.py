"""Identified coordinates of a Bernstein kernel's shape (You 2023 eqs 4.2-4.3).

Only the shape of omega = sum_k D_k r^-alpha B_{k,P}(r / delta) matters (the LPS forces scale
with omega / m), so D and c D (c > 0) are one kernel, and a model with D in R^(P+1) has a flat
direction. Every kernel with a positive moment a . D, a_k = int_0^1 s^(3-alpha) B_{k,P}(s) ds
(``Bernstein.moment``; m > 0 needs it), has exactly one representative on the hyperplane
a . D = a . 1 through the constant kernel D = 1 (for alpha = 0 the plane of
``learn.kernel.normalised``). Written D = D_0 + N t, with D_0 the plane's point nearest the origin
(distance rho = a . 1 / |a|) and N an orthonormal basis of a's null space, t in R^P are
identified coordinates. A direction uniform on the sphere (D ~ N(0, I), kept where a . D > 0)
lands at t = rho x_perp / |x_par|: the P-variate Student t with one degree of freedom (Cauchy)
of scale rho centred at 0 (``uniform_direction_scale``).
"""
from __future__ import annotations

import torch


class KernelShape:
    """The hyperplane coordinates of ``influence`` (a ``Bernstein``): ``coefficients(t)`` -> D,
    ``coordinates(D)`` -> t (D rescaled onto the plane first)."""

    def __init__(self, influence):
        n = influence.degree + 1
        self.a = torch.stack([torch.as_tensor(influence.moment(3, 1.0, {"D": e})) for e in torch.eye(n)])
        level = self.a.sum()
        self.origin = self.a * level / self.a.dot(self.a)
        self.uniform_direction_scale = float(level / self.a.norm())
        q, _ = torch.linalg.qr(self.a[:, None], mode="complete")
        self.basis = q[:, 1:]  # (P + 1, P), orthonormal, orthogonal to a

    @property
    def dim(self) -> int:
        return self.basis.shape[1]

    def coefficients(self, t) -> torch.Tensor:
        """D (..., P + 1) on the plane a . D = a . 1 at coordinates t (..., P)."""
        return self.origin + torch.as_tensor(t) @ self.basis.T

    def coordinates(self, D) -> torch.Tensor:
        """t (..., P) of the kernel D (..., P + 1), any positive scale of it."""
        D = torch.as_tensor(D, dtype=self.a.dtype)
        moment = D @ self.a
        if not bool(torch.all(moment > 0)):
            raise ValueError("the kernel's moment int omega r^3 dr is not positive (m <= 0): no LPS "
                             "kernel has this shape; flip the sign of D")
        return (D * (self.a.sum() / moment)[..., None]) @ self.basis
