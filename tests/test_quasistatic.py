"""Quasi-static loading with bond breaking (You 2023 §5.2): the small-strain limit is the
linear solve, a bar breaks at the load predicted from its elastic stretch, the reaction of a
cut bar is zero, damage is irreversible, detached pieces leave the system non-singular."""
import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.damage import CriticalStretch, DamageODE
from bayespd.solvers.quasistatic import LoadedBody, equilibrium, quasi_static

H, DELTA, U = 1.0, 3.0, 0.1  # spacing, horizon, pull at load factor 1 (mm)
PARAMS = {"K": 1000.0, "G": 600.0, "delta": DELTA}


def bar(cls=bp.BondBased, pull=(U, 0.0)):
    """A 20 x 4 bar clamped on the left, its right layer moved by ``pull``."""
    p = bp.grid_2d(20.0, 4.0, H)
    mat = cls(p, bp.find_bonds(p, DELTA))
    params = {k: PARAMS[k] for k in mat.param_names}
    bcs = [bp.Dirichlet.layer(p, "left", DELTA), bp.Dirichlet.layer(p, "right", DELTA, pull)]
    return mat, params, bcs, LoadedBody(mat, params, bcs)


def crossing(body, x=10.0):
    """Bonds that cross the section at x."""
    xa, xb = body.particles.x[body.bonds.i, 0], body.particles.x[body.bonds.j, 0]
    return torch.as_tensor((np.minimum(xa, xb) < x) & (np.maximum(xa, xb) > x))


def elastic(mat, params, bcs):
    return bp.Scene(mat, bcs, [bp.Load(mat.particles.layer("right", H), (0.0, 0.0))]).solve(params)


@pytest.mark.parametrize("cls", [bp.BondBased, bp.LPS, bp.ConicalBondBased])
def test_small_strain_response_is_the_linear_solve(cls):
    """Before any bond breaks u(lambda) = lambda u_lin + O(lambda^2): at strain ~1e-7 the two
    agree to 1e-8, and the relative deviation grows in proportion to lambda (slope 1)."""
    mat, params, bcs, body = bar(cls)
    u_lin = elastic(mat, params, bcs)
    dev = []
    for lam in (1e-5, 1e-2, 1e-1):
        u = quasi_static(body, [lam], CriticalStretch(1.0)).u
        dev.append(float((u / lam - u_lin).norm() / u_lin.norm()))
    assert dev[0] < 1e-8
    assert 10 * 0.9 < dev[2] / dev[1] < 10 * 1.1, dev


@pytest.mark.parametrize("cls", [bp.BondBased, bp.LPS, bp.ConicalBondBased])
def test_bar_breaks_at_the_predicted_load_and_then_carries_nothing(cls):
    """A weak section (s0 halved across x = 10): the first bond fails at the first load step
    reaching lambda* = min_b s0_b / s_b(u_lin) (1 % slack for the O(strain) nonlinearity); the
    section is then cut through and the reaction falls below 1 % of the peak."""
    mat, params, bcs, body = bar(cls)
    s = body.kinematics.stretch(elastic(mat, params, bcs))
    s0 = torch.full((body.n_bonds,), 0.01)
    s0[crossing(body)] = 0.005
    lam_star = float((s0 / s)[s > 0].min())
    lams = np.linspace(0.02, 1.0, 50)
    res = quasi_static(body, lams, CriticalStretch(s0))
    k = res.first_failure
    assert lams[k - 1] < lam_star * 1.01 and lams[k] > lam_star * 0.99, (lams[k - 1], lam_star, lams[k])
    # the first failure is where the stretch first reaches s0 (elastic solves without damage)
    before, at = (float((body.kinematics.stretch(quasi_static(body, [lam]).u) / s0).max()) for lam in lams[k - 1:k + 1])
    assert before < 1 <= at
    assert bool((res.intact[crossing(body)] == 0).all())
    assert res.peak == k - 1
    assert abs(res.reaction[-1, 0]) < 0.01 * res.reaction[res.peak, 0]
    assert np.all(np.diff(res.broken) >= 0)


