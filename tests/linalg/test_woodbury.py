"""Solves after a local change (``bayespd.linalg.woodbury``): the Woodbury update of a factor
equals a fresh factorisation of the changed matrix, refuses a change that makes it
indefinite, and conjugate gradients on the exact tangent, preconditioned by a stale factor,
converge within the iteration bound of their condition number (the change of a
``Scene.at``'s operator itself is tested in ``tests/solvers/test_body.py``)."""
import math

import numpy as np
import pytest
import scipy.linalg as sla
import scipy.sparse as sp
import torch

import bayespd as bp
from bayespd.solvers.fracture import StochasticFracture
from bayespd.damage import CriticalStretch
from bayespd.solvers import white_noise
from bayespd.linalg.factors import shifted_factor, spd_factor
from bayespd.linalg import trailing, woodbury
from bayespd.linalg.woodbury import LocallyUpdated, Refined
from bayespd.linalg.sparse import NotPositiveDefiniteError

SIDE, H, DELTA = 12.0, 1.0, 3.0


PARAMS = {"K": 1000.0, "G": 600.0, "delta": DELTA}


def scene(material=bp.BondBased):
    """The plate, bottom clamped and top pulled, with the critical stretch and white noise."""
    p = bp.grid_2d(SIDE, SIDE, H)
    bcs = [bp.Dirichlet.layer(p, "bottom", DELTA), bp.Dirichlet.layer(p, "top", DELTA, (0.0, 0.1))]
    return bp.Scene(material(p, bp.find_bonds(p, DELTA)), bcs, damage=CriticalStretch(0.01),
                    noise=lambda dofs: white_noise(50.0, len(dofs)))


def body(material=bp.BondBased):
    plate = scene(material)
    return plate.at({k: PARAMS[k] for k in plate.param_names})


@pytest.fixture(scope="module")
def plate():
    return body()


def broken(b, bonds) -> torch.Tensor:
    intact = torch.ones(b.n_bonds)
    intact[bonds] = 0.0
    return intact


def test_updated_factor_equals_a_fresh_one(plate):
    """Two successive changes (bonds breaking near the centre, then more): the solve with
    the updated factor equals the direct one to 1e-10 relative, for one and several
    right-hand sides; a change touching more rows than max_rank asks for a new factor."""
    active = plate.active(torch.ones(plate.n_bonds))
    s, b = np.full(len(active), 2.0), 1e-3
    centre = np.flatnonzero(np.abs(plate.particles.x[plate.bonds.i, 1] - SIDE / 2) < 1)
    A0 = LocallyUpdated(plate.operator(torch.ones(plate.n_bonds), active), max_rank=40)
    rhs = np.random.default_rng(0).standard_normal((len(active), 3))
    for bonds in (centre[:5], centre[:20]):
        intact = broken(plate, bonds)
        A = A0.changed(plate.operator_change(torch.ones(plate.n_bonds), intact, active))
        exact = spd_factor(sp.diags(s) + b * plate.operator(intact, active)).solve(rhs)
        got = shifted_factor(A, s, b).solve(rhs)
        assert np.abs(got - exact).max() <= 1e-10 * np.abs(exact).max()
        assert np.abs(shifted_factor(A, s, b).solve(rhs[:, 0]) - exact[:, 0]).max() <= 1e-10 * np.abs(exact).max()
        v = rhs[:, 0]
        assert np.abs(A @ v - plate.operator(intact, active) @ v).max() <= 1e-10 * np.abs(A @ v).max()
    assert A0.changed(plate.operator_change(torch.ones(plate.n_bonds), broken(plate, centre), active)) is None


