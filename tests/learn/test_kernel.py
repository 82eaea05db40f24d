"""Phase 1 of paper 004 on small synthetic periodic PD data: recovery of known moduli and kernel,
the solvability refusal, the coercivity's long-wave limit."""
import numpy as np
import pytest
import torch

from bayespd.influence import Bernstein
from bayespd.learn.kernel import (UnsolvableKernel, check_solvable, coercivity, learn_kernel, lps_params,
                                  normalised, relative_errors)
from bayespd.learn.periodic import PeriodicSheet, periodic_bonds, periodic_grid
from bayespd.materials.lps import LPS

BOX = (40.0, 38.0)  # not square: cells 4 x 3.8


def sheet(degree=2, n=10, box=BOX, ratio=3.0):
    p = periodic_grid(box, n)
    return PeriodicSheet(LPS(p, periodic_bonds(p, box, ratio * p.h), plane="strain", influence=Bernstein(degree)), box)


def sinusoidal_forces(s, modes):
    """Nodal forces of eq 5.1 loads (n1, n2, axis) on the periodic grid of ``s``."""
    x, v = s.material.particles.x, s.material.particles.volume
    out = []
    for n1, n2, axis in modes:
        f = np.zeros_like(x)
        f[:, axis] = np.cos(x @ (2 * np.pi * np.array([n1, n2]) / np.asarray(BOX))) * v
        out.append(f)
    return torch.as_tensor(np.array(out))


MODES = [(1, 0, 0), (0, 1, 0), (1, 0, 1), (0, 1, 1), (1, 1, 0), (2, 1, 1), (1, 2, 0), (3, 0, 1), (0, 3, 0)]


@pytest.mark.slow
@pytest.mark.parametrize("D, positive", [([1.0, 1.5, -0.1], False), ([0.5, 2.0, 1.0], True)])
def test_learn_kernel_recovers_moduli_and_kernel_shape(D, positive):
    """Noise-free data of the model itself: the minimiser is the truth, so lambda, mu and the
    normalised D come back to the optimiser's tolerance (1e-4 relative at ftol = 1e-12)."""
    s = sheet()
    delta = 2.6 * s.material.particles.h
    true = lps_params(-1.0, 3.0, D, delta)
    f = sinusoidal_forces(s, MODES)
    u = s.spectral_solve(true, f).detach()
    fit = learn_kernel(s, f, u, delta, positive_kernel=positive, ftol=1e-14, maxiter=400)
    assert abs(fit.lam - -1.0) < 1e-4 * 3.0 and abs(fit.mu - 3.0) < 1e-4 * 3.0
    np.testing.assert_allclose(fit.D, normalised(s.material.influence, true["D"], delta).numpy(), rtol=1e-3, atol=1e-3)
    assert fit.misfit < 1e-10
    errors = relative_errors(s, fit.params(), f, u, spectral=False)  # the sparse solve agrees
    assert float(errors.max()) < 1e-4


def test_unsolvable_kernel_is_refused_naming_the_fix():
    s = sheet()
    bad = lps_params(-1.0, 3.0, [-2.0, 0.0, 1.0], 2.6 * s.material.particles.h)
    assert float(coercivity(s, bad)) < 0  # some wave costs negative energy
    with pytest.raises(UnsolvableKernel, match="solvability constraint.*eq 4.4.*learn_kernel"):
        check_solvable(s, bad)
    with pytest.raises(UnsolvableKernel, match="weighted volume"):  # m <= 0: not a kernel at all
        check_solvable(s, lps_params(-1.0, 3.0, [-1.0, -1.0, -1.0], 2.6 * s.material.particles.h))
    good = lps_params(-1.0, 3.0, [1.0, 1.0, 1.0], 2.6 * s.material.particles.h)
    assert check_solvable(s, good) > 0.05


def test_coercivity_of_a_constant_kernel_tends_to_one_at_long_waves():
    """For local elasticity the normalised symbol is min(mu, lambda + 2 mu) / mu = 1 at long waves;
    the LPS symbol's relative deviation there is O((k delta)^2) plus the lattice quadrature error."""
    s = sheet(n=16, box=(64.0, 64.0), ratio=2.0)
    params = lps_params(2.0, 1.0, [1.0, 1.0, 1.0], 2.0 * s.material.particles.h)
    k = s.wavevectors[(s.wavevectors.norm(dim=1) - 2 * np.pi / 64).abs() < 1e-9]
    low = torch.linalg.eigvalsh(s.symbol(params, k))
    ratio = low / (float(s.material.particles.volume[0]) * (2 * np.pi / 64) ** 2)
    assert torch.allclose(ratio[:, 0], torch.tensor(1.0), rtol=0.1)   # mu = 1
    assert torch.allclose(ratio[:, 1], torch.tensor(4.0), rtol=0.1)   # lambda + 2 mu = 4
