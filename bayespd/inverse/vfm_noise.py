"""The PD-VFM under measurement noise: the noise-optimal combination of a set of virtual
fields, the errors-in-variables correction, and the estimate's standard error.

Noise model: iid noise of sd ``sigma`` on every measured displacement, y = u + e. The VFM
residuals (Delorme 2018 eq 25's terms) are linear in the data and in a = (a_s, a_d),

    r_k(a) = -(K(a) u*_k)^T y - W*_ext,k = (A a - b)_k,   A_kp = -(K_p u*_k)^T y,  b = -W*_ext,

so at the true a they have zero mean and covariance sigma^2 C(a), C_kl = (K(a) u*_k)^T
(K(a) u*_l) over the measured dofs. Among all linear combinations of the fields (virtual
fields Sum_k c_k u*_k), the estimating equations of least variance are the generalised least
squares ones, A^T C^-1 (A a - b) = 0 (Gauss-Markov): this is Avril, Grédiac & Pierron 2004's
noise-optimal special fields, searched within the span of the given fields, on the PD
internal virtual work. The noise also enters A (errors in variables), so A^T W A is biased
by sigma^2 T, T_pq = sum_kl W_kl (K_p u*_k)^T (K_q u*_l); the plain closed form then shrinks
the weakly excited column (K in bending: -89 % at 1 % noise). We subtract T ("corrected least
squares", consistent for a fixed W) and iterate W = C(a)^-1 from the plain estimate. The
covariance of a is Cov(a) = sigma^2 (A^T W A - sigma^2 T)^-1; the standard errors of K and G are
the sd of a parametric bootstrap through ``vfm.moduli_of_constants`` (``bootstrap_se``: the map
is a ratio, far from linear at 1 % noise), the linearised ones (Jacobian) kept as ``se_linear``;
chi2 = r^T W r / sigma^2 has mean M - 2 when the model
error is below the noise.
"""
from __future__ import annotations

import time
import warnings

import numpy as np

from bayespd.inverse.vfm import (VFMResult, VirtualWork, least_squares_constants, moduli_from_constants,
                                moduli_of_constants, system)
from bayespd.validate import positive

BOOTSTRAP = 4000  # draws of the se's bootstrap: its own relative error ~ 1 / sqrt(2 x 4000) = 1.1 % (Gaussian)
MAX_SE = 0.005  # warn when a relative standard error exceeds this (the 0.5 % at one sd)


class NoisyEstimateWarning(UserWarning):
    """The noise sd makes the VFM estimate's standard error larger than the stated fraction."""


def _inverse(C: np.ndarray, rcond: float = 1e-12) -> np.ndarray:
    """Pseudo-inverse of the symmetric PSD C (eigenvalues below rcond x the largest dropped)."""
    lam, V = np.linalg.eigh(C)
    keep = lam > rcond * lam.max()
    return (V[:, keep] / lam[keep]) @ V[:, keep].T


def moduli_jacobian(material, a) -> np.ndarray:
    """d(K, G)/d(a_s, a_d) by central differences (step 1e-6 |a_p|; the map is smooth and
    rational, so the relative error is ~1e-10)."""
    a = np.asarray(a, dtype=float)
    J = np.zeros((2, 2))
    for p in range(2):
        step = np.zeros(2)
        step[p] = 1e-6 * abs(a[p])
        J[:, p] = (np.array(moduli_from_constants(material, *(a + step)))
                   - np.array(moduli_from_constants(material, *(a - step)))) / (2 * step[p])
    return J


class NoiseModel:
    """Grams G_pq = R_p R_q^T (M, M) of the virtual force fields R_p = K_p u*_k restricted to
    the measured dofs (p, q in {s, d}), from which C(a) and T(W) of the module docstring."""

    def __init__(self, work: VirtualWork, measured: np.ndarray):
        m = work.n_fields
        R = [(P.numpy() * measured[None]).reshape(m, -1) for P in (work.Ps, work.Pd)]
        self.gram = [[R[p] @ R[q].T for q in range(2)] for p in range(2)]

    def covariance(self, a) -> np.ndarray:
        """C(a): Cov(r) / sigma^2."""
        return sum(a[p] * a[q] * self.gram[p][q] for p in range(2) for q in range(2))

    def bias(self, W: np.ndarray) -> np.ndarray:
        """T(W): E[A^T W A] - A0^T W A0 = sigma^2 T."""
        return np.array([[np.sum(W * self.gram[p][q]) for q in range(2)] for p in range(2)])


