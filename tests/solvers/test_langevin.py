"""Overdamped Langevin dynamics (Dodwell 2019 eq 4): deterministic limit, invariant law,
strong/weak order of Euler-Maruyama, stiff stability, correlated (Karhunen-Loeve) noise."""
import re

import numpy as np
import pytest
import scipy.sparse as sp
import torch

import bayespd as bp
from bayespd.solvers import (Langevin, LinearForce, NumericalInstabilityError, karhunen_loeve,
                             linear_elastic, white_noise)

ETA, SIGMA = 0.5, 0.7  # eta != 1 and sigma != 1, so a wrong scaling shows


@pytest.fixture(scope="module")
def plate():
    """24 dofs: a 4 x 3 bond-based plate, no Dirichlet, confinement eps = 0.2 (Dodwell 2019 eq 3),
    cond(A) ~ 11."""
    p = bp.grid_2d(4, 3, 1.0)
    mat = bp.BondBased(p, bp.find_bonds(p, 2.0))
    load = torch.zeros(p.n, 2)
    load[:, 0] = torch.linspace(-0.1, 0.2, p.n)
    return p, linear_elastic(mat, {"K": 1.0, "delta": 2.0}, load=load, eps=0.2)


def discrete_covariance(A, C, dt, theta):
    """Stationary covariance of the theta-chain for f = p - A u: eta (A + (theta - 1/2) a A C A)^-1."""
    return ETA * np.linalg.inv(A + (theta - 0.5) * dt / ETA * A @ C @ A)


def whitened_scores(U, mean, cov):
    """For chains U (n, B) against N(mean, cov): z-scores of the sample mean, of each entry of
    the whitened covariance (standard errors 1/sqrt(B) off the diagonal, sqrt(2/B) on it), and
    of its trace (sum of n B squared standard normals: SE sqrt(2 n B))."""
    n, B = U.shape
    Z = np.linalg.solve(np.linalg.cholesky(cov), U - mean[:, None])
    S = Z @ Z.T / B
    se = np.sqrt((1 + np.eye(n)) / B)
    return (np.abs(Z.mean(1)) * np.sqrt(B)).max(), (np.abs(S - np.eye(n)) / se).max(), \
        abs(np.trace(S) - n) * B / np.sqrt(2 * n * B)


@pytest.mark.parametrize("theta", [0.0, 0.5, 1.0])
def test_deterministic_limit_is_the_gradient_flow(plate, theta):
    """dB = 0 gives eta du/dt = -C grad V; against the exact solution m + Q exp(-sigma^2 Lambda
    t / eta) Q^T (u0 - m) the error at t = 3 is O(dt) (EM, implicit Euler: ratio 2 per halving)
    and O(dt^2) for theta = 1/2 (ratio 4)."""
    _, F = plate
    A = F.matrix.toarray()
    lam, Q = np.linalg.eigh(A)
    m = np.linalg.solve(A, F.load.numpy())
    u0 = torch.ones(F.n)
    T = 3.0
    exact = m + Q @ (np.exp(-SIGMA**2 * lam * T / ETA) * (Q.T @ (u0.numpy() - m)))
    L = Langevin(F, white_noise(SIGMA, F.n), ETA, operator=F.matrix)
    errors = []
    for steps in (40, 80, 160):
        tr = L.run(u0, T / steps, steps, theta=theta, brownian=torch.zeros(steps, F.n))
        errors.append(np.abs(tr.final.numpy() - exact).max())
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    expected = 4.0 if theta == 0.5 else 2.0
    assert np.all(np.abs(ratios - expected) < 0.15 * expected), ratios


