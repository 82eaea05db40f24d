"""bayespd/inverse/regularization.py: the graph gradient L (exact on linear fields, constants
in its null space, one row per neighbour pair), the operators a spec names, and the penalty's
gradient against finite differences."""
import numpy as np
import pytest
import scipy.sparse as sp
import torch

import bayespd as bp
from bayespd.inverse.regularization import graph_gradient, regularization_operator


def test_graph_gradient_has_one_row_per_neighbour_pair():
    """radius 1.5 h on an nx x ny grid: the 8-neighbour pairs, nx (ny - 1) + ny (nx - 1) +
    2 (nx - 1)(ny - 1) rows, each with -h/|xi| at i and +h/|xi| at j (1 or 1/sqrt 2)."""
    p = bp.grid_2d(5.0, 4.0, 0.5)  # 10 x 8
    L = graph_gradient(p).to_dense().numpy()
    assert L.shape == (10 * 7 + 8 * 9 + 2 * 9 * 7, p.n)
    assert np.all((L != 0).sum(1) == 2)
    assert set(np.round(np.abs(L[L != 0]), 12)) == {1.0, round(1 / np.sqrt(2), 12)}
    np.testing.assert_allclose(L.sum(1), 0.0, atol=1e-15)
    assert graph_gradient(p, radius=0.5).shape[0] == 10 * 7 + 8 * 9


def test_graph_gradient_is_exact_on_linear_fields():
    """For z = a . x, (L z)_b = h a . xi / |xi|: the directional derivative times h, exact to
    rounding; constants give zero (the penalty leaves the mean free)."""
    p = bp.grid_2d(4.0, 3.0, 1.0)
    L = graph_gradient(p)
    a = np.array([0.7, -1.3])
    z = torch.as_tensor(p.x @ a)
    Lz = torch.sparse.mm(L, z[:, None]).squeeze(1).numpy()
    A = L.to_dense().numpy()
    i, j = np.argmin(A, axis=1), np.argmax(A, axis=1)
    xi = p.x[j] - p.x[i]
    np.testing.assert_allclose(Lz, p.h * xi @ a / np.linalg.norm(xi, axis=1), rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(torch.sparse.mm(L, torch.ones(p.n, 1)).numpy(), 0.0, atol=1e-15)


def test_penalty_gradient_matches_finite_differences():
    """P(z) = psi/2 ||L (z - z_ref)||^2 through the sparse L: autograd's gradient is
    psi L^T L (z - z_ref) (1e-12) and the Taylor remainder |P(z + e v) - P(z) - e g . v|
    falls with slope 2 in e (P is quadratic: the remainder is exactly e^2 psi/2 ||L v||^2)."""
    p = bp.grid_2d(5.0, 5.0, 1.0)
    L = graph_gradient(p)
    gen = torch.Generator().manual_seed(0)
    z = torch.randn(p.n, generator=gen, dtype=torch.float64).requires_grad_()
    z_ref, v, psi = torch.randn(p.n, generator=gen, dtype=torch.float64), torch.randn(p.n, generator=gen, dtype=torch.float64), 3.0

    def penalty(x):
        return 0.5 * psi * (torch.sparse.mm(L, (x - z_ref)[:, None]) ** 2).sum()

    (g,) = torch.autograd.grad(penalty(z), z)
    dense = L.to_dense()
    torch.testing.assert_close(g, psi * dense.T @ (dense @ (z.detach() - z_ref)), rtol=1e-12, atol=1e-12)
    with torch.no_grad():
        eps = np.array([1e-1, 5e-2, 2.5e-2])
        rem = np.array([float(abs(penalty(z + e * v) - penalty(z) - e * (g @ v))) for e in eps])
        slopes = np.diff(np.log(rem)) / np.diff(np.log(eps))
        np.testing.assert_allclose(slopes, 2.0, atol=1e-6)
        np.testing.assert_allclose(rem, eps**2 * 0.5 * psi * float((dense @ v).square().sum()), rtol=1e-9)


def test_specs_give_the_same_operator_in_any_matrix_type():
    """None and 'identity' mean L = I (None); 'gradient' the graph gradient; a scipy
    sparse, numpy or torch matrix becomes the same float64 torch tensor."""
    p = bp.grid_2d(3.0, 2.0, 1.0)
    assert regularization_operator(None, "G", p.n, p) is None
    assert regularization_operator("identity", "G", 1, p) is None
    torch.testing.assert_close(regularization_operator("gradient", "G", p.n, p).to_dense(),
                               graph_gradient(p).to_dense(), rtol=0, atol=0)
    M = np.arange(12.0).reshape(2, 6) - 5
    for spec in (M, sp.csr_matrix(M), torch.as_tensor(M, dtype=torch.float32)):
        L = regularization_operator(spec, "G", p.n, p)
        L = L.to_dense() if L.is_sparse else L
        assert L.dtype == torch.float64
        np.testing.assert_array_equal(L.numpy(), M)


def test_bad_specs_name_the_fix():
    p = bp.grid_2d(3.0, 2.0, 1.0)
    with pytest.raises(ValueError, match="unknown regularisation 'laplacian'.*'gradient'"):
        regularization_operator("laplacian", "G", p.n, p)
    with pytest.raises(ValueError, match="has 1 value.*use 'identity' for scalars"):
        regularization_operator("gradient", "K", 1, p)
    with pytest.raises(ValueError, match="must have 6 column"):
        regularization_operator(np.eye(5), "G", p.n, p)
    with pytest.raises(ValueError, match="radius >= h"):
        graph_gradient(p, radius=0.5)
