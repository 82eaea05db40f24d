"""Damage laws (sharp, smoothed, ODE), the damage index and crack geometry."""
import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

import bayespd as bp
from bayespd import bond_loops
from bayespd.damage import (CriticalStretch, DamageODE, SmoothStep, broken, crack_length,
                            crack_path, damage_index)
from bayespd.nonlinear import NonlinearBonds


def run(law, history, dt=None):
    state = law.init(len(history[0]))
    out = []
    for s in history:
        state = law.update(state, torch.as_tensor(s, dtype=torch.float64), dt)
        out.append(law.intact(state))
    return torch.stack(out)


def test_critical_stretch_is_irreversible():
    s0 = 0.01
    # bond 0 stays below s0; bond 1 goes above, then back (and into compression); bond 2 hits s0
    history = [[0.005, 0.005, 0.0], [0.009, 0.012, 0.01], [0.0, 0.002, 0.0], [0.0, -0.01, 0.0]]
    mu = run(CriticalStretch(s0), history)
    expected = [[1, 1, 1], [1, 0, 0], [1, 0, 0], [1, 0, 0]]
    assert torch.equal(mu, torch.tensor(expected, dtype=mu.dtype))
    assert torch.equal(broken(mu[-1]), torch.tensor([False, True, True]))


def test_critical_stretch_from_displacement():
    """Two particles pulled apart past s0 and released: the bond stays broken."""
    p = bp.from_points([[0.0, 0.0], [1.0, 0.0]], [1.0, 1.0], h=1.0)
    nl = NonlinearBonds(bp.BondBased(p, bp.find_bonds(p, 1.0)))
    law = CriticalStretch(0.05)
    state = law.init(1)
    for pull in (0.03, 0.06, 0.0):
        state = law.update(state, nl.stretch(torch.tensor([[0.0, 0.0], [pull, 0.0]])))
    assert float(state) == pytest.approx(0.06, abs=1e-15)
    assert float(law.intact(state)) == 0.0


def test_smooth_step_derivative_and_sharp_limit():
    S = torch.tensor([-0.01, 0.008, 0.0099, 0.0101, 0.013])
    s0, eta = torch.tensor(0.01, requires_grad=True), 0.002
    gamma = SmoothStep(s0, eta).intact(S)
    (dgamma,) = torch.autograd.grad(gamma.sum(), s0)
    analytic = (1 / (2 * eta) / torch.cosh((S - 0.01) / eta) ** 2).sum()
    fd = (SmoothStep(0.01 + 1e-7, eta).intact(S) - SmoothStep(0.01 - 1e-7, eta).intact(S)).sum() / 2e-7
    assert float(dgamma) == pytest.approx(float(analytic), rel=1e-12)
    assert float(dgamma) == pytest.approx(float(fd), rel=1e-7)
    # eta -> 0: |gamma - sharp| = (1 - tanh(d/eta))/2 <= exp(-2 d / eta) at distance d from s0
    sharp = CriticalStretch(0.01).intact(S)
    d = (S - 0.01).abs()
    for eta in (1e-3, 1e-4, 1e-5):
        err = (SmoothStep(0.01, eta).intact(S) - sharp).abs()
        assert torch.all(err <= torch.exp(-2 * d / eta) * (1 + 1e-6))  # 1 - tanh cancels
    assert float((SmoothStep(0.01, 1e-5).intact(S) - sharp).abs().max()) < 1e-8


def test_smooth_step_is_irreversible_and_differentiable_in_eta():
    mu = run(SmoothStep(0.01, 0.001), [[0.0], [0.02], [0.0]])
    assert float(mu[1]) == float(mu[2]) < 1e-8
    state = torch.tensor([0.004, 0.011, 0.02])
    assert torch.autograd.gradcheck(lambda s0, eta: SmoothStep(s0, eta).intact(state),
                                    (torch.tensor(0.01, requires_grad=True),
                                     torch.tensor(0.003, requires_grad=True)))