@pytest.mark.parametrize("theta", [0.0, 0.5, 1.0])
def test_stationary_law_is_eta_inverse_stiffness(plate, theta):
    """In the elastic regime the invariant law of eq 4 is N(A^-1 p, eta A^-1), A = K + eps I.
    2000 independent chains at one late time are i.i.d., so the test needs no autocorrelation
    correction; the burn-in bias (slowest contraction rate^(2 steps)) is bounded below 1e-6.
    The chain's own law is N(A^-1 p, eta (A + (theta - 1/2) a A C A)^-1) (a = dt / eta):
    exactly eta A^-1 for theta = 1/2 at any dt; EM is run at 0.9 of its limit where its law
    is far from eta A^-1 (top mode variance 10x), which the same scores must detect.
    Tolerances: 4.5 standard errors; the trace score alone detects a 2.6% error in the scale
    of the covariance (e.g. eta^2 or 1 instead of eta)."""
    _, F = plate
    A = F.matrix.toarray()
    C = white_noise(SIGMA, F.n)
    L = Langevin(F, C, ETA, operator=F.matrix)
    lam = np.linalg.eigvalsh(C.dense() @ A)
    if theta == 0.5:  # a lam spread geometrically around 2: fastest mixing
        dt = 2 * ETA / np.sqrt(lam.min() * lam.max())
    else:
        dt = 0.9 * L.explicit_limit()
        assert dt == pytest.approx(0.9 * 2 * ETA / lam.max(), rel=1e-8)
    z = dt / ETA * lam
    rate = np.abs((1 - (1 - theta) * z) / (1 + theta * z)).max()
    steps = int(np.ceil(np.log(1e-6) / (2 * np.log(rate))))
    B = 2000
    tr = L.run(torch.zeros(F.n, B), dt, steps, theta=theta, generator=7)
    m = F.equilibrium().numpy()
    S_chain = discrete_covariance(A, C.dense(), dt, theta)
    mean_z, entry_z, trace_z = whitened_scores(tr.final.numpy(), m, S_chain)
    assert mean_z < 4.5 and entry_z < 4.5 and trace_z < 4.5, (steps, mean_z, entry_z, trace_z)
    _, entry_c, _ = whitened_scores(tr.final.numpy(), m, ETA * np.linalg.inv(A))
    if theta == 0.5:
        np.testing.assert_allclose(S_chain, ETA * np.linalg.inv(A), rtol=1e-10, atol=1e-12)
        wrong = whitened_scores(tr.final.numpy(), m, ETA**2 * np.linalg.inv(A))[2]
        assert wrong > 20  # the eta^2 A^-1 law (temperature eta^2) is rejected
    elif theta == 0.0:
        assert entry_c > 20  # EM near its limit is visibly off the continuum law


def test_stationary_law_with_correlated_noise(plate):
    """With C = sigma^2 (R_r + nugget I) (Karhunen-Loeve, rank 4 of 12) the invariant law is
    still N(A^-1 p, eta A^-1): C changes the path, not the law. theta = 1/2 samples it exactly
    (the implicit step goes through Woodbury)."""
    p, F = plate
    A = F.matrix.toarray()
    C = karhunen_loeve(p.x, SIGMA, 1.5, rank=4, nugget=0.2)
    assert C.n_xi == 8 + F.n
    L = Langevin(F, C, ETA, operator=F.matrix)
    lam = np.linalg.eigvals(C.dense() @ A).real
    dt = 2 * ETA / np.sqrt(lam.min() * lam.max())
    z = dt / ETA * lam
    steps = int(np.ceil(np.log(1e-6) / (2 * np.log(np.abs((1 - z / 2) / (1 + z / 2)).max()))))
    tr = L.semi_implicit(torch.zeros(F.n, 2000), dt, steps, theta=0.5, generator=3)
    scores = whitened_scores(tr.final.numpy(), F.equilibrium().numpy(), ETA * np.linalg.inv(A))
    assert max(scores) < 4.5, (steps, scores)


def _ou_paths(lam, T, n_fine, M, seed):
    """Brownian increments on n_fine steps and, on the same paths, the exact stochastic
    integrals I_i = int_0^T exp(-k_i (T - s)) dW_i(s) (k_i = sigma^2 lam_i / eta): per step,
    (dW, int exp(-k (T - s)) dW) is bivariate normal with known covariance."""
    g = torch.Generator().manual_seed(seed)
    h = T / n_fine
    k = SIGMA**2 * lam / ETA
    t = np.arange(n_fine + 1) * h
    decay = np.exp(-k[None, :] * (T - t[:, None]))  # (n_fine + 1, dofs)
    cov = (decay[1:] - decay[:-1]) / k  # Cov(dW, I_j)
    var = (decay[1:] ** 2 - decay[:-1] ** 2) / (2 * k)  # Var(I_j)
    dW = torch.randn(n_fine, len(lam), M, generator=g) * np.sqrt(h)
    zeta = torch.randn(n_fine, len(lam), M, generator=g)
    I_j = torch.as_tensor(cov / h)[..., None] * dW + torch.as_tensor(np.sqrt(var - cov**2 / h))[..., None] * zeta
    return dW, I_j.sum(0)


