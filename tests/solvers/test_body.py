"""``bayespd.solvers.body.LoadedBody`` (``Scene.at(params)``): prescribed dofs moved by the load
factor, reactions as the sum of minus the internal force on the loaded particles, the dofs
solved for (a detached piece dropped when eps = 0, kept when eps > 0), the bond-based tangent
as the Hessian of the bond energy in tension, and the change of operator after bonds break
as the difference of the assembled operators."""
import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd import bond_loops
from bayespd.solvers.quasistatic import equilibrium
from tests.conftest import plate_scene
from tests.linalg.test_woodbury import body, broken
from tests.solvers.test_quasistatic import DELTA, H, U, bar


@pytest.fixture(scope="module")
def plate():
    return body()


def pmb_plate(eps=0.0):
    """The conftest plate (clamped left, loaded right by (30, 10)), bond-based, with eps."""
    sc = plate_scene(material="pmb")
    return bp.Scene(sc.material, sc.dirichlet, sc.loads, eps=eps).at({"K": 1000.0, "delta": 2.5})


def test_move_sets_the_prescribed_dofs_and_keeps_the_free_ones():
    *_, b = bar(pull=(U, None))  # the right layer moves along x only: y stays free there
    u = torch.randn(b.particles.n, 2, generator=torch.Generator().manual_seed(0))
    moved = b.move(u, 0.7)
    c = b.constraints
    fixed = torch.as_tensor(~c.free_mask).view(b.particles.n, 2)
    assert torch.equal(moved[~fixed], u[~fixed])
    assert torch.equal(moved[fixed], 0.7 * c.prescribed[fixed])
    right = torch.as_tensor(b.particles.layer("right", DELTA))
    assert torch.all(moved[right, 0] == 0.7 * U) and torch.equal(moved[right, 1], u[right, 1])
    assert torch.all(moved[torch.as_tensor(b.particles.layer("left", DELTA))] == 0)


def test_reaction_is_minus_the_internal_force_summed_over_the_loaded_particles():
    *_, b = bar()
    u = b.move(0.01 * torch.randn(b.particles.n, 2, generator=torch.Generator().manual_seed(1)), 1.0)
    intact = torch.linspace(0.5, 1.0, b.n_bonds)
    f = b.internal(u, intact)
    expect = -f[torch.as_tensor(b.loaded)].sum(0)
    assert torch.equal(b.reaction(u, intact), expect)
    assert torch.equal(b.reaction(u, intact, f_int=f), expect)
    assert np.array_equal(b.loaded, b.particles.layer("right", DELTA))  # the moved layer


@pytest.mark.parametrize("eps", [0.0, 5.0])
def test_reaction_under_force_control_is_the_applied_load_at_equilibrium(eps):
    """At equilibrium the residual f_int + lambda p - eps u vanishes on the free dofs, so the
    reaction on the (free) loaded particles is lambda times the total load, up to the
    residual tolerance rtol |f_int| = 1e-10 |f_int|."""
    b = pmb_plate(eps)
    intact = torch.ones(b.n_bonds)
    active = b.active(intact)
    lam = 0.5
    u, _ = equilibrium(b, b.move(torch.zeros(b.particles.n, 2), lam), lam, intact,
                       b.tangent(intact, active), active)
    f = b.internal(u, intact)
    np.testing.assert_allclose(b.reaction(u, intact).numpy(), [lam * 30.0, lam * 10.0], rtol=0,
                               atol=1e-9 * float(f.norm()))
    assert float(u.abs().max()) > 1e-3  # a real deformation, not the trivial state