def logistic(alpha0, tau):
    return alpha0 / (alpha0 + (1 - alpha0) * np.exp(tau))


def test_damage_ode_logistic_exact_for_any_step():
    """n = m = 1 at constant stretch: the update is the closed form, whatever dt."""
    k, lam, a0 = 40.0, 0.3, 0.99
    s = torch.tensor([0.0, 0.01, 0.05])
    law = DamageODE(k=k, alpha0=a0, lam=lam)
    mu = run(law, [s] * 7, dt=0.9)[-1]
    exact = logistic(a0, lam * np.exp(k * s.numpy()) * 6.3)
    np.testing.assert_allclose(mu.numpy(), exact, rtol=1e-13)


def test_damage_ode_first_order_for_varying_stretch():
    """s = a t: tau = lam (e^(k a t) - 1)/(k a); the end-of-step stretch gives O(dt)."""
    k, lam, a0, a, T = 20.0, 1.0, 0.999, 0.05, 2.0  # tau(T) = e^2 - 1: alpha(T) ~ 0.5
    exact = logistic(a0, lam * np.expm1(k * a * T) / (k * a))
    errors = []
    for steps in (100, 200, 400):
        dt = T / steps
        history = [[a * dt * (q + 1)] for q in range(steps)]
        errors.append(abs(float(run(DamageODE(k=k, alpha0=a0, lam=lam), history, dt)[-1]) - exact))
    slopes = np.diff(np.log(errors)) / np.diff(np.log([100, 200, 400]))
    np.testing.assert_allclose(slopes, -1.0, atol=0.05)


def test_damage_ode_general_exponents_fourth_order():
    """n = 2, m = 1.5 against a tight reference: the RK4 error falls with slope -4."""
    k, lam, a0, s, T, steps = 50.0, 0.5, 0.9, 0.02, 3.0, 6
    rate = lam * np.exp(k * s)
    ref = solve_ivp(lambda t, a: -rate * a**2 * (1 - a) ** 1.5, (0, T), [a0], method="DOP853",
                    rtol=1e-13, atol=1e-15).y[0, -1]
    subs = [1, 2, 4, 8]
    errors = []
    for sub in subs:
        law = DamageODE(k=k, alpha0=a0, lam=lam, n=2.0, m=1.5, substeps=sub)
        errors.append(abs(float(run(law, [[s]] * steps, T / steps)[-1]) - ref))
    slopes = np.diff(np.log(errors)) / np.diff(np.log(subs))
    np.testing.assert_allclose(slopes, -4.0, atol=0.1)


def test_damage_ode_monotone_and_bounded_for_huge_steps():
    """lam e^(k s) dt up to 5e22: z stays finite and non-increasing (the rate underflows to 0
    far out), alpha in [0, 1) (0 only by underflow of sigmoid(z))."""
    law = DamageODE(k=100.0, alpha0=0.9, n=3.0, m=0.5, substeps=1)
    z = law.init(3)
    history = [z]
    for _ in range(5):
        z = law.update(z, torch.tensor([0.0, 0.1, 0.5]), 10.0)
        history.append(z)
    z = torch.stack(history)
    assert torch.all(torch.isfinite(z)) and torch.all(z[1:] <= z[:-1]) and torch.all(z[1] < z[0])
    mu = law.intact(z)
    assert torch.all((mu >= 0) & (mu < 1)) and float(mu[-1, 0]) > 0


def test_damage_ode_gradient_in_k_and_lam():
    s = torch.tensor([0.0, 0.01, 0.03])

    def alpha(k, lam):
        law = DamageODE(k=k, alpha0=0.95, lam=lam, n=1.5, m=2.0)
        return law.intact(law.update(law.update(law.init(3), s, 0.2), 2 * s, 0.2))

    assert torch.autograd.gradcheck(alpha, (torch.tensor(30.0, requires_grad=True),
                                            torch.tensor(0.7, requires_grad=True)))


