"""``models/smooth_fracture.py``: quasi-static loading under the smoothed damage law (You 2023
eq 3.10), small-strain and differentiable in s0. Without damage it is the linear static solve,
linear in the load factor; its equilibria zero the residual; the gradient in s0 and the
openings of the notched plate of ``tests/models/test_damage_criterion.py`` (moved here)."""
import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.models.smooth_fracture import SmoothFracture
from tests.models.test_damage_criterion import (DELTA, ETA, LAMS, S0, X, bond_breaking_openings,  # noqa: F401
                                                plate)

PARAMS = {"K": 1.0, "delta": 2.0}


@pytest.fixture(scope="module")
def block():
    """A 6 x 6 bond-based block, bottom clamped, top moved by (0.01, 0.02) at load factor 1."""
    p = bp.grid_2d(6.0, 6.0, 1.0)
    material = bp.BondBased(p, bp.find_bonds(p, 2.0))
    dirichlet = [bp.Dirichlet.layer(p, "bottom", 2.0), bp.Dirichlet.layer(p, "top", 2.0, (0.01, 0.02))]
    return material, dirichlet


def test_without_damage_it_is_the_linear_static_solve(block):
    """s0 = 100 (gamma = 1 to rounding at strains ~1e-2): u(lam) = lam u(1), and u(1) is
    Scene.solve of the same material and Dirichlet values (K = B^T diag(k) B), to 1e-10."""
    material, dirichlet = block
    u = SmoothFracture(material, PARAMS, dirichlet, 0.01).run(100.0, [0.5, 1.0])
    ref = bp.Scene(material, dirichlet).solve(PARAMS).detach()
    scale = float(ref.abs().max())
    assert float((u[1] - ref).abs().max()) <= 1e-10 * scale
    assert float((u[0] - 0.5 * u[1]).abs().max()) <= 1e-10 * scale


def test_the_equilibria_zero_the_residual_and_damage_softens(block):
    """s0 = 0.004 at the block's strain level (~0.005), eta = 0.002: at each step the
    residual R(u_f) = B_f^T (k gamma e) vanishes to 1e-9 of the sum of the |bond terms|
    (Newton to rtol 1e-10) with the history h carried between steps; some bonds are more
    than half broken, and the displacement departs from the undamaged one."""
    material, dirichlet = block
    fracture = SmoothFracture(material, PARAMS, dirichlet, 0.002)
    lams = [0.5, 1.0]
    s0 = torch.tensor(0.004)
    u = fracture.run(s0, lams)
    c = fracture.constraints
    h = torch.zeros(len(fracture.length))
    for lam, ui in zip(lams, u):
        u_f = c.free(ui)
        e, s, gamma, _ = fracture._parts(u_f, lam, h, s0)
        R = fracture.residual(u_f, lam, h, s0)
        assert float(R.norm()) <= 1e-9 * float((fracture.B_f.T.abs() @ (fracture.k * gamma * e).abs()).norm())
        h = torch.maximum(h, s)
    assert float(gamma.min()) < 0.5  # some bonds mostly broken
    elastic = fracture.run(100.0, lams)[-1]
    assert float((u[-1] - elastic).abs().max()) > 1e-3 * float(elastic.abs().max())


def test_force_control_is_refused(block):
    material, _ = block
    with pytest.raises(ValueError, match="displacement control needs a Dirichlet region with a non-zero value"):
        SmoothFracture(material, PARAMS, [bp.Dirichlet.layer(material.particles, "bottom", 2.0)], 0.01)


# moved from tests/models/test_damage_criterion.py
def test_gradient_in_s0_matches_finite_differences(plate):
    """Central differences have error O(e^2): with e = 1e-6 s0 the two agree to ~1e-8."""
    *_, obs, fracture = plate
    s0 = torch.tensor(S0, requires_grad=True)
    y = fracture.run(s0, LAMS, obs)[..., 1]
    w = torch.linspace(1.0, 2.0, y.numel()).reshape(y.shape)
    (g,) = torch.autograd.grad((w * y).sum(), s0)
    e = 1e-6 * S0
    with torch.no_grad():
        fd = ((w * fracture.run(S0 + e, LAMS, obs)[..., 1]).sum()
              - (w * fracture.run(S0 - e, LAMS, obs)[..., 1]).sum()) / (2 * e)
    assert abs(float(g) - float(fd)) < 1e-6 * abs(float(fd)), (float(g), float(fd))
    assert float(g) < 0  # a weaker criterion opens the crack more


def test_openings_agree_with_the_bond_breaking_solver(plate):
    """Same grid and steps, exact kinematics: the small-strain model differs by the geometric
    nonlinearity of the process zone (bond stretches up to a few s0): within 3 % of the largest
    opening, and the crack has grown (the station 0.5 h ahead of the notch tip opens > 3x its
    undamaged value)."""
    material, dirichlet, obs, fracture = plate
    with torch.no_grad():
        y = fracture.run(S0, LAMS, obs)[-1]
        elastic = fracture.run(10.0, LAMS, obs)[-1]
    ref = bond_breaking_openings(material, dirichlet, obs, 1.0, 0.1)
    assert float((y - ref)[:, 1].abs().max()) < 0.03 * float(ref[:, 1].abs().max())
    tip = int(np.argmin(np.abs(X - 4.5)))
    assert float(y[tip, 1]) > 3 * float(elastic[tip, 1])


def test_a_law_that_is_not_pairwise_or_a_non_positive_eta_is_refused(plate):
    material, dirichlet, obs, fracture = plate
    with pytest.raises(ValueError, match="bond-based"):
        SmoothFracture(bp.LPS(material.particles, material.bonds), {"K": 1.0, "G": 1.0, "delta": DELTA},
                       dirichlet, ETA)
    with pytest.raises(ValueError, match="eta must be positive"):
        SmoothFracture(material, {"K": 1.0, "delta": DELTA}, dirichlet, 0.0)
