"""Quasi-static loading with bond breaking (You 2023 §5.2): the small-strain limit is the
linear solve, a bar breaks at the load predicted from its elastic stretch, the reaction of a
cut bar is zero, damage is irreversible; one Scene serves the static solve, quasi-static
loading and stochastic fracture."""
import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.damage import CriticalStretch, DamageODE
from bayespd.solvers import white_noise
from bayespd.solvers.fracture import StochasticFracture
from bayespd.solvers.quasistatic import quasi_static

H, DELTA, U = 1.0, 3.0, 0.1  # spacing, horizon, pull at load factor 1 (mm)
PARAMS = {"K": 1000.0, "G": 600.0, "delta": DELTA}


def bar(cls=bp.BondBased, pull=(U, 0.0)):
    """A 20 x 4 bar clamped on the left, its right layer moved by ``pull``: (material, params,
    Dirichlet regions, the body at params)."""
    p = bp.grid_2d(20.0, 4.0, H)
    mat = cls(p, bp.find_bonds(p, DELTA))
    params = {k: PARAMS[k] for k in mat.param_names}
    bcs = [bp.Dirichlet.layer(p, "left", DELTA), bp.Dirichlet.layer(p, "right", DELTA, pull)]
    return mat, params, bcs, bp.Scene(mat, bcs).at(params)


def crossing(body, x=10.0):
    """Bonds that cross the section at x."""
    xa, xb = body.particles.x[body.bonds.i, 0], body.particles.x[body.bonds.j, 0]
    return torch.as_tensor((np.minimum(xa, xb) < x) & (np.maximum(xa, xb) > x))


def elastic(mat, params, bcs):
    return bp.Scene(mat, bcs).solve(params)


def loading(mat, params, bcs, lams, damage=None, **kw):
    """``quasi_static`` of the scene of ``mat`` and ``bcs`` with ``damage``."""
    return quasi_static(bp.Scene(mat, bcs, damage=damage), params, lams, **kw)


@pytest.mark.parametrize("cls", [bp.BondBased, bp.LPS, bp.ConicalBondBased])
def test_small_strain_response_is_the_linear_solve(cls):
    """Before any bond breaks u(lambda) = lambda u_lin + O(lambda^2): at strain ~1e-7 the two
    agree to 1e-8, and the relative deviation grows in proportion to lambda (slope 1)."""
    mat, params, bcs, body = bar(cls)
    u_lin = elastic(mat, params, bcs)
    dev = []
    for lam in (1e-5, 1e-2, 1e-1):
        u = loading(mat, params, bcs, [lam], CriticalStretch(1.0)).u
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
    res = loading(mat, params, bcs, lams, CriticalStretch(s0))
    k = res.first_failure
    assert lams[k - 1] < lam_star * 1.01 and lams[k] > lam_star * 0.99, (lams[k - 1], lam_star, lams[k])
    # the first failure is where the stretch first reaches s0 (elastic solves without damage)
    before, at = (float((body.kinematics.stretch(loading(mat, params, bcs, [lam]).u) / s0).max())
                  for lam in lams[k - 1:k + 1])
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
    res = loading(mat, params, bcs, lams, CriticalStretch(s0))
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
    params, bcs = {"K": 1000.0, "delta": DELTA}, [bp.Dirichlet.layer(p, "left", DELTA)]
    body = bp.Scene(mat, bcs, [load]).at(params)
    s = body.kinematics.stretch(quasi_static(bp.Scene(mat, bcs, [load]), params, [1e-3]).u) / 1e-3
    s0 = torch.full((body.n_bonds,), 0.01)
    s0[crossing(body)] = 0.005
    lam_star = float((s0 / s)[s > 0].min())
    lams = np.linspace(0.05, 2.0, 40)
    res = quasi_static(bp.Scene(mat, bcs, [load], damage=CriticalStretch(s0)), params, lams)
    assert res.separated and len(res.load_factors) < len(lams)
    k = len(res.load_factors) - 1
    assert lams[k - 1] < lam_star * 1.01 and lams[k] > lam_star * 0.99
    assert res.reaction[0, 0] == pytest.approx(20.0 * lams[0], rel=1e-9)