@pytest.mark.parametrize("rows", [[1], [0, 3]])
def test_an_indefinite_change_is_refused(rows):
    """Subtracting 20 from diagonal entries of M0 = I + A (<= 7): one or two negative
    eigenvalues (two keep det(M) > 0, which a determinant's sign would let pass)."""
    A = sp.diags([4.0, 3.0, 2.0, 5.0]) + sp.diags([1.0, 1.0, 1.0], 1) + sp.diags([1.0, 1.0, 1.0], -1)
    delta = sp.csr_matrix(([-20.0] * len(rows), (rows, rows)), shape=(4, 4))
    assert np.sum(np.linalg.eigvalsh(np.eye(4) + (A + delta).toarray()) < 0) == len(rows)
    with pytest.raises(NotPositiveDefiniteError, match="not positive definite"):
        LocallyUpdated(A).changed(delta).shifted_factor(np.ones(4), 1.0)
    ok = LocallyUpdated(A).changed(-0.5 * delta).shifted_factor(np.ones(4), 1.0).solve(np.ones(4))
    assert np.allclose((np.eye(4) + (A + (-0.5 * delta)).toarray()) @ ok, 1.0, atol=1e-12)


def test_conjugate_gradients_on_the_exact_tangent_meet_their_bound(plate):
    """Exact tangent at a stretched state, preconditioner the factor at u = 0: the iteration
    count stays within the textbook bound ceil(log(2 / rtol) / log(1 / rho)),
    rho = (sqrt(kappa) - 1) / (sqrt(kappa) + 1), kappa of the preconditioned operator."""
    intact = torch.ones(plate.n_bonds)
    active = plate.active(intact)
    u = plate.move(torch.zeros(plate.particles.n, 2), 1.0)
    u[:, 1] += 0.01 * torch.as_tensor(plate.particles.x[:, 1])  # a uniform 1 % stretch, so the geometric part is on
    s, b = np.full(len(active), 1.0), 1e-2
    T = plate.operator(intact, active, u)
    exact = Refined(lambda v: T @ v, LocallyUpdated(plate.operator(intact, active)))
    M = np.diag(s) + b * T.toarray()
    P = np.diag(s) + b * plate.operator(intact, active).toarray()
    lam = sla.eigh(M, P, eigvals_only=True)
    kappa = lam.max() / lam.min()
    rho = (math.sqrt(kappa) - 1) / (math.sqrt(kappa) + 1)
    r = np.random.default_rng(1).standard_normal(len(active))
    x = shifted_factor(exact, s, b).solve(r)
    assert np.linalg.norm(M @ x - r) <= 1e-8 * np.linalg.norm(r)
    assert 1 <= exact.iterations <= math.ceil(math.log(2 / 1e-8) / math.log(1 / rho))
    assert kappa > 1.001  # the geometric part does change the operator


def test_fracture_with_updates_follows_fracture_with_refactorisation(plate):
    """Noisy mode-I run: the Woodbury-updated operator (conjugate gradients to 1e-8) and a
    fresh factorisation at every change break the same bonds, with the same seed."""
    lams = np.linspace(0.1, 2.0, 12)
    frac = StochasticFracture(scene(), {"K": 1000.0, "delta": DELTA}, eta=50.0**2 / 1e3)
    a = frac.run(lams, 1.0, seed=5)
    b = frac.run(lams, 1.0, seed=5, max_rank=0)
    assert a.broken[-1] > 0 and np.array_equal(a.broken, b.broken)
    assert torch.allclose(a.u, b.u, rtol=0, atol=1e-6 * float(a.u.abs().max()))


