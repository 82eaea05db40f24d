"""Stochastic fracture (Dodwell 2019 eq 4 with damage): the noise -> 0 limit is the quasi-static
path, a seed reproduces its run bit for bit, large noise makes paths differ, and the
rate-dependent damage ODE breaks a bond when its damage clock predicts."""
import numpy as np
import pytest
import scipy.sparse.linalg as sla
import torch

import bayespd as bp
from bayespd.damage import CriticalStretch, DamageODE
from bayespd.solvers import karhunen_loeve, white_noise
from bayespd import bond_loops
from bayespd.solvers import fracture
from bayespd.solvers.fracture import StochasticFracture
from bayespd.solvers.quasistatic import quasi_static

SIDE, H, DELTA, S0 = 20.0, 1.0, 3.0, 0.01
LAMS = np.linspace(0.02, 0.7, 35)  # top layer pulled by 0.2 lambda mm
PARAMS = {"K": 1000.0, "delta": DELTA}


def notched(damage=CriticalStretch(S0), noise=None) -> bp.Scene:
    """A 20 x 20 bond-based plate notched from the left edge to the centre, bottom clamped,
    top pulled (mode I)."""
    p = bp.grid_2d(SIDE, SIDE, H)
    bonds = bp.precrack(p, bp.find_bonds(p, DELTA), [[0.0, SIDE / 2], [SIDE / 2, SIDE / 2]])
    bcs = [bp.Dirichlet.layer(p, "bottom", DELTA), bp.Dirichlet.layer(p, "top", DELTA, (0.0, 0.2))]
    return bp.Scene(bp.BondBased(p, bonds), bcs, damage=damage, noise=noise)


@pytest.fixture(scope="module")
def plate():
    """The notched plate at PARAMS (``Scene.at``)."""
    return notched().at(PARAMS)


@pytest.fixture(scope="module")
def deterministic():
    return quasi_static(notched(), PARAMS, LAMS)


def driver(sigma, mobility=1e3, noise=None, damage=CriticalStretch(S0)):
    """C = sigma^2 I (or ``noise``), eta = sigma^2 / mobility: the drift eta^-1 C grad V keeps
    its rate as sigma changes, the noise scales with sigma."""
    scene = notched(damage, noise or (lambda dofs: white_noise(sigma, len(dofs))))
    return StochasticFracture(scene, PARAMS, eta=sigma**2 / mobility)


@pytest.mark.parametrize("tangent, spare", [("exact", 0.0), ("lagged", 0.01)])
def test_vanishing_noise_follows_the_quasi_static_path(plate, deterministic, tangent, spare):
    """sigma = 1e-6 at mobility M with M dt lambda_min(A) ~ 1e4 >> 1: each step is one Newton
    step plus a random force of size sqrt(2/dt) sigma / M ~ 1e-9, so first failure and peak
    load fall within one load step of the quasi-static run and the damage is the same. With
    the lagged tangent a step is one chord step, which leaves a residual of about the
    geometric fraction max(e/r) ~ s0 of the increment: bonds within that of their critical
    stretch may break one step apart, and the count of broken bonds moves by ``spare``."""
    intact = torch.ones(plate.n_bonds)
    lam_min = sla.eigsh(plate.operator(intact, plate.active(intact)), k=1, sigma=0, return_eigenvectors=False)[0]
    assert 1e3 * lam_min > 1e4
    run = driver(1e-6).run(LAMS, dt=1.0, seed=0, tangent=tangent)
    qs = deterministic
    assert abs(run.load_factor[run.first_failure] - LAMS[qs.first_failure]) <= LAMS[1] - LAMS[0] + 1e-12
    assert abs(run.load_factor[run.peak] - LAMS[qs.peak]) <= LAMS[1] - LAMS[0] + 1e-12
    assert np.array_equal(run.phi > 0.4, qs.damage[-1] > 0.4)
    assert abs(run.broken[-1] - qs.broken[-1]) <= spare * qs.broken[-1]
    assert np.abs(run.path[:, 1] - SIDE / 2).max() <= H  # the straight crack of mode I
    assert run.crack_length[-1] >= SIDE / 2 - 2 * H  # through the ligament
    assert np.all(np.diff(run.crack_length[run.broken > 0]) >= -2 * H)


def test_the_lagged_tangent_converges_to_the_same_equilibrium(plate):
    """Below the critical stretch, at one load factor held for 25 steps of vanishing noise:
    both operators iterate to the nonlinear equilibrium of ``quasi_static`` (the W-method
    has the fixed points of the exact scheme), to 1e-9 of |u|; an unknown tangent is refused."""
    lam = 0.3
    qs = quasi_static(notched(None), PARAMS, [lam])
    frac = driver(1e-9, damage=CriticalStretch(1.0))
    for tangent in ("exact", "lagged"):
        run = frac.run([lam] * 25, dt=1.0, seed=0, tangent=tangent, hold=False)
        assert run.broken[-1] == 0
        assert float((run.u - qs.u).abs().max()) <= 1e-9 * float(qs.u.abs().max())
    with pytest.raises(ValueError, match="lagged"):
        frac.run([lam], dt=1.0, seed=0, tangent="secant")


