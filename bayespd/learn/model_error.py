"""A correlated, relative model-error term for PD predictions of coarse-grained MD fields.

The misfit of a PD forward run is structured model error, not nodal noise: it grows with the
displacement (about 5 % of it at the first frame, 20-25 % later, docs/results.md) and moves as
smooth fields in space and time. The term models it as

    e[t, i, c] = u_md - u_pd = r s_t G[t, i, c],   G ~ N(0, C_time (x) C_space) per component c,

with s_t the rms of the PD prediction at frame t (the error relative to the field's size, as the
paper's metric measures it), r the relative level, and separable exponential correlations
C_time = exp(-|t - t'| / tau), C_space = exp(-|x_i - x_j| / ell). Under p(r) ~ 1/r, r integrates out:

    log p(e | ell, tau) = -N/2 log Q - n_c n sum_t log s_t - (n_c / 2)(n logdet C_time + T logdet C_space) + const,
    Q = sum_c || L_time^-1 (E_c / s) L_space^-T ||^2,   r^2 | e ~ Q / chi^2_N,

N = T n n_c values, L the Cholesky factors. (ell, tau) are chosen by this evidence on a grid.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg


def exponential_correlation(points, length: float) -> np.ndarray:
    """exp(-|p_i - p_j| / length) for points (n, d) or times (n,)."""
    p = np.asarray(points, float)
    p = p[:, None] if p.ndim == 1 else p
    if not length > 0:
        raise ValueError(f"the correlation length must be positive, got {length}")
    return np.exp(-np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1) / length)


@dataclass
class RelativeFieldError:
    """The module docstring's term at fixed (ell, tau) for nodes ``points`` (n, d) and frame
    ``times`` (T,)."""
    points: np.ndarray
    times: np.ndarray
    ell: float
    tau: float

    def __post_init__(self):
        self.L_space = np.linalg.cholesky(exponential_correlation(self.points, self.ell))
        self.L_time = np.linalg.cholesky(exponential_correlation(self.times, self.tau))
        self.logdet = 2 * (len(self.times) * np.log(np.diag(self.L_space)).sum()
                           + len(self.points) * np.log(np.diag(self.L_time)).sum())

    def quadratic(self, residual, scale) -> float:
        """Q for residuals (T, n, n_c) and frame scales s (T,)."""
        E = np.asarray(residual, float) / _positive_scale(scale)[:, None, None]
        q = 0.0
        for c in range(E.shape[2]):
            Z = scipy.linalg.solve_triangular(self.L_time, E[:, :, c], lower=True)
            q += (scipy.linalg.solve_triangular(self.L_space, Z.T, lower=True) ** 2).sum()
        return float(q)

    def log_evidence(self, residual, scale) -> float:
        """log p(e | ell, tau) with r marginalised (module docstring), up to a constant in (ell, tau, e)."""
        residual = np.asarray(residual, float)
        T, n, nc = residual.shape
        return (-0.5 * T * n * nc * np.log(self.quadratic(residual, scale))
                - n * nc * np.log(_positive_scale(scale)).sum() - 0.5 * nc * self.logdet)

    def draw(self, rng, scale, r: float, components: int) -> np.ndarray:
        """One draw of e (T, n, components) with relative level ``r``: spatially correlated per
        frame, frames independent (the marginal sd r s_t per value is the band's)."""
        z = rng.standard_normal((len(scale), len(self.points), components))
        return r * np.asarray(scale)[:, None, None] * np.einsum("ij,tjc->tic", self.L_space, z)


def fit_relative_error(residual, scale, points, times, lengths, durations) -> tuple[RelativeFieldError, np.ndarray]:
    """The (ell, tau) of the grids ``lengths`` x ``durations`` with the largest evidence for
    ``residual`` (T, n, n_c); returns the term and the table of log evidences."""
    table = np.array([[RelativeFieldError(points, times, ell, tau).log_evidence(residual, scale) for tau in durations]
                      for ell in lengths])
    a, b = np.unravel_index(np.argmax(table), table.shape)
    return RelativeFieldError(points, times, float(lengths[a]), float(durations[b])), table


def _positive_scale(scale) -> np.ndarray:
    s = np.asarray(scale, float)
    if np.any(~(s > 0)):
        raise ValueError("every frame scale s_t must be positive: leave out frames where the prediction is zero")
    return s
