"""Exact Gaussian likelihoods of the Brownian-bias (overdamped Langevin) model, Dodwell 2019 eqs 3-4.

    dU = -eta^-1 C grad V(U) dt + sqrt(2 C) dB,   V(U) = U^T A U / 2 - p^T U,   A = K_ff + eps I

(elastic regime; the state U is the free dofs, p = f_f - K_fc u_c).

**Stationary marginal.** The Fokker-Planck equation of eq 4 is
d_t rho = div(C (eta^-1 rho grad V + grad rho)); its flux vanishes for rho ~ exp(-V / eta)
whatever the SPD C, so the invariant law is N(A^-1 p, eta A^-1): eta is a temperature. (An
earlier reading found the same for eq 4 as printed; the drift -eta^-1 C grad V with noise
sqrt(2C) is eq 4 run at time t / eta of dU = -C grad V dt + sqrt(2 eta C) dB.) Observations
y_f = H U_f + e_f, e_f ~ N(0, sigma^2 I), of F independent stationary frames U_f give

    y_f ~ N(H A^-1 p (+ H_c u_c), eta S + sigma^2 I),   S = H A^-1 H^T,

computed with one factorisation of A for the n_obs + 1 right-hand sides [p, H^T] and a dense
Cholesky of the n_obs x n_obs covariance (moderate n_obs). eta and sigma are separable in
principle from one frame whenever S is not a multiple of I (in S's eigenbasis the residual
has independent components of variance eta lambda_k + sigma^2), and F frames multiply the
information by F.

**Euler-Maruyama transition.** U_{n+1} | U_n ~ N(U_n + (dt / eta) C (p - A U_n), 2 dt C):
an exact discrete-time likelihood. With C = s^2 R (R of unit diagonal scale, length l), the
noise covariance fixes s^2 and l; the drift fixes s^2 A / eta and s^2 p / eta, hence, with
the load p known, eta and A (K, G, delta, eps). Only with an unknown load factor lam do
(eta, A, lam) enter as (A / eta, lam / eta): a scale family (c eta, c A, c lam) then gives
the same process. All of (K, G, delta, eta, s, l) are identifiable from a path with a known
load; the posterior of eta is correlated with the moduli through A / eta.
"""
from __future__ import annotations

import math

import pyro.distributions as dist
import torch


class StationaryMarginal:
    """The law of the observed entries of one stationary frame (masked rows dropped)."""

    def __init__(self, scene):
        if scene.observation is None:
            raise ValueError("the stationary marginal needs a scene with an observation operator")
        self.scene = scene
        self.observed = torch.as_tensor(scene.observation.mask.reshape(-1))
        H = scene.observation_matrix().to_dense()[self.observed]
        self.n_obs = H.shape[0]
        self.H = H.to_sparse()
        self.Ht = H.T.contiguous()

    def mean_and_covariance(self, params: dict):
        """(H A^-1 p + H_c u_c, S = H A^-1 H^T) from one factorisation of A."""
        scene = self.scene
        rhs = torch.cat([scene.free_load(params)[:, None], self.Ht.to(scene.force.dtype)], dim=1)
        X = scene.solve_free(params, rhs)
        u = scene.constraints.expand(X[:, 0])
        mean = scene.observe(u).reshape(-1)[self.observed]
        S = torch.sparse.mm(self.H, X[:, 1:])
        return mean, 0.5 * (S + S.T)

    def __call__(self, params: dict, eta, sigma) -> dist.MultivariateNormal:
        """N(H A^-1 p, eta S + sigma^2 I) as a Pyro distribution (event shape (n_obs,))."""
        mean, S = self.mean_and_covariance(params)
        cov = eta * S + sigma**2 * torch.eye(self.n_obs, dtype=S.dtype)
        return dist.MultivariateNormal(mean, scale_tril=torch.linalg.cholesky(cov))

    def log_likelihood(self, y: torch.Tensor, params: dict, eta, sigma) -> torch.Tensor:
        """Sum over frames of log N(y_f; H A^-1 p, eta S + sigma^2 I), y of shape (F, n_obs)."""
        return self(params, eta, sigma).log_prob(y).sum()


def squared_exponential_kl(x: torch.Tensor, length, rank: int):
    """Leading ``rank`` eigenpairs (lam, Phi) of R_ij = exp(-|x_i - x_j|^2 / (2 length^2)),
    dense and differentiable in ``length`` (a small particle set; the same kernel as
    ``bayespd.solvers.karhunen_loeve`` without its sparse cut-off)."""
    d2 = ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    lam, phi = torch.linalg.eigh(torch.exp(-d2 / (2 * length**2)))
    return lam.flip(0)[:rank], phi.flip(1)[:, :rank].contiguous()


class NoiseCovariance:
    """C = diag(d) + G G^T on the state's dofs, as torch tensors (differentiable)."""

    def __init__(self, diagonal: torch.Tensor, factor: torch.Tensor | None = None):
        self.d, self.G = diagonal, factor

    @staticmethod
    def white(sigma_c, n: int) -> "NoiseCovariance":
        """C = sigma_c^2 I."""
        return NoiseCovariance(sigma_c**2 * torch.ones(n))

    @staticmethod
    def karhunen_loeve(x, sigma_c, length, rank: int, nugget: float, dofs, dim: int) -> "NoiseCovariance":
        """C = sigma_c^2 (Phi Lambda Phi^T + nugget I) (x) I_dim restricted to ``dofs`` (node-major),
        the structure of ``bayespd.solvers.karhunen_loeve``."""
        lam, phi = squared_exponential_kl(torch.as_tensor(x), length, rank)
        G = torch.kron(sigma_c * phi * lam.clamp(min=0).sqrt(), torch.eye(dim))[torch.as_tensor(dofs)]
        return NoiseCovariance(sigma_c**2 * nugget * torch.ones(G.shape[0]), G)

    def matmul(self, v: torch.Tensor) -> torch.Tensor:
        """C v for v of shape (..., n) (rows are vectors)."""
        out = self.d * v
        return out if self.G is None else out + (v @ self.G) @ self.G.T

    def gaussian(self, loc: torch.Tensor, scale: float) -> dist.Distribution:
        """N(loc, scale^2 C) per row of loc, exact (Woodbury / determinant lemma when low rank)."""
        if self.G is None:
            return dist.Normal(loc, scale * self.d.sqrt()).to_event(1)
        return dist.LowRankMultivariateNormal(loc, scale * self.G, scale**2 * self.d)


def euler_maruyama_transition(scene, params: dict, eta, C: NoiseCovariance, dt: float,
                              previous: torch.Tensor) -> dist.Distribution:
    """U_{n+1} | U_n ~ N(U_n + (dt / eta) C (p - A U_n), 2 dt C) for each row U_n of
    ``previous`` (T, n_free): the Euler-Maruyama step of Dodwell 2019 eq 4."""
    A = scene.stiffness_values(params)
    AU = scene.constraints.pattern.matvec(A, previous.T).T
    drift = C.matmul(scene.free_load(params) - AU)
    return C.gaussian(previous + (dt / eta) * drift, math.sqrt(2 * dt))


def transition_log_likelihood(U: torch.Tensor, scene, params: dict, eta, C: NoiseCovariance,
                              dt: float) -> torch.Tensor:
    """log p(U_1..U_T | U_0) of a path U (T + 1, n_free) under the Euler-Maruyama chain."""
    return euler_maruyama_transition(scene, params, eta, C, dt, U[:-1]).log_prob(U[1:]).sum()
