"""The periodic sheet (bayespd.learn.periodic): the Fourier solve against the sparse one with the
project's adjoint, the symbol against K's spectrum, the refusal of a horizon that meets its image."""
import numpy as np
import pytest
import torch

from bayespd.learn.kernel import lps_params
from bayespd.learn.periodic import periodic_bonds, periodic_grid
from tests.learn.test_kernel import sheet


def test_fourier_solve_is_the_sparse_solve_with_the_same_gradient():
    s = sheet()
    D = torch.tensor([1.0, 0.5, 0.2], requires_grad=True)
    params = lps_params(1.0, 2.0, D, 2.5 * s.material.particles.h)
    f = torch.as_tensor(np.random.default_rng(0).normal(size=(3, s.n, 2)))
    u1, u2 = s.solve(params, f), s.spectral_solve(params, f)
    assert float((u1 - u2).detach().abs().max() / u1.detach().abs().max()) < 1e-11
    g1 = torch.autograd.grad((u1**2).sum(), D)[0]
    g2 = torch.autograd.grad((u2**2).sum(), D)[0]
    assert torch.allclose(g1, g2, rtol=1e-9)


def test_symbol_eigenvalues_are_the_stiffness_spectrum():
    s = sheet(n=8)
    params = lps_params(-1.0, 3.0, [1.0, 1.5, -0.1], 2.6 * s.material.particles.h)
    S = torch.linalg.eigvalsh(s.symbol(params, s.wavevectors)).flatten().sort().values
    K = torch.zeros(2 * s.n, 2 * s.n)
    pat = s.material.pattern
    K[pat.rows, pat.cols] = s.material.stiffness(params)
    dense = torch.linalg.eigvalsh(K).sort().values
    assert float(dense[:2].abs().max()) < 1e-10 * float(dense[-1])  # the two rigid translations
    assert torch.allclose(S, dense[2:], rtol=1e-10, atol=1e-10 * float(dense[-1]))


def test_periodic_bonds_refuse_a_horizon_that_meets_its_own_image():
    p = periodic_grid((20.0, 20.0), 5)
    with pytest.raises(ValueError, match="half the periodic box"):
        periodic_bonds(p, (20.0, 20.0), 9.0)