def test_damage_ode_refuses_bad_input():
    with pytest.raises(ValueError, match="rest point"):
        DamageODE(k=1.0, alpha0=1.0)
    with pytest.raises(ValueError, match="finite time"):
        DamageODE(k=1.0, alpha0=0.9, n=0.5)
    with pytest.raises(ValueError, match="time step"):
        DamageODE(k=1.0, alpha0=0.9).update(torch.zeros(2), torch.zeros(2))


def intact_after_precrack(p, bonds, crack):
    kept = bp.precrack(p, bonds, crack)
    keep = set(zip(kept.i.tolist(), kept.j.tolist()))
    return torch.tensor([float((a, b) in keep) for a, b in zip(bonds.i.tolist(), bonds.j.tolist())])


@pytest.mark.parametrize("compiled", [True, False])
def test_damage_index_by_hand(monkeypatch, compiled):
    """h = 1, search radius 1.5: 8 neighbours, 3 of them across a full-width line
    (2 of 5 at the side columns): phi = 3/8 and 2/5 beside the line, 0 elsewhere (by the
    compiled pass and by torch)."""
    monkeypatch.setattr(bond_loops, "ENABLED", compiled)
    p = bp.grid_2d(8.0, 6.0, 1.0)
    bonds = bp.find_bonds(p, 1.0)
    mu = intact_after_precrack(p, bonds, [[-1.0, 3.0], [9.0, 3.0]])
    phi = damage_index(p, bonds, mu)
    x, y = p.x[:, 0], p.x[:, 1]
    beside = np.abs(y - 3.0) == 0.5
    side = (x == 0.5) | (x == 7.5)
    expected = np.where(beside, np.where(side, 2 / 5, 3 / 8), 0.0)
    np.testing.assert_allclose(phi.numpy(), expected, rtol=0, atol=1e-15)


def test_damage_index_independent_count_with_partial_volumes():
    """Edge crack to the middle, delta = 2.7 with partial-volume weights: compare with a
    brute-force loop over all pairs and a segment-intersection test written here."""
    p = bp.grid_2d(12.0, 8.0, 1.0)
    delta, c0, c1 = 2.7, np.array([-1.0, 4.0]), np.array([6.2, 4.0])
    bonds = bp.find_bonds(p, 3.0)
    mat = bp.BondBased(p, bonds)
    mu = intact_after_precrack(p, bonds, [c0, c1])
    phi = damage_index(p, bonds, mu, mat.bond_weight({"delta": delta}))

    def crosses(a, b):  # solve a + s (b - a) = c0 + t (c1 - c0) for s, t in (0, 1)
        M = np.column_stack([b - a, c0 - c1])
        if abs(np.linalg.det(M)) < 1e-12:
            return False
        s, t = np.linalg.solve(M, c0 - a)
        return 0 < s < 1 and 0 <= t <= 1

    expected = np.zeros(p.n)
    for q in range(p.n):
        total = cut = 0.0
        for r in range(p.n):
            dist = np.linalg.norm(p.x[r] - p.x[q])
            w = np.clip((delta + 0.5 - dist) / 1.0, 0.0, 1.0) if r != q else 0.0
            total += w * p.volume[r]
            cut += w * p.volume[r] * crosses(p.x[q], p.x[r])
        expected[q] = cut / total
    assert expected.max() > 0.3
    np.testing.assert_allclose(phi.numpy(), expected, rtol=0, atol=1e-13)


@pytest.fixture(scope="module")
def plate():
    return bp.grid_2d(40.0, 20.0, 1.0)