def test_grouped_columns_are_solved_a_tile_at_a_time(plate, monkeypatch):
    """Columns solved a tile at a time (``groups``): the updated solve equals the direct one
    to 1e-10, the columns equal those solved row by row to 1e-12, and a second change whose
    new rows lie in tiles already touched needs no solve; a groups array of the wrong
    length is refused."""
    intact0 = torch.ones(plate.n_bonds)
    active = plate.active(intact0)
    tiles = plate.tiles(active, 4 * H)
    assert len(np.unique(tiles)) == 6 and np.all(tiles[0::2] == tiles[1::2])  # the free 12 x 6 band: 3 x 2 tiles; a particle's dofs together
    s, b = np.full(len(active), 2.0), 1e-3
    centre = np.flatnonzero(np.abs(plate.particles.x[plate.bonds.i, 1] - SIDE / 2) < 1)
    first, second = centre[:3], centre[:6]
    rhs = np.random.default_rng(3).standard_normal(len(active))
    T0 = plate.operator(intact0, active)
    batches = []
    solve_rows = woodbury._Solved._solve
    monkeypatch.setattr(woodbury._Solved, "_solve", lambda self, rows: batches.append(len(rows)) or solve_rows(self, rows))

    def run(groups):
        A0 = LocallyUpdated(T0, max_rank=200, groups=groups)
        batches.clear()
        counts = []
        for bonds in (first, second):
            solve = shifted_factor(A0.changed(plate.operator_change(intact0, broken(plate, bonds), active)), s, b).solve
            counts.append(int(np.count_nonzero(batches)))
        base = next(iter(A0._bases.values()))
        return solve, dict(zip(base.order.tolist(), base.columns.T)), counts

    solve, grouped, counts = run(tiles)
    _, alone, counts_alone = run(None)
    exact = spd_factor(sp.diags(s) + b * plate.operator(broken(plate, second), active)).solve(rhs)
    assert np.abs(solve(rhs) - exact).max() <= 1e-10 * np.abs(exact).max()
    assert grouped.keys() == alone.keys()
    scale = max(np.abs(c).max() for c in alone.values())
    assert max(np.abs(grouped[r] - alone[r]).max() for r in grouped) <= 1e-12 * scale
    assert counts == [1, 1] and counts_alone == [1, 2]  # grouped: the second change's new rows were ready
    with pytest.raises(ValueError, match="one label per row"):
        LocallyUpdated(T0, groups=tiles[:-1])


needs_cholmod = pytest.mark.skipif(not trailing.available(), reason="the trailing factor needs CHOLMOD")


