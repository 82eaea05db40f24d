"""bayespd.infer.trust_region: the exact trust-region subproblem, and the Laplace step from a
saddle (where L-BFGS stops at once: the gradient vanishes) reaching the true mode with the
analytic covariance."""
import warnings

import pyro
import pyro.distributions as dist
import pytest
import torch
from pyro.distributions import constraints
from pyro.infer.autoguide.initialization import init_to_value

from bayespd.infer.laplace import laplace
from bayespd.infer.mode import find_map
from bayespd.infer.trust_region import step
from tests.infer.test_mode import _Potential

H = torch.tensor([[-1.75, -0.5], [-0.5, 1.0]])  # indefinite: eigenvalues -1.85, 1.10


def kkt(g, h, p, radius):
    """The multiplier of Nocedal & Wright Theorem 4.1: (H + lam I) p = -g with lam >= 0 and
    H + lam I positive semidefinite, lam (radius - |p|) = 0; returns lam (checked to 1e-10)."""
    lam = float(-(g + h @ p) @ p / (p @ p))
    assert torch.allclose((h + lam * torch.eye(len(g), dtype=h.dtype)) @ p, -g, atol=1e-10, rtol=0)
    assert lam >= -1e-12 and float(torch.linalg.eigvalsh(h)[0]) + lam >= -1e-10
    assert lam < 1e-10 or abs(float(p.norm()) - radius) < 1e-10
    return lam


@pytest.mark.parametrize("g, h, radius", [
    (torch.tensor([0.3, -0.2]), torch.tensor([[4.0, 1.0], [1.0, 3.0]]), 10.0),  # interior Newton step
    (torch.tensor([3.0, -2.0]), torch.tensor([[4.0, 1.0], [1.0, 3.0]]), 0.1),  # on the boundary
    (torch.tensor([0.3, -0.2]), H, 0.5),  # indefinite
    (torch.tensor([0.0, 0.0]), H, 0.5),  # the hard case: a saddle
])
def test_step_solves_the_subproblem(g, h, radius):
    """The step meets the optimality conditions of the subproblem, and the predicted decrease is
    the model's -(g.p + p.H.p / 2) (positive away from a minimum)."""
    g, h = g.double(), h.double()
    p, predicted = step(g, h, radius)
    kkt(g, h, p, radius)
    assert predicted == pytest.approx(float(-(g @ p + p @ h @ p / 2)), rel=1e-14) and predicted > 0


def test_a_converged_mode_is_left_where_it_is():
    """At the exact mode of a quadratic (gradient exactly 0, Hessian positive definite) the
    search returns the start bit for bit."""
    P = torch.tensor([[4.0, 1.0], [1.0, 3.0]], dtype=torch.float64)
    m = torch.tensor([0.75, -1.25], dtype=torch.float64)
    space = _Potential(lambda z: 0.5 * (z - m) @ P @ (z - m), m.tolist())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        z, u, g, h, _ = find_map(space, hessian_fn=lambda z: P, progress=False)
    assert torch.equal(z, m) and u == 0.0


K, C = 2.0, 0.5


def double_well():
    """U(z) = K (z1^2 - 1)^2 / 4 + (z2 - C z1)^2 / 2 on a flat prior: a saddle at 0 (Hessian H
    above), modes at +-(1, C) with Hessian [[2K + C^2, -C], [-C, 1]]."""
    z = pyro.sample("z", dist.ImproperUniform(constraints.real_vector, (), (2,)))
    pyro.factor("U", -(K * (z[0] ** 2 - 1) ** 2 / 4 + (z[1] - C * z[0]) ** 2 / 2))


def test_laplace_from_a_saddle_reaches_a_mode_with_the_analytic_covariance():
    """L-BFGS stops at the saddle (its gradient is 0); the trust-region polish follows the negative
    curvature to a mode. Tolerance: the polish ends one Newton step after the predicted decrease
    falls below 1e-13, i.e. from |z - z*| <= sqrt(2e-13 / 0.94) = 5e-7 (0.94: the mode's smallest
    curvature), and Newton's error is then <= |U'''| / (2 x 0.94) |z - z*|^2 = 6.4 x 2.1e-13 = 1.4e-12
    (|U'''| = 6 K |z1| <= 12); the covariance moves by |U'''| |z - z*| |H^-1|^2 < 1e-10."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        saddle = init_to_value(values={"z": torch.zeros(2, dtype=torch.float64)})
        space, gaussian, info = laplace(double_well, {}, saddle, progress=False)
    sign = 1.0 if float(gaussian.mean[0]) > 0 else -1.0
    mode = sign * torch.tensor([1.0, C], dtype=torch.float64)
    assert torch.allclose(gaussian.mean, mode, atol=1e-10, rtol=0)
    analytic = torch.linalg.inv(torch.tensor([[2 * K + C**2, -C], [-C, 1.0]], dtype=torch.float64))
    assert torch.allclose(gaussian.covariance, analytic, atol=1e-10, rtol=0)
    assert info["map_grad_norm"] < 1e-10