def test_damage_is_irreversible_and_unloading_is_elastic():
    """Four weak axial bonds break; unloading to zero and reloading keeps them broken, retraces
    the same (damaged, softer) line, and the reaction vanishes at zero load."""
    mat, params, bcs, body = bar()
    axial = crossing(body) & torch.as_tensor(np.abs(body.bonds.xi[:, 1]) < 1e-9) & \
        torch.as_tensor(body.bonds.length < 1.5)
    assert int(axial.sum()) == 4
    s0 = torch.full((body.n_bonds,), 1.0)
    s0[axial] = 1e-3
    lams = [0.1, 0.4, 0.2, 0.0, 0.2, 0.4]
    res = quasi_static(body, lams, CriticalStretch(s0))
    assert list(res.broken) == [0, 4, 4, 4, 4, 4]
    R = res.reaction[:, 0]
    assert R[2] == pytest.approx(R[4], rel=1e-9)  # unloading and reloading: the same state
    assert R[1] / 0.4 < 0.99 * R[0] / 0.1  # softer after breaking
    assert R[2] / 0.2 == pytest.approx(R[1] / 0.4, rel=1e-3)  # linear up to O(strain)
    assert abs(R[3]) < 1e-8 * R[1]


def test_force_control_stops_when_the_loaded_piece_comes_loose():
    """Force-controlled bar: the weak section fails at the predicted load, the loaded piece
    separates, and the run stops there; the reaction is the applied load before that."""
    p = bp.grid_2d(20.0, 4.0, H)
    mat = bp.BondBased(p, bp.find_bonds(p, DELTA))
    load = bp.Load(p.layer("right", DELTA), (20.0, 0.0))
    body = LoadedBody(mat, {"K": 1000.0, "delta": DELTA}, [bp.Dirichlet.layer(p, "left", DELTA)], [load])
    s = body.kinematics.stretch(quasi_static(body, [1e-3]).u) / 1e-3
    s0 = torch.full((body.n_bonds,), 0.01)
    s0[crossing(body)] = 0.005
    lam_star = float((s0 / s)[s > 0].min())
    lams = np.linspace(0.05, 2.0, 40)
    res = quasi_static(body, lams, CriticalStretch(s0))
    assert res.separated and len(res.load_factors) < len(lams)
    k = len(res.load_factors) - 1
    assert lams[k - 1] < lam_star * 1.01 and lams[k] > lam_star * 0.99
    assert res.reaction[0, 0] == pytest.approx(20.0 * lams[0], rel=1e-9)


@pytest.mark.parametrize("eps", [0.0, 1.0])
def test_a_detached_particle_leaves_the_system_nonsingular(eps):
    """A free particle whose bonds are all broken: eps = 0 drops its dofs (it keeps its
    displacement), eps > 0 keeps them (confinement, Dodwell 2019 eq 3: it returns to 0)."""
    mat, params, bcs, body = bar()
    body = LoadedBody(mat, params, bcs, eps=eps)
    k = int(np.flatnonzero(body.particles.box([9, 1], [11, 3]))[0])
    intact = torch.ones(body.n_bonds)
    intact[torch.as_tensor((body.bonds.i == k) | (body.bonds.j == k))] = 0.0
    active = body.active(intact)
    assert (2 * k in active) == (eps > 0)
    assert len(active) == len(body.constraints.free_dofs) - (0 if eps else 2)
    u, _ = equilibrium(body, body.move(torch.zeros(body.particles.n, 2), 0.5), 0.5, intact,
                       body.tangent(intact, active), active)
    assert float(u[k].abs().max()) == 0.0
    assert float(body.residual(u, 0.5, intact).view(-1)[torch.as_tensor(active)].norm()) < 1e-8


def test_the_damage_ode_is_refused():
    *_, body = bar()
    with pytest.raises(TypeError, match="rate-dependent"):
        quasi_static(body, [0.1], DamageODE(k=1.0, alpha0=0.9))


@pytest.mark.parametrize("flip", [False, True])
def test_a_bond_listed_twice_is_refused(flip):
    """The same pair twice (as i, j or as j, i) would count its stiffness twice."""
    p = bp.grid_2d(6.0, 4.0, H)
    b = bp.find_bonds(p, DELTA)
    i, j = (b.j[:1], b.i[:1]) if flip else (b.i[:1], b.j[:1])
    twice = bp.Bonds(np.r_[b.i, i], np.r_[b.j, j], np.r_[b.xi, np.asarray(p.x[j] - p.x[i])],
                     np.r_[b.length, b.length[:1]], b.h, b.delta_max, b.rule)
    body = LoadedBody(bp.BondBased(p, twice), {"K": 1000.0, "delta": DELTA},
                      [bp.Dirichlet.layer(p, "left", DELTA), bp.Dirichlet.layer(p, "right", DELTA, (U, 0.0))])
    with pytest.raises(ValueError, match="listed twice"):
        body.operator(torch.ones(body.n_bonds), body.constraints.free_dofs)
