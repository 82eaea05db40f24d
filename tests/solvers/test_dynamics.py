"""Explicit dynamics: stable time step, Verlet energy conservation O(dt^2), blow-up
detection, damped relaxation to the static solution."""
import re

import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.solvers import (NumericalInstabilityError, critical_time_step, linear_elastic,
                             lumped_mass, stable_time_step, velocity_verlet)


@pytest.fixture(scope="module")
def wave():
    """A free 12 x 8 bond-based plate (192 dofs), density varying in space, and a smooth
    initial bump (zero velocity): an elastic wave problem."""
    p = bp.grid_2d(12, 8, 1.0)
    F = linear_elastic(bp.BondBased(p, bp.find_bonds(p, 3.0)), {"K": 1.0, "delta": 3.0})
    M = lumped_mass(p, 1.0 + p.x[:, 0] / 12)
    r2 = ((p.x - p.x.mean(0)) ** 2).sum(1)
    u0 = torch.zeros(p.n, 2)
    u0[:, 0] = torch.as_tensor(0.01 * np.exp(-r2 / 4))
    return F, M, u0.reshape(-1)


def test_stable_time_step_is_the_verlet_limit(wave):
    """2 / sqrt(lambda_max(M^-1 K)) against a dense eigensolve, times the safety factor."""
    F, M, _ = wave
    s = 1 / np.sqrt(M.numpy())
    lam = np.linalg.eigvalsh(s[:, None] * F.matrix.toarray() * s[None, :]).max()
    assert critical_time_step(F.matrix, M) == pytest.approx(2 / np.sqrt(lam), rel=1e-8)
    assert stable_time_step(F.matrix, M, safety=0.8) == pytest.approx(1.6 / np.sqrt(lam), rel=1e-8)


def test_verlet_energy_error_is_second_order(wave):
    """Kinetic + strain energy over 40 critical steps: the largest deviation from E0 falls 4x
    per halving of dt (Verlet conserves a modified energy O(dt^2) away), and stays below the
    harmonic bound (omega dt)^2 / 4 / (1 - (omega dt)^2 / 4) at omega_max."""
    F, M, u0 = wave
    dt_crit = critical_time_step(F.matrix, M)
    E0 = float(F.energy(u0))
    errors = []
    for fraction in (0.25, 0.125):
        dt = fraction * dt_crit
        tr = velocity_verlet(F, M, u0, dt, int(round(40 / fraction)))
        errors.append(np.abs(tr.energy).max() / E0)
        wdt2 = (2 * fraction) ** 2
        assert errors[-1] < wdt2 / 4 / (1 - wdt2 / 4)
        assert tr.potential[-1] == pytest.approx(float(F.energy(tr.final)) - E0, abs=1e-12 * E0)
    assert errors[0] / errors[1] == pytest.approx(4.0, rel=0.1)


@pytest.mark.parametrize("with_stiffness", [True, False])
def test_verlet_above_the_limit_is_reported(wave, with_stiffness):
    """dt = 1.05 x the limit: the top mode grows geometrically; the run stops with an error
    that names the limit (from the given stiffness or the force's Hessian at u0)."""
    F, M, u0 = wave
    dt_crit = critical_time_step(F.matrix, M)
    with pytest.raises(NumericalInstabilityError, match="reduce dt below") as info:
        velocity_verlet(F, M, u0, 1.05 * dt_crit, 2000, stiffness=F.matrix if with_stiffness else None)
    stated = float(re.search(r"reduce dt below ([0-9.eE+-]+)", str(info.value)).group(1))
    assert stated == pytest.approx(dt_crit, rel=1e-5)


def test_damped_verlet_relaxes_to_the_static_solution():
    """Dynamic relaxation: with damping 2 omega_min a clamped LPS plate (one Dirichlet layer
    prescribed to move) settles on Scene.solve's equilibrium; the energy ends at
    V(u*) - V(0) = -p^T u* / 2 (free dofs, A u* = p) and the kinetic energy at 0."""
    p, delta = bp.grid_2d(10, 6, 1.0), 2.5
    mat = bp.LPS(p, bp.find_bonds(p, delta))
    scene = bp.Scene(mat, [bp.Dirichlet.layer(p, "left", delta), bp.Dirichlet.layer(p, "right", delta, (0.1, None))],
                     [bp.Load(p.box((3, 0), (7, 1)), (0.0, -0.5))])
    params = {"K": 1.0, "G": 0.6}
    c = scene.constraints
    F = linear_elastic(mat, dict(params, delta=delta), load=scene.force, constraints=c)
    M = lumped_mass(p, 1.0, dofs=c.free_dofs)
    s = 1 / np.sqrt(M.numpy())
    omega_min = np.sqrt(np.linalg.eigvalsh(s[:, None] * F.matrix.toarray() * s[None, :]).min())
    tr = velocity_verlet(F, M, torch.zeros(F.n), stable_time_step(F.matrix, M), 600, damping=2 * omega_min)
    u_static = scene.solve({**params, "delta": delta})
    assert (c.expand(tr.final) - u_static).abs().max() < 1e-10 * u_static.abs().max()
    assert tr.energy[-1] == pytest.approx(-0.5 * float(F.load @ c.free(u_static)), rel=1e-9)
    assert tr.kinetic[-1] < 1e-20


def test_bad_inputs_are_refused(wave):
    F, M, u0 = wave
    p = bp.grid_2d(2, 2, 1.0)
    with pytest.raises(ValueError, match="rho"):
        lumped_mass(p, -1.0)
    with pytest.raises(ValueError, match="dt"):
        velocity_verlet(F, M, u0, float("nan"), 10)
    with pytest.raises(ValueError, match="mass"):
        velocity_verlet(F, M[:-1], u0, 0.1, 10)