def bootstrap_se(material, a, cov_a, moduli, draws: int = BOOTSTRAP, seed: int = 0) -> tuple:
    """({"K", "G"} relative standard errors, fraction of draws with no positive moduli): the sd
    of (K, G) over ``draws`` parametric-bootstrap draws a* ~ N(a, cov_a) of the closed form's
    constants mapped by ``vfm.moduli_of_constants``, divided by ``moduli``. The map a -> K is a
    ratio (plane stress: K = 4 G kappa / (9 G - 3 kappa)), far from linear once se K is ~10 %:
    there the linearised (delta-method) se is ~15-20 % below the sd of K over noise draws, the
    bootstrap's within ~5 % (docs/results.md, VFM). Draws that map to no positive (K, G) are left
    out and counted."""
    z = np.random.default_rng(seed).standard_normal((draws, 2))
    A = np.asarray(a)[None] + z @ np.linalg.cholesky(cov_a).T
    KG = np.stack(moduli_of_constants(material, A[:, 0], A[:, 1]), 1)
    ok = np.isfinite(KG).all(1)
    sd = KG[ok].std(0) if ok.sum() > 1 else np.full(2, np.inf)
    return {"K": float(sd[0] / moduli[0]), "G": float(sd[1] / moduli[1])}, float(1 - ok.mean())


def warn_if_noisy(se: dict, sigma: float, max_se: float, spread: dict | None = None):
    """:class:`NoisyEstimateWarning` when a relative standard error in ``se`` (or a model
    spread of ``vfm_defaults.model_spread``) exceeds ``max_se``."""
    spread = spread or {"K": 0.0, "G": 0.0}
    if max(se.values()) > max_se or max(spread.values()) > max_se:
        warnings.warn(f"the VFM estimate's relative standard error (K {se['K']:.2%}, G {se['G']:.2%}) or "
                      f"the spread over the horizons the noise cannot tell apart (K {spread['K']:.2%}, "
                      f"G {spread['G']:.2%}) exceeds {max_se:.2%} at noise sd {sigma:.3g}: trust it only to "
                      "about 3 se plus the spread. Reduce them with a finer grid or less noisy data "
                      "(se ~ sigma / sqrt(particles))", NoisyEstimateWarning, stacklevel=3)


def weighted_identify(work: VirtualWork, u, sigma: float, *, observed=None, iterations: int = 4,
                      max_se: float | None = MAX_SE) -> VFMResult:
    """K, G by noise-weighted, bias-corrected least squares over ``work``'s fields (module
    docstring), with ``extra['se']`` (relative standard errors of K and G), ``extra['chi2']``
    and ``extra['dof']``; warns (:class:`NoisyEstimateWarning`) when a relative se exceeds
    ``max_se`` (None: never). ``sigma`` is the noise sd of each measured displacement."""
    start = time.perf_counter()
    positive("sigma", sigma, "pass the noise sd of the measured displacements, or use vfm.identify "
             "for noise-free data")
    A, b = system(work, u, observed, sigma)
    measured = work.measured(u, observed)[1]
    a = least_squares_constants(A, b)
    noise = NoiseModel(work, measured)
    for _ in range(iterations):
        W = _inverse(noise.covariance(a))
        N = A.T @ W @ A - sigma**2 * noise.bias(W)
        if N[0, 0] <= 0 or np.linalg.det(N) <= 0:  # 2 x 2: positive definite iff these hold
            raise ValueError(
                f"the noise (sigma = {sigma:.3g}) swamps what the {work.n_fields} virtual fields "
                "see of the moduli: the bias-corrected normal matrix is not positive definite. Use "
                "fields that strain more of the body (larger bumps, fewer horizons of clearance) "
                "or less noisy data")
        a = np.linalg.solve(N, A.T @ W @ b)
    try:
        K, G = moduli_from_constants(work.material, *a)
    except ValueError as err:
        raise ValueError(f"{err}; at sigma = {sigma:.3g} the noise dominates these fields") from None
    J = moduli_jacobian(work.material, a)
    cov_a = sigma**2 * np.linalg.inv(N)
    cov = J @ cov_a @ J.T
    se, unphysical = bootstrap_se(work.material, a, cov_a, (K, G))
    r = A @ a - b
    chi2 = float(r @ W @ r / sigma**2)
    if max_se is not None:
        warn_if_noisy(se, sigma, max_se)
    return VFMResult({"K": K, "G": G}, (float(a[0]), float(a[1])), work.phi(r), r.tolist(), 0,
                     time.perf_counter() - start, "weighted_closed_form",
                     {"se": se, "se_linear": {"K": float(np.sqrt(cov[0, 0]) / K), "G": float(np.sqrt(cov[1, 1]) / G)},
                      "unphysical_fraction": unphysical, "cov_KG": cov.tolist(), "chi2": chi2, "dof": work.n_fields - 2, "sigma": float(sigma)})
