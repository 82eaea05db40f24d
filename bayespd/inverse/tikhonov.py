"""Tikhonov-regularised least squares with adjoint gradients (seed 000 eq 12).

    J(p) = 1/2 sum_obs mask (H u(p) - y)^2 / sigma^2 + psi/2 ||log p - log p_ref||^2,

minimised over log-parameters (positivity for free) with scipy's L-BFGS-B. Each gradient
costs one forward and one adjoint solve whatever the number of parameters.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.optimize
import torch


@dataclass
class TikhonovResult:
    params: dict
    objective: float
    residual_rms: float
    iterations: int
    evaluations: int
    wall_time_s: float
    converged: bool
    message: str


def tikhonov(scene, y, init: dict, *, fixed: dict | None = None, mask=None, sigma: float = 1.0,
             psi: float = 0.0, ref: dict | None = None, bounds: dict | None = None,
             gtol: float = 1e-12, maxiter: int = 500) -> TikhonovResult:
    """Estimate the parameters named in ``init`` (starting values) from observations ``y``.

    ``fixed`` holds parameters kept constant (e.g. ``{"delta": 3.0}``), ``bounds`` optional
    (low, high) per parameter in natural units, ``ref`` the regularisation centre (defaults
    to ``init``).
    """
    names = list(init)
    fixed = dict(fixed or {})
    if set(names) & set(fixed):
        raise ValueError("a parameter cannot be both estimated and fixed")
    y = torch.as_tensor(y)
    w = torch.ones_like(y) if mask is None else torch.as_tensor(mask, dtype=y.dtype)
    if not bool(torch.all(torch.isfinite(y[w > 0]))):
        raise ValueError("observations contain NaN or inf where the mask is true: mask them out")
    z_ref = torch.log(torch.tensor([float((ref or init)[k]) for k in names]))
    evaluations = 0

    def objective(z):
        nonlocal evaluations
        evaluations += 1
        zt = torch.tensor(z, requires_grad=True)
        params = dict(fixed, **{k: torch.exp(zt[i]) for i, k in enumerate(names)})
        r = (scene.observe(scene.solve(params)) - y) * w / sigma
        J = 0.5 * (r**2).sum() + 0.5 * psi * ((zt - z_ref) ** 2).sum()
        (g,) = torch.autograd.grad(J, zt)
        return float(J.detach()), g.numpy()

    log_bounds = [tuple(np.log(bounds[k])) if bounds and k in bounds else (None, None) for k in names]
    z0 = np.log([float(init[k]) for k in names])
    start = time.perf_counter()
    res = scipy.optimize.minimize(objective, z0, jac=True, method="L-BFGS-B", bounds=log_bounds,
                                  options={"gtol": gtol, "ftol": 1e-15, "maxiter": maxiter})
    wall = time.perf_counter() - start
    estimate = {k: float(np.exp(res.x[i])) for i, k in enumerate(names)}
    with torch.no_grad():
        r = (scene.observe(scene.solve(dict(fixed, **estimate))) - y) * w
    rms = float(torch.sqrt((r**2).sum() / w.sum()))
    return TikhonovResult(estimate, float(res.fun), rms, int(res.nit), evaluations, wall,
                          bool(res.success), str(res.message))