def test_euler_maruyama_strong_and_weak_order():
    """Ornstein-Uhlenbeck problem (A = diag(0.5, 2), C = sigma^2 I), T = 1. The reference is
    the exact solution X(T) = m + exp(-kT)(u0 - m) + sqrt(2) sigma int exp(-k(T-s)) dW on the
    same Brownian paths; coarse paths sum the fine increments.

    Strong: EM's strong order is 1/2 in general, but eq 4's noise is additive (C does not
    depend on U), where EM coincides with Milstein and has strong order 1: the RMS error
    slope is 1 (asserted in [0.9, 1.1], so >= 1/2 a fortiori).
    Weak: E|X|^2 error against the exact moment, estimated as mean(|X_h|^2 - |X(T)|^2) over
    coupled paths (a control variate with exactly known mean: SE ~ 1% of the error): slope 1
    (pre-asymptotic ratios 2.03-2.06 on these levels).
    """
    lam, p0, T, M = np.array([0.5, 2.0]), np.array([0.5, 0.0]), 1.0, 4000
    F = LinearForce(sp.diags(lam), p0)
    L = Langevin(F, white_noise(SIGMA, 2), ETA)
    u0 = np.ones(2)
    n_fine = 128
    dW, integral = _ou_paths(lam, T, n_fine, M, seed=11)
    k, m = SIGMA**2 * lam / ETA, p0 / lam
    mean = m + np.exp(-k * T) * (u0 - m)
    exact = torch.as_tensor(mean)[:, None] + np.sqrt(2) * SIGMA * integral
    second_moment = float((mean**2 + ETA / lam * (1 - np.exp(-2 * k * T))).sum())
    phi_exact = (exact**2).sum(0)
    assert abs(float(phi_exact.mean()) - second_moment) < 4.5 * float(phi_exact.std()) / np.sqrt(M)
    hs, strong, weak, weak_se = [], [], [], []
    for n in (16, 32, 64, 128):
        r = n_fine // n
        x = L.euler_maruyama(torch.as_tensor(u0)[:, None].repeat(1, M), T / n, n,
                             brownian=dW.reshape(n, r, 2, M).sum(1)).final
        d = (x**2).sum(0) - phi_exact
        hs.append(T / n)
        strong.append(float(((x - exact) ** 2).sum(0).mean().sqrt()))
        weak.append(float(d.mean()))
        weak_se.append(float(d.std()) / np.sqrt(M))
    assert max(np.array(weak_se) / np.abs(weak)) < 0.05
    strong_order = np.polyfit(np.log(hs), np.log(strong), 1)[0]
    weak_order = np.polyfit(np.log(hs), np.log(np.abs(weak)), 1)[0]
    assert 0.9 < strong_order < 1.1, strong
    assert 0.9 < weak_order < 1.1, weak


def test_semi_implicit_is_stable_far_beyond_the_explicit_limit(plate):
    """At dt = 100x the EM limit 2 eta / lambda_max(C A): EM blows up and says so (with the
    limit, not NaNs); implicit Euler stays bounded with the exact mean A^-1 p (its covariance
    is eta (A + a A C A / 2)^-1, which gives the standard errors)."""
    _, F = plate
    A = F.matrix.toarray()
    C = white_noise(SIGMA, F.n)
    L = Langevin(F, C, ETA, operator=F.matrix)
    limit = L.explicit_limit()
    dt = 100 * limit
    with pytest.raises(NumericalInstabilityError, match="reduce dt below") as info:
        L.euler_maruyama(torch.zeros(F.n), dt, 1000, generator=0)
    stated = float(re.search(r"reduce dt below ([0-9.eE+-]+)", str(info.value)).group(1))
    assert stated == pytest.approx(limit, rel=1e-5)
    B = 1000
    tr = L.semi_implicit(torch.zeros(F.n, B), dt, 20, generator=1, save_every=1)
    assert torch.isfinite(tr.u).all()
    S = discrete_covariance(A, C.dense(), dt, 1.0)
    U = tr.u[5:].permute(1, 0, 2).reshape(F.n, -1).numpy()  # 15 states x 1000 chains
    m = F.equilibrium().numpy()
    assert np.abs(U - m[:, None]).max() < 6 * np.sqrt(S.diagonal().max())
    mean_z, _, _ = whitened_scores(tr.final.numpy(), m, S)
    assert mean_z < 4.5


@pytest.mark.parametrize("nugget", [0.0, 0.3])
def test_implicit_solver_solves_the_linear_system(plate, nugget):
    """(I + b C A) x = r, for white, KL + nugget (Cholesky + Woodbury) and pure low-rank KL."""
    p, F = plate
    A = F.matrix.toarray()
    r = np.random.default_rng(0).standard_normal((F.n, 3))
    for C in (white_noise(torch.linspace(0.5, 1.0, F.n), F.n), karhunen_loeve(p.x, SIGMA, 1.5, rank=5, nugget=nugget)):
        x = C.implicit_solver(F.matrix, 0.7)(torch.as_tensor(r)).numpy()
        np.testing.assert_allclose((np.eye(F.n) + 0.7 * C.dense() @ A) @ x, r, atol=1e-10)


def test_runs_are_reproducible_and_refuse_missing_seeds(plate):
    _, F = plate
    L = Langevin(F, white_noise(SIGMA, F.n), ETA, operator=F.matrix)
    a = L.semi_implicit(torch.zeros(F.n), 0.5, 10, generator=42).final
    b = L.semi_implicit(torch.zeros(F.n), 0.5, 10, generator=torch.Generator().manual_seed(42)).final
    assert torch.equal(a, b)
    with pytest.raises(ValueError, match="generator="):
        L.euler_maruyama(torch.zeros(F.n), 0.1, 10)
    with pytest.raises(ValueError, match="operator="):
        Langevin(F, white_noise(SIGMA, F.n), ETA).semi_implicit(torch.zeros(F.n), 0.1, 1, generator=0)
