"""bayespd/solvers/noise.py: covariances C = diag(d) + G G^T of the Langevin forcing: the
square root, its adjoint and C v exactly, draws' covariance within chi-square bounds, the
implicit solve (I + b C A)^-1, the Karhunen-Loeve kernel, refused input."""
import numpy as np
import pytest
import scipy.sparse as sp
import torch

import bayespd as bp
from bayespd.solvers.noise import Covariance, karhunen_loeve, white_noise

SIGMA = 0.7


def covariances():
    rng = np.random.default_rng(0)
    n = 12
    return {"white": white_noise(torch.linspace(0.5, 1.0, n), n),
            "diag+low rank": Covariance(rng.uniform(0.5, 2.0, n), rng.standard_normal((n, 3))),
            "low rank": Covariance(np.zeros(n), rng.standard_normal((n, 4)))}


@pytest.mark.parametrize("name", ["white", "diag+low rank", "low rank"])
def test_square_root_adjoint_and_matvec_are_exact(name):
    """S = C^{1/2} applied to the identity of n_xi columns has S S^T = C; <S xi, v> =
    <xi, S^T v> for the adjoint; C v = dense C v; all to rounding (1e-12)."""
    C = covariances()[name]
    S = C.sample(torch.eye(C.n_xi)).numpy()
    np.testing.assert_allclose(S @ S.T, C.dense(), rtol=0, atol=1e-12)
    rng = np.random.default_rng(1)
    xi, v = torch.as_tensor(rng.standard_normal((C.n_xi, 2))), torch.as_tensor(rng.standard_normal((C.n, 2)))
    lhs = (C.sample(xi) * v).sum(0)
    rhs = (xi * C.adjoint(v)).sum(0)
    torch.testing.assert_close(lhs, rhs, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(C.matvec(v).numpy(), C.dense() @ v.numpy(), rtol=1e-12, atol=1e-12)
    assert C.n_xi == {"white": 12, "diag+low rank": 15, "low rank": 4}[name]


def test_white_noise_draws_have_the_stated_variances():
    """sigma per dof, M = 4000 draws: each dof's sample variance over sigma^2 is
    chi^2_{M-1} / (M - 1), sd sqrt(2 / (M - 1)) = 0.022: all 12 within 4.5 sd (a false alarm
    has probability 12 x 7e-6); the sample correlation of every pair of dofs within
    4.5 / sqrt(M) (66 pairs: 66 x 7e-6 = 4.5e-4); a 20 % error in one sigma^2 would be
    9 sd away (power ~1)."""
    sigma = np.linspace(0.5, 1.0, 12)
    C = white_noise(torch.as_tensor(sigma), 12)
    np.testing.assert_array_equal(C.dense(), np.diag(sigma**2))
    M = 4000
    X = C.sample(torch.randn(C.n_xi, M, generator=torch.Generator().manual_seed(2), dtype=torch.float64)).numpy()
    var = X.var(axis=1, ddof=1) / sigma**2
    assert np.all(np.abs(var - 1) < 4.5 * np.sqrt(2 / (M - 1)))
    corr = np.corrcoef(X)[np.triu_indices(12, 1)]
    assert np.abs(corr).max() < 4.5 / np.sqrt(M)
    np.testing.assert_array_equal(white_noise(SIGMA, 3).dense(), SIGMA**2 * np.eye(3))


@pytest.mark.parametrize("name", ["white", "diag+low rank", "low rank"])
def test_implicit_solver_solves_i_plus_b_c_a(name):
    """x = (I + b C A)^-1 r (sparse Cholesky for the diagonal, Woodbury for G) on a random
    sparse SPD A: the residual of the dense system is at rounding (1e-10 relative)."""
    C = covariances()[name]
    rng = np.random.default_rng(3)
    B = sp.random(C.n, C.n, density=0.3, random_state=4)
    A = (B @ B.T + sp.identity(C.n)).tocsc()
    r = rng.standard_normal((C.n, 3))
    x = C.implicit_solver(A, 0.7)(torch.as_tensor(r)).numpy()
    np.testing.assert_allclose((np.eye(C.n) + 0.7 * C.dense() @ A.toarray()) @ x, r, rtol=0, atol=1e-10)


def test_restricted_dofs_are_the_submatrix():
    """``dofs`` restricts C to those node-major dofs: the dense result is C[dofs][:, dofs]."""
    p = bp.grid_2d(5.0, 4.0, 1.0)
    full = karhunen_loeve(p.x, SIGMA, 1.5, rank=6, nugget=0.1)
    dofs = np.arange(3, 2 * p.n, 2)
    part = karhunen_loeve(p.x, SIGMA, 1.5, rank=6, nugget=0.1, dofs=dofs)
    np.testing.assert_allclose(part.dense(), full.dense()[np.ix_(dofs, dofs)], rtol=0, atol=1e-12)


def test_bad_covariances_name_the_fix():
    with pytest.raises(ValueError, match="all positive or all zero"):
        Covariance([1.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="must have 3 rows"):
        Covariance([1.0, 1.0, 1.0], np.ones((2, 1)))
    with pytest.raises(ValueError, match="C = 0"):
        Covariance(np.zeros(3))
    with pytest.raises(ValueError, match="sigma must be finite and positive"):
        white_noise(0.0, 3)
    x = bp.grid_2d(4.0, 4.0, 1.0).x
    with pytest.raises(ValueError, match="length > 0"):
        karhunen_loeve(x, SIGMA, 0.0)
    with pytest.raises(ValueError, match=r"rank must lie in \[1, 15\]"):
        karhunen_loeve(x, SIGMA, 1.0, rank=16)


def test_karhunen_loeve_reproduces_the_kernel():
    """Squared-exponential kernel R (length 2.5 h) on 20 x 20 particles, keeping 95% of its
    trace. Against the dense kernel: the eigenpairs are those of the cut-off kernel R_c
    (|R - R_c| <= exp(-8) entrywise); the truncation error has Frobenius norm
    sqrt(sum_{k>r} lambda_k^2) and 2-norm lambda_{r+1} (up to |R - R_c|_2); samples
    C^{1/2} xi have covariance sigma^2 (R_r + nugget I) (quadratic forms within 4.5 SE)."""
    p = bp.grid_2d(20, 20, 1.0)
    ell, nugget = 2.5, 0.1
    C = karhunen_loeve(p.x, SIGMA, ell, fraction=0.95, nugget=nugget)
    r = len(C.eigenvalues)
    assert C.fraction >= 0.95 and C.fraction == pytest.approx(C.eigenvalues.sum() / p.n)
    d2 = ((p.x[:, None, :] - p.x[None, :, :]) ** 2).sum(-1)
    R = np.exp(-d2 / (2 * ell**2))
    Rc = np.where(d2 <= (4 * ell) ** 2, R, 0.0)
    assert np.abs(R - Rc).max() <= np.exp(-8)
    lam_c = np.linalg.eigvalsh(Rc)[::-1]
    np.testing.assert_allclose(C.eigenvalues, lam_c[:r], rtol=1e-8)
    Rr = C.modes @ np.diag(C.eigenvalues) @ C.modes.T
    assert np.linalg.norm(Rc - Rr) == pytest.approx(np.sqrt((lam_c[r:] ** 2).sum()), rel=1e-6)
    gap = np.linalg.norm(R - Rc, 2)
    assert abs(np.linalg.norm(R - Rr, 2) - lam_c[r]) <= gap + 1e-9
    assert 1 - C.fraction == pytest.approx(np.trace(R - Rr) / p.n)  # the stated trace error
    # C is sigma^2 (R_r + nugget I) per component, block diagonal over the dim components
    Cd = C.dense()
    np.testing.assert_allclose(Cd[0::2, 0::2], SIGMA**2 * (Rr + nugget * np.eye(p.n)), atol=1e-12)
    assert np.abs(Cd[0::2, 1::2]).max() == 0
    M = 20000
    X = C.sample(torch.randn(C.n_xi, M, generator=torch.Generator().manual_seed(5))).numpy()
    V = np.random.default_rng(1).standard_normal((C.n, 5))
    var = ((V.T @ X) ** 2).mean(1)
    expected = np.einsum("ik,ij,jk->k", V, Cd, V)
    assert np.all(np.abs(var / expected - 1) < 4.5 * np.sqrt(2 / M))
