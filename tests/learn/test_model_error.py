"""The correlated relative model-error term (bayespd.learn.model_error)."""
import numpy as np
import pytest
import scipy.integrate

from bayespd.learn.model_error import RelativeFieldError, exponential_correlation, fit_relative_error

RNG = np.random.default_rng(3)
X = RNG.uniform(0, 60, size=(50, 2))
T = np.arange(16) * 0.05
S = np.linspace(0.5, 2.0, len(T))


def synthetic(ell, tau, r, seed):
    """e = r s_t G with G ~ N(0, C_time (x) C_space) per component."""
    rng = np.random.default_rng(seed)
    Ls = np.linalg.cholesky(exponential_correlation(X, ell))
    Lt = np.linalg.cholesky(exponential_correlation(T, tau))
    z = rng.standard_normal((len(T), len(X), 2))
    return r * S[:, None, None] * np.einsum("ts,sic->tic", Lt, np.einsum("ij,sjc->sic", Ls, z))


def test_quadratic_form_is_the_dense_kronecker_one():
    term = RelativeFieldError(X, T, 10.0, 0.2)
    E = RNG.normal(size=(len(T), len(X), 2))
    D = np.diag(np.repeat(S, len(X)))
    C = D @ np.kron(exponential_correlation(T, 0.2), exponential_correlation(X, 10.0)) @ D
    dense = sum(E[:, :, c].reshape(-1) @ np.linalg.solve(C, E[:, :, c].reshape(-1)) for c in range(2))
    assert term.quadratic(E, S) == pytest.approx(dense, rel=1e-11)


def test_log_evidence_is_the_gaussian_likelihood_integrated_over_r():
    """Differences of log p(e | ell, tau) between two (ell, tau) equal those of
    int N(e; 0, r^2 S C S) dr / r computed by quadrature (few values, so the integral is smooth)."""
    x, t, s = X[:4], T[:3], S[:3]
    E = np.random.default_rng(0).normal(size=(3, 4, 2))

    def by_quadrature(ell, tau):
        D = np.diag(np.repeat(s, 4))
        C = D @ np.kron(exponential_correlation(t, tau), exponential_correlation(x, ell)) @ D
        logdet = np.linalg.slogdet(C)[1]
        q = sum(E[:, :, c].reshape(-1) @ np.linalg.solve(C, E[:, :, c].reshape(-1)) for c in range(2))
        N = E.size
        f = lambda lr: np.exp(-N * lr - q / (2 * np.exp(2 * lr)) - logdet + 10.0)  # r = e^lr, dr / r = d lr
        return np.log(scipy.integrate.quad(f, -10, 10, limit=200)[0])

    a, b = (RelativeFieldError(x, t, *p).log_evidence(E, s) for p in ((5.0, 0.1), (20.0, 0.4)))
    assert a - b == pytest.approx(by_quadrature(5.0, 0.1) - by_quadrature(20.0, 0.4), abs=1e-8)


def test_fit_recovers_the_correlation_lengths_and_the_level():
    """1,600 correlated values from (ell, tau, r) = (10 A, 0.2 ps, 0.2): the evidence picks the true
    grid point among lengths a factor 2 apart, and r = sqrt(Q / N) is within 8 % (whitened values:
    sd of Q / N is sqrt(2 / N) = 3.5 %, so 8 % is 2.3 sd of r^2 / 2)."""
    e = synthetic(10.0, 0.2, 0.2, seed=7)
    term, table = fit_relative_error(e, S, X, T, [2.5, 5.0, 10.0, 20.0, 40.0], [0.05, 0.1, 0.2, 0.4, 0.8])
    assert (term.ell, term.tau) == (10.0, 0.2)
    assert np.sqrt(term.quadratic(e, S) / e.size) == pytest.approx(0.2, rel=0.08)
    assert table.shape == (5, 5)


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="positive"):
        exponential_correlation(X, 0.0)
    with pytest.raises(ValueError, match="frame scale"):
        RelativeFieldError(X, T, 10.0, 0.2).quadratic(np.zeros((len(T), len(X), 2)), np.zeros(len(T)))
