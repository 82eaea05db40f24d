"""bayespd/linalg/adjoint.py: the differentiable SPD solve against dense linear algebra, and its
gradient in the matrix values, grad_values[k] = -lambda[rows[k]] u[cols[k]] (K lambda = grad_u)."""
import numpy as np
import pytest
import torch

from bayespd.linalg.adjoint import solve
from bayespd.linalg.sparse import NotPositiveDefiniteError
from tests.linalg.linalg_systems import csc_pattern, grid_spd


def test_solve_matches_dense_and_refuses_an_indefinite_matrix():
    spd = grid_spd()
    pattern, values = csc_pattern(spd)
    rhs = torch.as_tensor(np.random.default_rng(1).standard_normal(spd.shape[0]))
    exact = np.linalg.solve(spd.toarray(), rhs.numpy())
    u = solve(pattern, values, rhs).numpy()
    assert np.abs(u - exact).max() <= 1e-12 * np.abs(exact).max()
    diagonal = torch.zeros(pattern.nnz)
    diagonal[pattern.position(np.arange(pattern.n), np.arange(pattern.n))] = 1.0
    with pytest.raises(NotPositiveDefiniteError):
        solve(pattern, values - 3.0 * diagonal, rhs)


def test_gradient_in_the_values_is_minus_lambda_u():
    """For J = w . u, dJ/dvalues[k] = -lambda[rows[k]] u[cols[k]] with K lambda = w, and
    dJ/drhs = lambda: against dense solves, to 1e-12 relative."""
    spd = grid_spd()
    pattern, values = csc_pattern(spd)
    rng = np.random.default_rng(2)
    rhs = torch.as_tensor(rng.standard_normal(spd.shape[0]), dtype=torch.float64).requires_grad_()
    w = torch.as_tensor(rng.standard_normal(spd.shape[0]))
    values = values.clone().requires_grad_()
    (w * solve(pattern, values, rhs)).sum().backward()
    dense = spd.toarray()
    u, lam = np.linalg.solve(dense, rhs.detach().numpy()), np.linalg.solve(dense, w.numpy())
    expected = -lam[pattern.rows] * u[pattern.cols]
    assert np.abs(values.grad.numpy() - expected).max() <= 1e-12 * np.abs(expected).max()
    assert np.abs(rhs.grad.numpy() - lam).max() <= 1e-12 * np.abs(lam).max()
