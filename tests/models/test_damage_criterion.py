"""models/damage_criterion.py: s0 of the smoothed damage law (You 2023 eq 3.10) from crack
openings during a displacement-controlled test (its forward model, models/smooth_fracture.py,
is tested in tests/models/test_smooth_fracture.py on the plate below).

A 10 x 12 bond-based plate (h = 1, delta = 3, K = 1, plane strain) with an edge notch a = 4 at
mid-height, the bottom layer fixed and the top layer moved up by lam * 0.06, lam = 0.1 .. 1 in
10 steps; s0 = 0.01, eta = 0.004 (damage starts near lam = 0.3, the crack grows ~2 h).
Openings at 8 stations along the crack line.
"""
import numpy as np
import pyro.distributions as dist
import pytest
import torch

import bayespd as bp
from bayespd.damage import SmoothStep
from bayespd.infer import fit
from bayespd.solvers.quasistatic import quasi_static
from bayespd.models.damage_criterion import damage_criterion
from bayespd.models.load_from_aperture import aperture_observation
from bayespd.models.smooth_fracture import SmoothFracture

W, HEIGHT, DELTA, A, Y_CRACK, TOP = 10.0, 12.0, 3.0, 4.0, 6.0, 0.06
S0, ETA = 0.01, 0.004
LAMS = np.linspace(0.1, 1.0, 10)
X = np.arange(0.5, 8.0, 1.0)


@pytest.fixture(scope="module")
def plate():
    p = bp.grid_2d(W, HEIGHT, 1.0)
    bonds = bp.precrack(p, bp.find_bonds(p, DELTA), [[-1.0, Y_CRACK], [A, Y_CRACK]])
    material = bp.BondBased(p, bonds, plane="strain")
    dirichlet = [bp.Dirichlet.layer(p, "bottom", DELTA), bp.Dirichlet.layer(p, "top", DELTA, (0.0, TOP))]
    obs = aperture_observation(p, np.stack([X, X * 0 + Y_CRACK + 0.5], 1), np.stack([X, X * 0 + Y_CRACK - 0.5], 1))
    return material, dirichlet, obs, SmoothFracture(material, {"K": 1.0, "delta": DELTA}, dirichlet, ETA)


def bond_breaking_openings(material, dirichlet, obs, lam, step):
    """Reference: bayespd.solvers.quasistatic (exact bond kinematics, staggered damage updates)."""
    scene = bp.Scene(material, dirichlet, damage=SmoothStep(S0, ETA))
    res = quasi_static(scene, {"K": 1.0, "delta": DELTA}, np.linspace(step, lam, int(round(lam / step))), damage_tol=1e-9)
    return obs(res.u)


@pytest.mark.slow
def test_laplace_recovers_s0_from_finer_load_steps(plate):
    """Data: the bond-breaking solver with load steps of 0.05 (twice finer), exact kinematics,
    1 % noise. The forward models differ by ~1.5 % in s0 (kinematics, stepping), more than
    the posterior sd (~0.6 %): we require the mean within 3 % of s0 and sigma within 3 sd of
    the noise (the model error is small next to the noise). About 1 min on the shared 2 cores."""
    material, dirichlet, obs, fracture = plate
    clean = torch.stack([bond_breaking_openings(material, dirichlet, obs, lam, 0.05) for lam in LAMS])
    sd = 0.01 * float(clean[..., 1].abs().max())
    y = clean + sd * torch.randn(clean.shape, generator=torch.Generator().manual_seed(0))
    model = damage_criterion(fracture, LAMS, obs, 0.008, 5 * sd)
    tree = fit(model, {"y": y}, "laplace", hessian="gauss-newton", num_samples=20, seed=0, progress=False)
    mode = float(np.exp(tree["sample_stats"]["mode_unconstrained"].sel(unconstrained="s0")))
    assert abs(mode / S0 - 1) < 0.03, mode
    sigma = tree["posterior"]["sigma"].values.ravel()
    assert abs(sigma.mean() - sd) < 3 * sigma.std() + 0.1 * sd


def test_bad_input_is_refused(plate):
    material, dirichlet, obs, fracture = plate
    with pytest.raises(ValueError, match=r"prior of s0 .*negative values.*LogNormal"):
        damage_criterion(fracture, LAMS, obs, 0.01, 1e-3, priors={"s0": dist.Normal(0.01, 0.01)})
    with pytest.raises(ValueError, match="nominal s0 must be finite and positive"):
        damage_criterion(fracture, LAMS, obs, -0.01, 1e-3)
    with pytest.raises(ValueError, match="increasing sequence of positive"):
        damage_criterion(fracture, LAMS[::-1], obs, 0.01, 1e-3)
    with pytest.raises(ValueError, match=r"no such parameter\(s\) \['eta'\]"):
        damage_criterion(fracture, LAMS, obs, 0.01, 1e-3, priors={"eta": dist.LogNormal(0.0, 1.0)})
    model = damage_criterion(fracture, LAMS, obs, 0.01, 1e-3)
    with pytest.raises(ValueError, match=r"y has shape \(9, 8, 2\) but the model predicts \(10, 8, 2\)"):
        model(torch.zeros(9, 8, 2))
