"""Influence functions: closed-form moments, calibration that makes the bulk response
independent of the choice, and gradients in delta and the learnable coefficients."""
import numpy as np
import pytest
import torch
from scipy.integrate import quad

import bayespd as bp
from bayespd.influence import Bernstein, Conical, Constant, Gaussian
from tests.materials.test_lps import classical_energy_density

E, NU = 4000.0, 0.3
D = torch.tensor([1.0, 2.0, 0.5, 0.3])
INFLUENCES = [(Constant(), {}), (Conical(), {}), (Gaussian(0.5), {}), (Bernstein(3, alpha=1.0), {"D": D})]
IDS = ["constant", "conical", "gaussian", "bernstein"]


@pytest.mark.parametrize("influence,extra", INFLUENCES, ids=IDS)
@pytest.mark.parametrize("k", [2, 3])
def test_moments_match_quadrature(influence, extra, k):
    delta = 2.7
    f = lambda r: float(influence(torch.tensor([r]), delta, extra)[0]) * r**k  # noqa: E731
    expected = quad(f, 0.0, delta, epsabs=0, epsrel=1e-12)[0]
    np.testing.assert_allclose(float(influence.moment(k, delta, extra)), expected, rtol=1e-10)


@pytest.fixture(scope="module")
def lattice():
    p = bp.grid_2d(24.0, 24.0, 1.0)
    return p, bp.find_bonds(p, 3.0)


@pytest.mark.parametrize("influence,extra", INFLUENCES, ids=IDS)
def test_lps_patch_and_energy_with_any_influence(lattice, influence, extra):
    """LPS absorbs omega into m: affine fields give zero interior force (1e-10) and the
    classical energy for a dilatation and for a strain plus its 45-degree rotation (1e-8),
    whatever the influence function."""
    p, bonds = lattice
    mat = bp.LPS(p, bonds, influence=influence)
    K, G = bp.moduli_from_young(E, NU)
    params = dict(extra, K=K, G=G)
    x = torch.as_tensor(p.x)
    eps = torch.tensor([[1e-3, 4e-4], [4e-4, -2e-3]])
    f = mat.pattern.matvec(mat.stiffness(dict(params, delta=3.0)), (x @ eps.T).reshape(-1)).reshape(-1, 2)
    inner = p.interior(2 * 3.5 + 1e-9)
    assert f[inner].abs().max() <= 1e-10 * f[~inner].abs().max()
    near = p.interior(3.5 + 1e-9)

    def W(e):
        return mat.energy_density(dict(params, delta=3.0), x @ torch.as_tensor(e).T)[near]

    iso = 1e-3 * np.eye(2)
    np.testing.assert_allclose(W(iso), classical_energy_density(iso, "stress"), rtol=1e-8)
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    R = np.array([[c, -s], [s, c]])
    e = eps.numpy()
    np.testing.assert_allclose(W(e) + W(R @ e @ R.T), 2 * classical_energy_density(e, "stress"), rtol=1e-8)


@pytest.mark.parametrize("influence,extra", INFLUENCES, ids=IDS)
def test_bond_based_calibration_converges_for_any_influence(influence, extra):
    """The micromodulus is calibrated with the same omega on the continuum family, so the
    interior energy of an isotropic expansion tends to the classical one as m grows; the
    partial-volume quadrature error falls like 1/m^2 (measured ratios 3.4-6.2 from m=3 to 6)."""
    K, strain = 1.0e3, 1e-3
    classical = 0.5 * (2 * strain) ** 2 * (0.75 * K)  # plane stress PMB: 2D bulk 3K/4
    errors = []
    for m in (3, 6):
        p = bp.grid_2d(8.0 * m, 8.0 * m, 1.0)
        mat = bp.BondBased(p, bp.find_bonds(p, float(m)), influence=influence)
        W = mat.energy_density(dict(extra, K=K, delta=float(m)), strain * torch.as_tensor(p.x))
        inner = p.interior(m + 0.5 + 1e-9)
        errors.append(abs(float(W[inner].mean()) - classical) / classical)
    assert errors[1] < 0.4 * errors[0] and errors[1] < 0.025, errors


def test_gradients_in_delta_and_bernstein_coefficients():
    """Scene.solve is differentiable in the Bernstein coefficients D and delta (gradcheck),
    through the same one-extra-solve adjoint."""
    p = bp.grid_2d(8.0, 5.0, 1.0)
    mat = bp.LPS(p, bp.find_bonds(p, 2.5), influence=Bernstein(2, alpha=0.5))
    scene = bp.Scene(mat, [bp.Dirichlet.layer(p, "left", 2.5)], [bp.Load(p.layer("right", 1.0), (30.0, 10.0))])
    assert scene.param_names == ("K", "G", "D", "delta")

    def u(D, delta):
        return scene.solve({"K": 3000.0, "G": 1400.0, "D": D, "delta": delta})[-3:]

    D0 = torch.tensor([1.0, 0.7, 0.4], requires_grad=True)
    delta = torch.tensor(2.2, requires_grad=True)
    assert torch.autograd.gradcheck(u, (D0, delta), eps=1e-6, atol=1e-8, rtol=1e-5)


def test_bernstein_input_errors():
    with pytest.raises(ValueError, match="alpha must be below 3"):
        Bernstein(2, alpha=3.0)
    p = bp.grid_2d(6.0, 4.0, 1.0)
    mat = bp.LPS(p, bp.find_bonds(p, 2.0), influence=Bernstein(2))
    with pytest.raises(ValueError, match=r"needs params \['D'\]"):
        mat.stiffness({"K": 1.0, "G": 1.0, "delta": 2.0})
    with pytest.raises(ValueError, match="3 finite coefficients"):
        mat.stiffness({"K": 1.0, "G": 1.0, "D": torch.ones(2), "delta": 2.0})


def test_bernstein_beyond_the_horizon_and_second_derivatives():
    """Bonds between delta and delta + h/2 (partial volumes) take omega(delta), whatever the
    polynomials do beyond 1; omega is twice differentiable in delta and D also where r = delta
    (a tensor power x**0 would give 0 * inf there)."""
    b = Bernstein(3)
    D = torch.tensor([1.0, 2.0, 0.5, 0.3], requires_grad=True)
    delta = torch.tensor(2.0, requires_grad=True)
    r = torch.tensor([0.5, 2.0, 2.3, 2.49])
    w = b(r, delta, {"D": D})
    assert torch.allclose(w[1:], D[-1].detach().expand(3))
    H = torch.autograd.functional.hessian(lambda z: b(r, z[4], {"D": z[:4]}).sum() ** 2, torch.cat([D, delta[None]]).detach())
    assert bool(torch.isfinite(H).all())
