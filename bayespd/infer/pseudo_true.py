"""Pseudo-true parameters: where the posterior of a misspecified model concentrates.

Data drawn from a law P outside the model family {Q_theta} (a finer PD model, a smaller time
step: the no-inverse-crime rule) make the posterior concentrate, as the data grow, at

    theta* = argmin_theta KL(P || Q_theta)

(Berk 1966; White 1982), not at the parameters P was made with. theta* - truth is the
model-form bias; posterior - theta* is the error of the inference. For the Gaussian
likelihoods of the Brownian-bias model the KL is closed form:

* stationary frames: KL(N(m, S) || N(m', S')) per frame (``torch.distributions.kl_divergence``
  of the two multivariate normals);
* a path U_0..U_T of a linear chain U_{n+1} = M U_n + c + N(0, Sigma) (the data's, with U_0
  fixed) scored by the model's transitions N(B U_n + a, Q): the sum over n of the expected
  per-step KL, E over U_n ~ N(mu_n, P_n) of KL(N(M U_n + c, Sigma) || N(B U_n + a, Q)) =
  [tr(Q^-1 Sigma) - d + log det Q - log det Sigma + r_n^T Q^-1 r_n
  + tr((M - B)^T Q^-1 (M - B) P_n)] / 2, r_n = (M - B) mu_n + c - a, with mu_n and P_n
  propagated by the data's chain.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from scipy.optimize import minimize

from bayespd.linalg.sparse import ConvergenceError


def kl_projection(kl, init, bounds: dict, gtol: float = 1e-9, max_iter: int = 500):
    """(theta*, kl(theta*)): the minimiser of ``kl(theta)`` (a differentiable torch scalar of
    a dict of scalar tensors) over the names in ``init``, each kept inside ``bounds[name]`` =
    (lo, hi) (hi may be inf) by z -> lo + e^z or lo + (hi - lo) sigmoid(z); L-BFGS from
    ``init`` with autograd gradients, or from each of a list of starts, keeping the lowest
    (the PD laws have kinks in delta, and local minima between them). Raises
    ConvergenceError when L-BFGS does not converge."""
    if isinstance(init, (list, tuple)):
        return min((kl_projection(kl, start, bounds, gtol, max_iter) for start in init), key=lambda r: r[1])
    names = list(init)
    for k in names:
        lo, hi = bounds[k]
        if not lo < init[k] < hi:
            raise ValueError(f"the start of {k!r} ({init[k]}) must lie inside its bounds ({lo}, {hi})")

    def constrain(z):
        out = {}
        for k, zk in zip(names, z):
            lo, hi = bounds[k]
            out[k] = lo + torch.exp(zk) if math.isinf(hi) else lo + (hi - lo) * torch.sigmoid(zk)
        return out

    def unconstrain(k, v):
        lo, hi = bounds[k]
        return math.log(v - lo) if math.isinf(hi) else math.log((v - lo) / (hi - v))

    def value_and_grad(x):
        z = torch.tensor(x, requires_grad=True)
        value = kl(constrain(z))
        (grad,) = torch.autograd.grad(value, z)
        return float(value.detach()), grad.numpy()

    x0 = np.array([unconstrain(k, float(init[k])) for k in names])
    res = minimize(value_and_grad, x0, jac=True, method="L-BFGS-B",
                   options={"maxiter": max_iter, "gtol": gtol, "ftol": 1e-15})
    if not np.all(np.abs(res.jac) <= 1e-5 * max(1.0, abs(res.fun))):
        raise ConvergenceError(f"the KL projection did not converge ({res.message}; "
                               f"|grad| = {np.abs(res.jac).max():.3g})")
    theta = {k: float(v) for k, v in constrain(torch.as_tensor(res.x)).items()}
    return theta, float(res.fun)


def chain_kl(M, c, Sigma, B, a, Q, u0, steps: int) -> torch.Tensor:
    """KL of the path law of the data's chain (M, c, Sigma; U_0 = u0) from the model's
    transitions (B, a, Q) over ``steps`` steps (module docstring)."""
    d = len(u0)
    LQ = torch.linalg.cholesky(Q)
    dB, da = M - B, c - a
    G = dB.T @ torch.cholesky_solve(dB, LQ)  # (M - B)^T Q^-1 (M - B)
    per_step = torch.trace(torch.cholesky_solve(Sigma, LQ)) - d + 2 * torch.log(torch.diagonal(LQ)).sum() \
        - torch.linalg.slogdet(Sigma)[1]
    mu, P = u0, torch.zeros(d, d, dtype=u0.dtype)
    total = steps * per_step
    for _ in range(steps):
        r = dB @ mu + da
        total = total + torch.cholesky_solve(r[:, None], LQ)[:, 0] @ r + (G * P).sum()
        mu, P = M @ mu + c, M @ P @ M.T + Sigma
    return 0.5 * total


def euler_maruyama_chain(scene, params: dict, eta, C, dt: float, substeps: int = 1):
    """(M, c, Sigma) of ``substeps`` Euler-Maruyama steps of dt / substeps of Dodwell 2019 eq 4
    in the elastic regime, U_{n+1} = M U_n + c + N(0, Sigma), dense on the free dofs
    (each step U + (h / eta) C (p - A U) + N(0, 2 h C), h = dt / substeps); ``C`` a
    ``likelihoods.NoiseCovariance``."""
    n = len(scene.constraints.free_dofs)
    eye = torch.eye(n, dtype=torch.float64)
    A = scene.constraints.pattern.matvec(scene.stiffness_values(params), eye)
    Cd = C.matmul(eye)
    h = dt / substeps
    M1, c1, S1 = eye - (h / eta) * Cd @ A, (h / eta) * Cd @ scene.free_load(params), 2 * h * Cd
    M, c, Sigma = eye, torch.zeros(n, dtype=torch.float64), torch.zeros(n, n, dtype=torch.float64)
    for _ in range(substeps):
        M, c, Sigma = M1 @ M, M1 @ c + c1, M1 @ Sigma @ M1.T + S1
    return M, c, 0.5 * (Sigma + Sigma.T)
