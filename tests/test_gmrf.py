"""bayespd/gmrf.py: the GMRF precision Q(ell, s) = tau (I + ell^2 A) over the particle graph:
exact density, Q Sigma = I, the Tikhonov square root, exact draws, refused graphs."""
import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.gmrf import GMRF


def test_gmrf_density_is_exact_and_its_laplacian_consistent():
    p = bp.grid_2d(12.0, 12.0, 1.0)
    g = GMRF(p, bp.find_bonds(p, 3.0))
    x, y = p.x[:, 0] - 6, p.x[:, 1] - 6
    inner = (np.abs(x) < 1.6) & (np.abs(y) < 1.6)  # a full family (3.5 h) inside the body
    # A ~ -Laplacian: exact for quadratics in the interior of a lattice family
    np.testing.assert_allclose((g.laplacian @ (x**2 + y**2))[inner], -4.0, atol=1e-12)
    np.testing.assert_allclose(g.laplacian @ np.ones(p.n), 0.0, atol=1e-12)
    ell, s = torch.tensor(2.0), torch.tensor(0.3)
    Q = g.precision(ell, s).to_dense()
    cov = torch.linalg.inv(Q)
    torch.testing.assert_close(torch.diagonal(cov).mean(), s**2, rtol=1e-12, atol=0)
    z = torch.randn(4, p.n, generator=torch.Generator().manual_seed(0))
    exact = torch.distributions.MultivariateNormal(torch.full((p.n,), 0.5), precision_matrix=Q)
    torch.testing.assert_close(g.log_prob(z, 0.5, ell, s), exact.log_prob(z), rtol=1e-12, atol=1e-9)
    # colour(w) has covariance Q^-1 exactly: C C^T = Q^-1 with C = colour(I)
    C = g.colour(torch.eye(p.n), ell, s)
    torch.testing.assert_close(C @ C.T, cov, rtol=0, atol=1e-12)
    L = g.square_root(1.7)
    np.testing.assert_allclose((L.T @ L).toarray(), np.eye(p.n) + 1.7**2 * g.laplacian.toarray(), atol=1e-12)
    # the log-determinant is differentiable in both hyper-parameters: check against autograd of logdet
    ell.requires_grad_(), s.requires_grad_()
    dl = torch.autograd.grad(g.log_det(ell, s), (ell, s))
    de = torch.autograd.grad(torch.logdet(g.precision(ell, s).to_dense()), (ell, s))
    torch.testing.assert_close(dl, de, rtol=1e-10, atol=0)


@pytest.fixture(scope="module")
def small():
    p = bp.grid_2d(6.0, 5.0, 1.0)
    return p, GMRF(p, bp.find_bonds(p, 2.0))


def test_precision_times_covariance_is_the_identity(small):
    """Q (from the sparse precision) times Sigma = V diag(1 / (tau (1 + ell^2 lambda))) V^T
    (from the eigenvectors, as ``colour`` uses them) is I to rounding, 1e-12; A is symmetric
    PSD with exactly one zero eigenvalue on a connected graph (the constants)."""
    p, g = small
    ell, s = 1.7, 0.4
    Q = g.precision(ell, s).to_dense()
    C = g.colour(torch.eye(p.n), ell, s)
    torch.testing.assert_close(Q @ (C @ C.T), torch.eye(p.n), rtol=0, atol=1e-12)
    A = g.laplacian.toarray()
    np.testing.assert_array_equal(A, A.T)
    lam = g.eigenvalues.numpy()
    assert lam.min() >= 0 and np.sum(lam < 1e-10 * lam.max()) == 1