def test_a_seed_reproduces_its_run_and_noise_changes_the_path(plate):
    """White noise large enough to deflect the crack: the same seed gives bit-identical
    results, another seed a different damage field. Without hold the ramp advances every
    step."""
    lams = LAMS[::2]
    frac = driver(100.0)
    a, b, c = frac.run(lams, 1.0, seed=3), frac.run(lams, 1.0, seed=3), frac.run(lams, 1.0, seed=4)
    assert torch.equal(a.u, b.u) and np.array_equal(a.phi, b.phi) and np.array_equal(a.path, b.path)
    assert not np.array_equal(a.phi > 0.4, c.phi > 0.4)
    free = frac.run(lams, 1.0, seed=torch.Generator().manual_seed(3), hold=False)
    assert np.array_equal(free.load_factor, lams) and free.seed is None


def test_correlated_noise_runs_and_is_checked(plate):
    """Karhunen-Loeve noise on the free dofs (with a nugget, so C is positive definite and the
    drift reaches every dof); a covariance on the wrong dofs is refused."""
    free = plate.constraints.free_dofs
    kl = karhunen_loeve(plate.particles.x, 1e-6, length=3.0, rank=20, nugget=1.0, dofs=free)
    run = driver(1e-6, noise=lambda dofs: kl).run(LAMS[::2], dt=1.0, seed=0)
    assert run.broken[-1] > 0 and np.abs(run.path[:, 1] - SIDE / 2).max() <= H
    with pytest.raises(ValueError, match="free dofs"):
        driver(1.0, noise=lambda dofs: white_noise(1.0, plate.particles.n * 2))


def test_damage_ode_breaks_when_its_clock_runs_out():
    """Damage ODE of Dodwell 2019 §2.1 (logistic, lam = exp(-k s_c)): z = logit(alpha) falls by
    tau = sum_n exp(k (s_n - s_c)) dt, so the most stretched bond of a bar (s_n = lambda_n
    s_1 from the elastic solve, the others barely damaged) breaks at the first step with
    tau > logit(alpha0). The driver (vanishing noise) breaks its first bond at that step."""
    p = bp.grid_2d(20.0, 4.0, H)
    bcs = [bp.Dirichlet.layer(p, "left", DELTA), bp.Dirichlet.layer(p, "right", DELTA, (0.1, 0.0))]
    k, s_c, alpha0 = 2000.0, 0.005, 0.999
    law = DamageODE(k=k, alpha0=alpha0, lam=np.exp(-k * s_c))
    scene = bp.Scene(bp.BondBased(p, bp.find_bonds(p, DELTA)), bcs, damage=law,
                     noise=lambda dofs: white_noise(1e-6, len(dofs)))
    body = scene.at(PARAMS)
    s1 = float(body.kinematics.stretch(quasi_static(bp.Scene(scene.material, bcs), PARAMS, [1e-3]).u).max()) / 1e-3
    lams = np.linspace(0.02, 1.0, 50)
    tau = np.cumsum(np.exp(k * (lams * s1 - s_c)))
    predicted = lams[np.argmax(tau > np.log(alpha0 / (1 - alpha0)))]
    frac = StochasticFracture(scene, PARAMS, eta=1e-15)
    run = frac.run(lams, dt=1.0, seed=0)
    assert run.load_factor[run.first_failure] == pytest.approx(predicted, abs=1e-12)


def test_a_body_that_came_loose_everywhere_has_nothing_to_solve():
    """Every bond broken (eps = 0): no dof is solved for, no operator is made, and a step
    leaves u as it is."""
    frac = driver(1.0)
    plate = frac.body
    u = 0.01 * torch.ones(plate.particles.n, 2)
    gone = frac._factorised(torch.zeros(plate.n_bonds), u, 512, None, plate.floating_pieces())
    assert gone.A is None and len(gone.active) == 0
    step, A = frac._stepper(torch.zeros(plate.n_bonds), u, gone, exact=False)
    assert A is None and torch.equal(step(u, 0.5, torch.zeros(plate.n_bonds), 1.0, torch.Generator()), u)


@pytest.mark.parametrize("compiled", [True, False])
def test_the_tally_of_a_damage_update(monkeypatch, compiled):
    """What the run reads after each damage update (largest move of an intact fraction since
    the operator followed them, the broken mask, its count, whether it changed), compiled
    or by torch: exact on fractions that cross 1/2, stay put, or sit on 1/2 itself."""
    monkeypatch.setattr(bond_loops, "ENABLED", compiled)
    operated = torch.tensor([1.0, 1.0, 0.0, 0.7, 0.5, 0.2])
    intact = torch.tensor([1.0, 0.3, 0.0, 0.45, 0.5, 0.2])
    before = operated < 0.5
    moved, broken, count, differs = fracture._tally(intact, operated, before)
    assert moved == pytest.approx(0.7, abs=1e-15) and count == 4 and differs
    assert broken.tolist() == [False, True, True, True, False, True]
    moved, again, count, differs = fracture._tally(intact, intact, broken)
    assert (moved, count, differs) == (0.0, 4, False) and torch.equal(again, broken)
