"""The Tikhonov misfit weighted by an approximation-error term (Kaipio & Somersalo 2007; the
term of ``bayespd.reduced.discrepancy``): generalised least squares

    1/2 r^T C^-1 r,   r = H u(p) + s mu(p) - y,   C = s0^2 (W W^T + diag d) + sigma^2 I,

over the observed entries, with the term's mean mu(p) (its trend in the parameters) and s the
displacement scale of a relative term (rms of H u(p); 1 for an absolute one). The covariance is
frozen at the starting point's scale s0 (the MAP of the Bayesian model differs by the
log-determinant of C(s), i.e. by O((s - s0) / s0), and ``tikhonov`` refreshes s0 at the
estimate when it moved). The whitening C^-1/2 = (I + B B^T)^-1/2 D^-1/2, D = diag(s0^2 d +
sigma^2), B = D^-1/2 s0 W = Q S V^T (thin SVD), is

    (I + B B^T)^-1/2 x = x + Q (((1 + S^2)^-1/2 - 1) Q^T x),

so r^T C^-1 r is a sum of squares and Gauss-Newton applies as without the term.
"""
from __future__ import annotations

import torch


class ErrorWeights:
    """Whitened residuals C^-1/2 (H u + s mu(p) - y) on the observed entries ``observed`` (bool,
    the shape of y) for the term ``discrepancy`` (a ``bayespd.Discrepancy`` estimated at the
    observation's points), noise sd ``sigma``, the covariance frozen at ``prediction0``."""

    def __init__(self, discrepancy, observed: torch.Tensor, sigma: float, prediction0: torch.Tensor,
                 params0: dict):
        discrepancy.check_shape(tuple(observed.shape), "the observations")
        self.term, self.keep, self.sigma = discrepancy, observed.reshape(-1), float(sigma)
        self.refresh(prediction0, params0)

    def refresh(self, prediction: torch.Tensor, params: dict) -> None:
        """Freeze C at the scale of ``prediction`` (the model's observation at ``params``)."""
        with torch.no_grad():
            _, factor, diag = self.term.gaussian(prediction.detach(), {k: v.detach() if torch.is_tensor(v) else v
                                                                       for k, v in params.items()})
            self.scale = float(prediction.detach().square().mean().sqrt())
            d = diag[self.keep] + self.sigma**2
            if not bool((d > 0).all()):
                raise ValueError("the discrepancy's covariance is singular on some observed entries and sigma = 0: "
                                 "pass the noise sd sigma > 0")
            B = factor[self.keep] / d.sqrt()[:, None]
            Q, S, _ = torch.linalg.svd(B, full_matrices=False)
            self.inv_sqrt_d, self.Q, self.shrink = d.rsqrt(), Q, (1 + S**2).rsqrt() - 1

    def __call__(self, prediction: torch.Tensor, params: dict, y: torch.Tensor) -> torch.Tensor:
        """C^-1/2 r on the observed entries (a vector)."""
        loc, _, _ = self.term.gaussian(prediction, params)
        x = (loc - y).reshape(-1)[self.keep] * self.inv_sqrt_d
        return x + self.Q @ (self.shrink * (self.Q.T @ x))