def test_the_damage_ode_is_refused():
    mat, params, bcs, _ = bar()
    with pytest.raises(TypeError, match="rate-dependent"):
        loading(mat, params, bcs, [0.1], DamageODE(k=1.0, alpha0=0.9))


def test_a_scene_without_damage_allocates_no_damage_state():
    """Nonlinear elasticity: no law, no state, every bond intact, nothing broken."""
    mat, params, bcs, _ = bar()
    scene = bp.Scene(mat, bcs)
    res = quasi_static(scene, params, [0.1, 0.5])
    assert scene.damage is None and res.state is None
    assert bool((res.intact == 1).all()) and list(res.broken) == [0, 0]


def test_one_scene_serves_the_static_solve_quasi_static_loading_and_fracture():
    """One Scene (the bar pulled at its end and pushed sideways along its top) with damage and
    noise: ``solve`` is differentiable (its K-derivative agrees with a central difference); the
    first quasi-static step is the static solve to O(lambda^2): the difference quadruples when
    lambda doubles (slope 2); the fracture driver at vanishing noise, holding that load,
    settles on the quasi-static u."""
    mat, params, bcs, _ = bar()
    scene = bp.Scene(mat, bcs, [bp.Load(mat.particles.layer("top", H), (0.0, 5.0))],
                     damage=CriticalStretch(0.01), noise=lambda dofs: white_noise(1e-9, len(dofs)))
    w = torch.randn(mat.particles.n, 2, generator=torch.Generator().manual_seed(0))
    K = torch.tensor(params["K"], requires_grad=True)
    (dK,) = torch.autograd.grad((scene.solve({**params, "K": K}) * w).sum(), K)
    step = 1e-3 * params["K"]
    fd = [float((scene.solve({**params, "K": params["K"] + s}) * w).sum()) for s in (step, -step)]
    assert float(dK) == pytest.approx((fd[0] - fd[1]) / (2 * step), rel=1e-5)
    u_lin = scene.solve(params)
    lams = (0.02, 0.04)
    diffs = [float((quasi_static(scene, params, [lam]).u - lam * u_lin).norm()) for lam in lams]
    slope = np.log(diffs[1] / diffs[0]) / np.log(lams[1] / lams[0])
    assert 1.9 < slope < 2.1, (diffs, slope)
    assert diffs[0] < 1e-2 * lams[0] * float(u_lin.norm())
    assert scene.at(params).constraints is scene.constraints
    with pytest.raises(ValueError, match="missing"):
        scene.at({"K": 1000.0})
    qs = quasi_static(scene, params, [lams[0]])
    run = StochasticFracture(scene, params, eta=1e-18 / 1e3).run([lams[0]] * 25, dt=1.0, seed=0, hold=False)
    assert run.broken[-1] == 0
    assert float((run.u - qs.u).abs().max()) <= 1e-9 * float(qs.u.abs().max())


def test_a_scene_refuses_what_it_cannot_solve():
    """No load and no prescribed displacement; noise that is not a callable; fracture
    without noise or without damage: each refusal names the fix."""
    mat, params, bcs, _ = bar()
    with pytest.raises(ValueError, match="non-zero value"):
        bp.Scene(mat, bcs[:1])
    with pytest.raises(ValueError, match="lambda dofs"):
        bp.Scene(mat, bcs, noise=white_noise(1.0, 10))
    with pytest.raises(ValueError, match="noise=lambda dofs"):
        StochasticFracture(bp.Scene(mat, bcs, damage=CriticalStretch(0.01)), params, eta=1.0)
    with pytest.raises(ValueError, match="damage=CriticalStretch"):
        StochasticFracture(bp.Scene(mat, bcs, noise=lambda dofs: white_noise(1.0, len(dofs))), params, eta=1.0)
    with pytest.raises(ValueError, match="free dofs"):
        StochasticFracture(bp.Scene(mat, bcs, damage=CriticalStretch(0.01),
                                    noise=lambda dofs: white_noise(1.0, 2 * mat.particles.n)), params, eta=1.0)