def test_crack_path_straight_band(plate):
    p = plate
    phi = np.where((p.x[:, 0] < 25.0) & (np.abs(p.x[:, 1] - 10.0) < 2.0), 1.0, 0.0)
    phi[(p.x[:, 0] > 34) & (p.x[:, 1] > 17)] = 1.0  # a small separate cluster is ignored
    path = crack_path(p, phi)
    np.testing.assert_allclose(path[:, 1], 10.0, atol=1e-12)
    assert np.all(np.diff(path[:, 0]) > 0) or np.all(np.diff(path[:, 0]) < 0)
    assert abs(crack_length(path) - 25.0) <= p.h
    np.testing.assert_allclose(sorted([path[0, 0], path[-1, 0]]), [0.0, 25.0], atol=p.h)


@pytest.mark.parametrize("angle", [30.0, 60.0])
def test_crack_path_slanted_band(plate, angle):
    """A band of half-width 1.5h and length 16h at an angle: the path follows the line
    (points within 0.75h), its principal direction within 1 degree, its length within h."""
    p = plate
    a = np.deg2rad(angle)
    d, n = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
    x0, L = np.array([7.3, 2.1]), 16.0
    t, s = (p.x - x0) @ d, (p.x - x0) @ n
    phi = np.where((t >= 0) & (t <= L) & (np.abs(s) < 1.5), 0.9, 0.0)
    path = crack_path(p, phi)
    assert np.abs((path - x0) @ n).max() < 0.75 * p.h
    c = path - path.mean(axis=0)
    axis = np.linalg.eigh(c.T @ c)[1][:, -1]
    assert np.rad2deg(np.arctan2(axis[1], axis[0])) % 180 == pytest.approx(angle, abs=1.0)
    assert abs(crack_length(path) - L) <= p.h


def test_crack_path_from_precrack_damage(plate):
    """phi of a pre-crack along y = 10 from x = 0 to 25: the path lies on the crack line and
    ends within h of the tip (particles beyond the tip keep phi < 0.4)."""
    p = plate
    bonds = bp.find_bonds(p, 3.0)
    mu = intact_after_precrack(p, bonds, [[-1.0, 10.0], [25.0, 10.0]])
    phi = damage_index(p, bonds, mu, bp.BondBased(p, bonds).bond_weight({"delta": 3.0}))
    path = crack_path(p, phi)
    np.testing.assert_allclose(path[:, 1], 10.0, atol=1e-12)
    assert abs(max(path[0, 0], path[-1, 0]) - 25.0) <= p.h
    assert abs(min(path[0, 0], path[-1, 0]) - 0.0) <= 1e-12


def test_damage_index_gradient_and_damaged_bonds_only():
    """The index over the damaged bonds only (no gradient wanted) equals the one over every
    bond (mu requires a gradient) to rounding, and d phi_i / d mu_b = -V_j / sum_j V_j for
    each bond b = (i, j) of particle i (here the gradient of sum_i c_i phi_i)."""
    p = bp.grid_2d(8.0, 6.0, 1.0)
    bonds = bp.find_bonds(p, 2.0)
    mu = torch.ones(bonds.n)
    mu[::7] = torch.linspace(0.0, 0.9, len(mu[::7]))
    plain = damage_index(p, bonds, mu)
    wanted = mu.clone().requires_grad_(True)
    phi = damage_index(p, bonds, wanted)
    np.testing.assert_allclose(phi.detach().numpy(), plain.numpy(), rtol=0, atol=1e-15)
    c = torch.linspace(1.0, 2.0, p.n, dtype=torch.float64)
    (grad,) = torch.autograd.grad((c * phi).sum(), wanted)
    V = torch.as_tensor(p.volume)
    i, j = torch.as_tensor(bonds.i), torch.as_tensor(bonds.j)
    total = torch.zeros(p.n, dtype=V.dtype).index_add(0, i, V[j]).index_add(0, j, V[i])
    expected = -(c[i] * V[j] / total[i] + c[j] * V[i] / total[j])
    np.testing.assert_allclose(grad.numpy(), expected.numpy(), rtol=1e-13)
