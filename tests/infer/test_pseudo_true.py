"""Pseudo-true parameters (``bayespd.infer.pseudo_true``): the chain KL equals the KL of the
two path laws written out as joint Gaussians; a well-specified target projects back onto the
parameters it was made with; the Euler-Maruyama chain is the model's transition."""
import numpy as np
import pytest
import torch
from torch.distributions import MultivariateNormal, kl_divergence

from bayespd.infer.likelihoods import NoiseCovariance, StationaryMarginal, euler_maruyama_transition
from bayespd.infer.pseudo_true import chain_kl, euler_maruyama_chain, kl_projection
from tests.infer.test_likelihoods import make_scene, tensors

MATERIAL = ("K", "G", "delta")
THETA0 = {"K": 3000.0, "G": 1400.0, "delta": 2.2, "eta": 0.002, "sigma": 2e-4}
BOUNDS = {"K": (0.0, np.inf), "G": (0.0, np.inf), "delta": (1.0, 2.5), "eta": (0.0, np.inf),
          "sigma": (0.0, np.inf), "sigma_c": (0.0, np.inf)}


def joint(M, c, S, u0, T):
    """Mean and covariance of (U_1, ..., U_T) of the chain U_{n+1} = M U_n + c + N(0, S)."""
    d = len(u0)
    mus, Ps, mu, P = [], [], u0, torch.zeros(d, d, dtype=u0.dtype)
    for _ in range(T):
        mu, P = M @ mu + c, M @ P @ M.T + S
        mus.append(mu)
        Ps.append(P)
    cov = torch.zeros(T * d, T * d, dtype=u0.dtype)
    for i in range(T):
        for j in range(i + 1):
            block = torch.linalg.matrix_power(M, i - j) @ Ps[j]  # Cov(U_i, U_j), i >= j
            cov[i * d:(i + 1) * d, j * d:(j + 1) * d] = block
            cov[j * d:(j + 1) * d, i * d:(i + 1) * d] = block.T
    return torch.cat(mus), cov


def test_chain_kl_is_the_kl_of_the_path_laws():
    """Random 3-dof chains over 6 steps: the per-step expected KL summed (the chain rule of
    KL) equals the KL of the joint Gaussians of (U_1..U_6) to rounding."""
    g = torch.Generator().manual_seed(0)

    def chain():
        M = 0.6 * torch.eye(3) + 0.2 * torch.randn(3, 3, generator=g)
        R = torch.randn(3, 3, generator=g)
        return M.double(), torch.randn(3, generator=g).double(), (R @ R.T + 0.5 * torch.eye(3)).double()

    (M, c, S), (B, a, Q) = chain(), chain()
    u0 = torch.randn(3, generator=g).double()
    expected = kl_divergence(MultivariateNormal(*joint(M, c, S, u0, 6)), MultivariateNormal(*joint(B, a, Q, u0, 6)))
    assert float(expected) > 1
    assert abs(float(chain_kl(M, c, S, B, a, Q, u0, 6)) - float(expected)) <= 1e-10 * float(expected)


def test_a_well_specified_stationary_law_projects_onto_its_parameters():
    """The stationary law of the model itself at theta0 is in the family: its KL projection,
    the lower of two searches (one started 10-20 % away, one in another delta basin),
    returns theta0 to 1e-4 relative, with KL ~ 0."""
    scene = make_scene()
    marginal = StationaryMarginal(scene)
    target = marginal(tensors(MATERIAL, THETA0), THETA0["eta"], THETA0["sigma"])

    def kl(t):
        law = marginal({k: t[k] for k in MATERIAL}, t["eta"], t["sigma"])
        return kl_divergence(target, law)

    start = {"K": 3500.0, "G": 1200.0, "delta": 2.35, "eta": 0.0025, "sigma": 2.4e-4}
    theta, value = kl_projection(kl, [{**start, "delta": 1.2}, start], BOUNDS)  # the lower of two searches
    assert value <= 1e-8
    for k in THETA0:
        assert abs(theta[k] / THETA0[k] - 1) <= 1e-4, (k, theta[k])
    with pytest.raises(ValueError, match="inside its bounds"):
        kl_projection(kl, {**start, "delta": 2.6}, BOUNDS)


def test_euler_maruyama_chain_is_the_model_transition_and_projects_back():
    """One step: loc M U + c and covariance Sigma of ``euler_maruyama_transition``; four
    substeps of dt / 4 are four one-step chains composed. A path law of the model itself
    projects back onto (K, eta, sigma_c) to 1e-4 relative."""
    scene = make_scene()
    n = len(scene.constraints.free_dofs)
    params = tensors(MATERIAL, THETA0)
    C = NoiseCovariance.white(torch.tensor(0.3), n)
    M, c, S = euler_maruyama_chain(scene, params, 0.002, C, 1e-6)
    U = 1e-3 * torch.randn(2, n, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    law = euler_maruyama_transition(scene, params, 0.002, C, 1e-6, U)
    torch.testing.assert_close(law.mean, U @ M.T + c, rtol=1e-12, atol=0)
    torch.testing.assert_close(law.variance[0], torch.diagonal(S), rtol=1e-12, atol=0)
    M4, c4, S4 = euler_maruyama_chain(scene, params, 0.002, C, 4e-6, substeps=4)
    M1, c1, S1 = euler_maruyama_chain(scene, params, 0.002, C, 1e-6)
    Mk, ck, Sk = torch.eye(n, dtype=torch.float64), torch.zeros(n, dtype=torch.float64), torch.zeros(n, n, dtype=torch.float64)
    for _ in range(4):
        Mk, ck, Sk = M1 @ Mk, M1 @ ck + c1, M1 @ Sk @ M1.T + S1
    torch.testing.assert_close(M4, Mk, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(S4, Sk, rtol=1e-10, atol=1e-20)

    u0 = torch.zeros(n, dtype=torch.float64)
    truth = {"K": 3000.0, "eta": 0.002, "sigma_c": 0.3}

    def chain(t):
        p = {"K": t["K"], "G": params["G"], "delta": params["delta"]}
        return euler_maruyama_chain(scene, p, t["eta"], NoiseCovariance.white(t["sigma_c"], n), 2e-6)

    data = chain({k: torch.tensor(v) for k, v in truth.items()})
    theta, value = kl_projection(lambda t: chain_kl(*data, *chain(t), u0, 20),
                                 {"K": 3300.0, "eta": 0.0023, "sigma_c": 0.33}, BOUNDS)
    assert value <= 1e-8
    for k in truth:
        assert abs(theta[k] / truth[k] - 1) <= 1e-4, (k, theta[k])