def test_tau_sets_the_mean_marginal_variance_and_log_det_is_exact(small):
    """(1/N) tr Q^-1 = s^2 for any ell (tau scales Q to it); log det Q = log det of the dense
    Q (1e-10); ell -> 0 gives Q = I / s^2, white noise of variance s^2."""
    p, g = small
    for ell in (0.0, 0.5, 3.0):
        Q = g.precision(ell, 0.25).to_dense()
        assert float(torch.linalg.inv(Q).diagonal().mean()) == pytest.approx(0.0625, rel=1e-12)
        assert float(g.log_det(ell, 0.25)) == pytest.approx(float(torch.logdet(Q)), rel=1e-10)
    torch.testing.assert_close(g.precision(0.0, 0.25).to_dense(), torch.eye(p.n) / 0.0625, rtol=1e-14, atol=0)


def test_square_root_gives_the_tikhonov_penalty(small):
    """With psi = tau(ell, s) and L = square_root(ell): -log N(z; m, Q^-1) + log N(m; m, Q^-1)
    = psi / 2 ||L (z - m)||^2, the Tikhonov term (1e-12 relative), batched over leading dims."""
    p, g = small
    ell, s = 1.3, 0.2
    z = torch.randn(2, 3, p.n, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    m = 0.3
    lp = g.log_prob(z, m, ell, s)
    assert lp.shape == (2, 3)
    L = g.square_root(ell)
    d = (z - m).reshape(-1, p.n).numpy()
    penalty = 0.5 * float(g.tau(ell, s)) * np.sum((L @ d.T) ** 2, axis=0).reshape(2, 3)
    top = g.log_prob(torch.full((p.n,), m), m, ell, s)
    np.testing.assert_allclose((top - lp).numpy(), penalty, rtol=1e-12)


def test_draws_have_the_precision_s_covariance(small):
    """M = 4000 exact draws: the sample mean of (1/N) |x - mean|^2 is s^2 within 4.5 standard
    errors, SE = sqrt(2 tr Sigma^2 / M) / N (a sum of Gaussian quadratic forms; the test
    fails by chance with probability 7e-6); the mean of the draws is within 4.5
    sqrt(mean(diag Sigma) / (M N)) (CLT, averaged over particles) of the given mean."""
    p, g = small
    ell, s, M = 1.5, 0.3, 4000
    x = g.sample(2.0, ell, s, shape=(M,), generator=torch.Generator().manual_seed(3))
    assert x.shape == (M, p.n)
    Sigma = torch.linalg.inv(g.precision(ell, s).to_dense())
    se = float(torch.sqrt(2 * (Sigma**2).sum() / M)) / p.n
    var = float(((x - 2.0) ** 2).mean())
    assert abs(var - s**2) < 4.5 * se
    se_mean = float(torch.sqrt(Sigma.sum() / p.n**2 / M))  # sd of the grand mean of the draws
    assert abs(float(x.mean()) - 2.0) < 4.5 * se_mean


def test_radius_selects_the_nearest_neighbour_graph():
    """radius = h on a grid: the 4-neighbour lattice, nx (ny - 1) + ny (nx - 1) pairs, n_max = 4
    so c = 2 dim / n_max = 1, and A is the 5-point graph Laplacian (4 on interior diagonals)."""
    p = bp.grid_2d(6.0, 5.0, 1.0)
    g = GMRF(p, bp.find_bonds(p, 2.0), radius=1.0)
    assert g.pairs == 6 * 4 + 5 * 5 and g.c == 1.0
    interior = np.all((p.x > 1) & (p.x < p.upper() - 1), axis=1)
    np.testing.assert_array_equal(g.laplacian.diagonal()[interior], 4.0)


def test_bad_graphs_are_refused():
    p = bp.grid_2d(4.0, 4.0, 1.0)
    with pytest.raises(ValueError, match="no pairs.*larger radius"):
        GMRF(p, bp.find_bonds(p, 1.0), radius=0.5)
    lonely = bp.from_points(np.vstack([p.x, [[20.0, 20.0]]]), np.append(p.volume, 1.0))
    with pytest.raises(ValueError, match="1 particle.*no pair"):
        GMRF(lonely, bp.find_bonds(lonely, 1.5))
