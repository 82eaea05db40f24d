"""Phase 2 of paper 004 (eqs 3.10, 4.8-4.9) on synthetic data: a crack opening across a line of a
small grid, forces made with a known s0, and s0 recovered by minimising the residual."""
import numpy as np
import pytest
import torch

from bayespd.bonds import find_bonds
from bayespd.discretize import grid_2d
from bayespd.influence import Bernstein
from bayespd.learn.criterion import MASS, DamageResidual, FractureData, learn_s0, max_stretch
from bayespd.learn.kernel import lps_params
from bayespd.materials.lps import LPS

S0 = 0.12


def opening_crack(frames=8, h=1.0):
    """An 8 x 8 grid; the right half moves away by 0.05 n h at frame n (with a smooth stretch)."""
    p = grid_2d(8.0, 8.0, h)
    material = LPS(p, find_bonds(p, 2.5 * h), plane="strain", influence=Bernstein(2))
    params = lps_params(1.0, 2.0, [0.5, 2.0, 1.0], 2.5 * h)
    right = (p.x[:, 0] > 4.0).astype(float)
    n = np.arange(frames)[:, None]
    u = np.zeros((frames, p.n, 2))
    u[:, :, 0] = 0.05 * h * n * right + 0.002 * n * p.x[:, 0]
    u[:, :, 1] = 0.003 * n * np.sin(p.x[:, 1])
    rho = np.full((frames, p.n), 2.0)
    return material, params, rho, u


def test_stretch_history_is_the_running_maximum_of_eq_3_16():
    material, _, _, u = opening_crack()
    u[3] = 0.0  # a frame back at rest does not heal a bond
    s = max_stretch(material, torch.as_tensor(u)).numpy()
    assert np.all(np.diff(s, axis=0) >= 0)
    y = material.bonds.xi + u[5][material.bonds.j] - u[5][material.bonds.i]
    direct = np.maximum(np.linalg.norm(y, axis=1) / material.bonds.length - 1, 0)
    assert np.all(s[5] >= direct - 1e-15) and np.allclose(s[-1], np.maximum(s[-2], s[-1]))


def test_s0_is_recovered_from_forces_made_with_it():
    material, params, rho, u = opening_crack()
    dt, nodes = 0.1, np.ones(material.particles.n, bool)
    zero = FractureData(rho, u, np.zeros_like(u), dt, nodes)
    b = np.zeros_like(u)
    b[1:-1] = DamageResidual(material, params, zero).residuals(S0)  # b balancing the s0 model exactly
    residual = DamageResidual(material, params, FractureData(rho, u, b, dt, nodes))
    assert residual(S0) < 1e-20 * residual(1e6)
    fit = learn_s0(residual, bounds=(0.01, 1.0), xatol=1e-5)
    assert abs(fit.s0 - S0) < 1e-3 * S0
    assert fit.residual < 1e-12 * fit.residual_intact


def test_inertia_uses_the_central_difference_in_ev_units():
    material, params, rho, u = opening_crack(frames=3)
    data = FractureData(rho, u, np.zeros_like(u), 0.5, np.ones(material.particles.n, bool))
    r = DamageResidual(material, params, data)
    expected = MASS * 2.0 * (u[2] - 2 * u[1] + u[0]) / 0.25
    np.testing.assert_allclose(r.inertia[0], expected, rtol=1e-14, atol=0)


def test_fracture_data_refuses_too_few_frames():
    with pytest.raises(ValueError, match="at least 3 frames"):
        FractureData(np.ones((2, 4)), np.zeros((2, 4, 2)), np.zeros((2, 4, 2)), 0.1, np.ones(4, bool))