@pytest.mark.parametrize("eps", [0.0, 1e-3])
def test_active_drops_a_detached_particle_only_without_confinement(eps):
    b = pmb_plate(eps)
    free = b.constraints.free_dofs
    k = int(np.flatnonzero(b.particles.box([4, 2], [5, 3]))[0])
    intact = torch.ones(b.n_bonds)
    assert np.array_equal(b.active(intact), free)
    intact[torch.as_tensor((b.bonds.i == k) | (b.bonds.j == k))] = 0.0
    expect = free if eps else free[free // 2 != k]
    assert np.array_equal(b.active(intact), expect)


def test_bond_based_tangent_taylor_remainder_has_slope_2():
    """Every bond in tension (a 1 % expansion plus 0.1 % noise), so T is the exact Hessian:
    |f(u + t v) - f(u) + t T v| = O(t^2) on the active dofs, with damaged bonds."""
    b = pmb_plate()
    intact = broken(b, [5, 6, 40])
    intact[9] = 0.4
    active = b.active(intact)
    idx = torch.as_tensor(active)
    x = torch.as_tensor(b.particles.x)
    gen = torch.Generator().manual_seed(3)
    u = 0.01 * (x - x.mean(0)) + 1e-3 * torch.randn(b.particles.n, 2, generator=gen)
    v = torch.zeros_like(u)
    v.view(-1)[idx] = torch.randn(len(active), generator=gen)
    Tv = b.operator(intact, active, u) @ v.view(-1)[idx].numpy()
    f0 = b.internal(u, intact).view(-1)[idx].numpy()
    ts, rem = [1e-2, 5e-3, 2.5e-3], []
    for t in ts:
        ft = b.internal(u + t * v, intact).view(-1)[idx].numpy()
        rem.append(np.linalg.norm(ft - f0 + t * Tv))
        assert rem[-1] < 0.1 * t * np.linalg.norm(Tv)
    np.testing.assert_allclose(np.diff(np.log(rem)) / np.diff(np.log(ts)), 2.0, atol=0.05)


def test_lps_operator_is_the_damaged_linearised_stiffness_plus_eps():
    """For a law that is not pairwise the tangent is material.terms(params, intact) on the
    active dofs, whatever u, plus eps on the diagonal."""
    sc = plate_scene()
    params = {"K": 3.0, "G": 2.0, "delta": 2.5}
    b = bp.Scene(sc.material, sc.dirichlet, sc.loads, eps=0.25).at(params)
    intact = broken(b, [1, 2, 3])
    active = b.active(intact)
    K = sc.material.pattern.matrix(sc.material.numeric_stiffness(params, intact)).toarray()
    expect = K[np.ix_(active, active)] + 0.25 * np.eye(len(active))
    u = torch.randn(b.particles.n, 2, generator=torch.Generator().manual_seed(4))
    for at in (None, u):
        assert np.abs(b.operator(intact, active, at).toarray() - expect).max() <= 1e-14 * np.abs(expect).max()


# moved from tests/linalg/test_woodbury.py


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("material", [bp.BondBased, bp.LPS])
def test_change_matches_the_assembled_operators(monkeypatch, material, compiled):
    """The change (compiled bond loops or numpy) equals the difference of the assembled
    operators to rounding, on the rows it touches and nowhere else."""
    monkeypatch.setattr(bond_loops, "ENABLED", compiled)
    b = body(material)
    before, after = broken(b, [3, 40]), broken(b, [3, 40, 41, 500])
    after[7] = 0.3
    active = b.active(before)
    u = 0.02 * torch.randn(b.particles.n, 2, generator=torch.Generator().manual_seed(0))
    change = b.operator_change(before, after, active, u)
    direct = (b.operator(after, active, u) - b.operator(before, active, u)).toarray()
    assert np.abs(change @ np.eye(len(active)) - direct).max() <= 1e-12 * np.abs(direct).max()
    assert np.array_equal(change.rows, np.flatnonzero(np.abs(direct).max(1) > 0))


def test_change_in_3d_by_the_loops_and_by_numpy(monkeypatch):
    """A bond-based cube, clamped at the bottom and pulled at the top: at one u the change
    equals the difference of the assembled operators, by the compiled loops and by numpy;
    with the damaged zone's tangent moved to a later u the two paths agree to rounding."""
    p = bp.grid_3d(5.0, 5.0, 5.0, 1.0)
    bcs = [bp.Dirichlet.layer(p, "bottom", 1.5, (0.0, 0.0, 0.0)), bp.Dirichlet.layer(p, "top", 1.5, (0.0, 0.0, 0.1))]
    b = bp.Scene(bp.BondBased(p, bp.find_bonds(p, 1.5)), bcs).at({"K": 1000.0, "delta": 1.5})
    before, after = broken(b, [3, 40]), broken(b, [3, 40, 41, 500, 501])
    active = b.active(before)
    gen = torch.Generator().manual_seed(0)
    u, later = (0.02 * torch.randn(p.n, 3, generator=gen) for _ in range(2))
    direct = (b.operator(after, active, u) - b.operator(before, active, u)).toarray()
    dense = {}
    for compiled in (True, False):
        monkeypatch.setattr(bond_loops, "ENABLED", compiled)
        change = b.operator_change(before, after, active, u)
        assert len(change.rows) >= 12  # the dofs of at least the four ends of the changed bonds
        assert np.abs(change @ np.eye(len(active)) - direct).max() <= 1e-12 * np.abs(direct).max()
        dense[compiled] = b.operator_change(before, after, active, u, later) @ np.eye(len(active))
    assert np.abs(dense[True] - dense[False]).max() <= 1e-12 * np.abs(dense[False]).max()


def test_change_takes_in_every_bond_between_the_changed_ends(plate):
    """The bonds whose tangent a change re-evaluates are read from the changed ends' own
    bonds: the same sorted set as a pass over every bond, for sparse to dense sets of ends."""
    rng = np.random.default_rng(0)
    i, j = plate.bonds.i, plate.bonds.j
    for fraction in (0.0, 0.02, 0.2, 0.6, 1.0):
        ends = rng.random(plate.particles.n) < fraction
        assert np.array_equal(plate._bonds_among(ends), np.flatnonzero(ends[i] & ends[j]))


def test_bond_based_tangent_is_the_hessian_in_tension(plate):
    """Every bond stretched (1 % in both directions plus a perturbation of 0.1 %), so the
    geometric part is on everywhere: T v equals the central difference of -f_int along v
    to O(h^2) (relative 1e-7 at h = 1e-4 |u|)."""
    intact = broken(plate, [10, 11, 300])
    active = plate.active(intact)
    x = torch.as_tensor(plate.particles.x)
    u = 0.01 * (x - x.mean(0)) + 1e-4 * torch.randn(plate.particles.n, 2, generator=torch.Generator().manual_seed(1))
    v = torch.zeros_like(u)
    v.view(-1)[torch.as_tensor(active)] = torch.randn(len(active), generator=torch.Generator().manual_seed(2), dtype=u.dtype)
    h = 1e-4 * float(u.abs().max())
    fd = (plate.internal(u - h * v, intact) - plate.internal(u + h * v, intact)) / (2 * h)
    Tv = plate.operator(intact, active, u) @ v.view(-1)[torch.as_tensor(active)].numpy()
    expected = fd.view(-1)[torch.as_tensor(active)].numpy()
    assert np.abs(Tv - expected).max() <= 1e-7 * np.abs(expected).max()


# moved from tests/solvers/test_quasistatic.py
@pytest.mark.parametrize("eps", [0.0, 1.0])
def test_a_detached_particle_leaves_the_system_nonsingular(eps):
    """A free particle whose bonds are all broken: eps = 0 drops its dofs (it keeps its
    displacement), eps > 0 keeps them (confinement, Dodwell 2019 eq 3: it returns to 0)."""
    mat, params, bcs, _ = bar()
    body = bp.Scene(mat, bcs, eps=eps).at(params)
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


@pytest.mark.parametrize("flip", [False, True])
def test_a_bond_listed_twice_is_refused(flip):
    """The same pair twice (as i, j or as j, i) would count its stiffness twice."""
    p = bp.grid_2d(6.0, 4.0, H)
    b = bp.find_bonds(p, DELTA)
    i, j = (b.j[:1], b.i[:1]) if flip else (b.i[:1], b.j[:1])
    twice = bp.Bonds(np.r_[b.i, i], np.r_[b.j, j], np.r_[b.xi, np.asarray(p.x[j] - p.x[i])],
                     np.r_[b.length, b.length[:1]], b.h, b.delta_max, b.rule)
    bcs = [bp.Dirichlet.layer(p, "left", DELTA), bp.Dirichlet.layer(p, "right", DELTA, (U, 0.0))]
    body = bp.Scene(bp.BondBased(p, twice), bcs).at({"K": 1000.0, "delta": DELTA})
    with pytest.raises(ValueError, match="listed twice"):
        body.operator(torch.ones(body.n_bonds), body.constraints.free_dofs)