@needs_cholmod
def test_region_update_equals_a_fresh_factor(plate):
    """Woodbury on a region ordered last: two successive changes inside it solve like a fresh
    factorisation to 1e-10 (one and several right-hand sides) and like the column-solving
    path; a change with a row outside the region asks for a new factor."""
    intact0 = torch.ones(plate.n_bonds)
    active = plate.active(intact0)
    s, b = np.full(len(active), 2.0), 1e-3
    y = plate.particles.x[:, 1]
    near = [np.abs(y[ends] - SIDE / 2) for ends in (plate.bonds.i, plate.bonds.j)]
    centre = np.flatnonzero((near[0] < 1) & (near[1] < 1))  # both ends on the two middle rows
    region = np.flatnonzero(np.abs(y[active // 2] - SIDE / 2) < 1)
    T0 = plate.operator(intact0, active)
    A0, plain = LocallyUpdated(T0, max_rank=200, region=region), LocallyUpdated(T0, max_rank=200)
    rhs = np.random.default_rng(0).standard_normal((len(active), 3))
    for bonds in (centre[:5], centre[:20]):
        intact = broken(plate, bonds)
        change = plate.operator_change(intact0, intact, active)
        exact = spd_factor(sp.diags(s) + b * plate.operator(intact, active)).solve(rhs)
        got = shifted_factor(A0.changed(change), s, b)
        assert np.abs(got.solve(rhs) - exact).max() <= 1e-10 * np.abs(exact).max()
        assert np.abs(got.solve(rhs[:, 0]) - exact[:, 0]).max() <= 1e-10 * np.abs(exact).max()
        assert np.abs(got.solve(rhs) - shifted_factor(plain.changed(change), s, b).solve(rhs)).max() <= 1e-10 * np.abs(exact).max()
    far = np.flatnonzero((near[0] == 2.5) & (near[1] == 2.5))[:1]  # on the lowest free row
    assert A0.changed(plate.operator_change(intact0, broken(plate, far), active)) is None


@pytest.mark.parametrize("zone", [False, pytest.param(True, marks=needs_cholmod)])
def test_many_small_changes_keep_the_update_exact(plate, zone):
    """Bonds breaking one at a time along the centre line, 40 changes: W_R^-1, bordered by a
    row or two at each, keeps the updated solve equal to a fresh factorisation to 1e-10."""
    intact0 = torch.ones(plate.n_bonds)
    active = plate.active(intact0)
    s, b = np.full(len(active), 2.0), 1e-3
    y = plate.particles.x[:, 1]
    centre = np.flatnonzero((np.abs(y[plate.bonds.i] - SIDE / 2) < 1) & (np.abs(y[plate.bonds.j] - SIDE / 2) < 1))
    region = np.flatnonzero(np.abs(y[active // 2] - SIDE / 2) < 1) if zone else None
    A0 = LocallyUpdated(plate.operator(intact0, active), max_rank=200, region=region)
    rhs = np.random.default_rng(1).standard_normal(len(active))
    for n in range(1, 41):
        intact = broken(plate, centre[:n])
        got = shifted_factor(A0.changed(plate.operator_change(intact0, intact, active)), s, b).solve(rhs)
    exact = spd_factor(sp.diags(s) + b * plate.operator(intact, active)).solve(rhs)
    assert np.abs(got - exact).max() <= 1e-10 * np.abs(exact).max()


@needs_cholmod
@pytest.mark.parametrize("tangent, where", [("lagged", "everywhere"), ("exact", "on the crack"),
                                            ("exact", "away from it")])
def test_fracture_with_a_zone_follows_fracture_without(plate, tangent, where):
    """The noisy mode-I run of ``test_fracture_with_updates_follows_fracture_with_refactorisation``
    with a crack zone ordered last in the factor breaks the same bonds as without one, to
    1e-9 in u. Lagged tangent, zone over the whole body: the same operators, so only the
    algebra differs. Exact tangent (the factor only preconditions): a zone on the crack line,
    and one away from it (every change leaves it, and each fresh factor takes in the damage)."""
    lams = np.linspace(0.1, 2.0, 12)
    frac = StochasticFracture(scene(), {"K": 1000.0, "delta": DELTA}, eta=50.0**2 / 1e3)
    y = plate.particles.x[:, 1]
    zone = {"everywhere": y > -1, "on the crack": np.abs(y - SIDE / 2) < 2, "away from it": y > SIDE - 4.5}[where]
    a = frac.run(lams, 1.0, seed=5, tangent=tangent)
    b = frac.run(lams, 1.0, seed=5, tangent=tangent, zone=zone)
    assert a.broken[-1] > 0 and np.array_equal(a.broken, b.broken)
    assert torch.allclose(a.u, b.u, rtol=0, atol=1e-9 * float(a.u.abs().max()))
    with pytest.raises(ValueError, match="mask of the"):
        frac.run(lams, 1.0, seed=5, zone=zone[:-1])


def test_runs_on_one_material_share_their_operator_and_its_pattern():
    """Two bodies of one scene (two draws of an ensemble) hold one copy of what they share: the
    sub-pattern on the same active dofs (``Pattern.restrict``: the same objects) and the
    starting operator of their LocallyUpdated (``woodbury.shared_operator``: one read-only
    CSR for operators equal bit for bit); an operator that differs gets its own, and solves
    with either are those of a fresh factor to 1e-10."""
    plate = scene()
    first, second = (plate.at({k: PARAMS[k] for k in plate.param_names}) for _ in range(2))
    intact = torch.ones(first.n_bonds)
    active = first.active(intact)
    assert first._restricted(active)[0] is second._restricted(active)[0]
    assert first._restricted(active)[1] is second._restricted(active)[1]
    A, B = (LocallyUpdated(b.operator(intact, active)) for b in (first, second))
    assert A.A0 is B.A0 and not A.A0.data.flags.writeable
    with pytest.raises(ValueError):
        A.A0.data[0] = 0.0
    cut = broken(first, np.flatnonzero(np.abs(first.particles.x[first.bonds.i, 1] - SIDE / 2) < 1)[:10])
    C = LocallyUpdated(second.operator(cut, active))
    assert C.A0 is not A.A0
    s, b = np.full(len(active), 2.0), 1e-3
    rhs = np.random.default_rng(1).standard_normal(len(active))
    for M, matrix in ((A, first.operator(intact, active)), (C, second.operator(cut, active))):
        exact = spd_factor(sp.diags(s) + b * matrix).solve(rhs)
        assert np.abs(shifted_factor(M, s, b).solve(rhs) - exact).max() <= 1e-10 * np.abs(exact).max()
