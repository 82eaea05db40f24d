"""The AMG preconditioner (``bayespd.linalg.amg``): rigid-body modes in the bond operator's null
space, a symmetric positive-definite V-cycle, and the PCG it preconditions against the direct
solve, in fewer iterations than the bond-graph Laplacian needs."""
import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.linalg.amg import amg_preconditioner, pair_operator, rigid_body_modes
from bayespd.linalg.stiffness_solver import Assembly
from tests.linalg.linalg_systems import lps_terms


def clamped(nx=30, ny=12):
    p, bonds, mat, terms = lps_terms(nx=nx, ny=ny)
    asm = Assembly(mat.grams(), ~np.repeat(p.layer("left", 2.6), 2))
    return p, asm, terms


@pytest.mark.parametrize("dim", [2, 3])
def test_rigid_body_modes_are_the_bond_operators_null_space(dim):
    """K_b B = 0 to rounding (1e-12 of ||K_b|| ||B||) for the 3 (2D) / 6 (3D) rigid-body modes of
    an unconstrained body: a rigid motion stretches no bond."""
    p = bp.grid_2d(8.0, 5.0, 1.0) if dim == 2 else bp.grid_3d(5.0, 4.0, 3.0, 1.0)
    kw = {"plane": "stress"} if dim == 2 else {}
    mat = bp.LPS(p, bp.find_bonds(p, 2.2), **kw)
    terms = mat.terms({"K": 3000.0, "G": 1500.0, "delta": 2.2})
    K = pair_operator(terms, np.arange(p.n * dim))
    B = rigid_body_modes(p.x)
    assert B.shape == (p.n * dim, 3 if dim == 2 else 6)
    assert np.linalg.matrix_rank(B) == B.shape[1]
    assert np.abs(K @ B).max() <= 1e-12 * abs(K).sum(axis=1).max() * np.abs(B).max()


def test_the_v_cycle_is_symmetric_positive_definite_and_columnwise():
    """v^T M^-1 w = w^T M^-1 v to 1e-12 relative (backward after forward Gauss-Seidel),
    v^T M^-1 v > 0, and a two-column right-hand side gives each column's result."""
    p, asm, terms = clamped()
    cycle = amg_preconditioner([(g, d.numpy(), w.numpy()) for g, d, w in terms], asm.free_index, p.x)
    assert len(cycle.levels) >= 1  # a real hierarchy, not only the coarse solve
    V = np.random.default_rng(0).standard_normal((len(asm.free_index), 2))
    MV = cycle(V)
    assert abs(V[:, 0] @ MV[:, 1] - V[:, 1] @ MV[:, 0]) <= 1e-12 * np.abs(V[:, 0] @ MV[:, 1])
    assert np.all(np.einsum("ij,ij->j", V, MV) > 0)
    np.testing.assert_allclose(MV[:, 1], cycle(V[:, 1]), rtol=1e-13, atol=1e-15 * np.abs(MV).max())


def test_amg_pcg_matches_the_direct_solve_in_few_iterations():
    """PCG with the V-cycle reaches rtol = 1e-10 and agrees with SuperLU to 1e-8 relative
    (kappa(K) rtol); it needs at most 2/3 of the iterations of the bond-graph Laplacian factor
    (measured 12 against 35 here, 23 against 35 at 160k particles)."""
    p, asm, terms = clamped()
    rhs = np.random.default_rng(1).standard_normal(len(asm.free_index))
    exact = asm.factorize(terms, "direct", backend="splu").solve(rhs)
    amg = asm.factorize(terms, "amg", rtol=1e-10, positions=p.x)
    lap = asm.factorize(terms, "pcg", rtol=1e-10)
    x = amg.solve(rhs)
    lap.solve(rhs)
    assert np.linalg.norm(x - exact) <= 1e-8 * np.linalg.norm(exact)
    assert amg.iterations <= (2 * lap.iterations) // 3, (amg.iterations, lap.iterations)


def test_amg_needs_positions():
    p, asm, terms = clamped(nx=10, ny=6)
    with pytest.raises(ValueError, match="positions=particles.x"):
        asm.factorize(terms, "amg")


def test_jacobi_radius_is_a_tight_lower_bound():
    """The seeded Lanczos estimate of rho(D^-1 K_b) lies within 2 % below the dense eigenvalue
    (a Ritz value never exceeds it; 15 steps resolve the end of the spectrum)."""
    from bayespd.linalg.amg import _jacobi_radius

    p, asm, terms = clamped(nx=20, ny=10)
    K = pair_operator([(g, d.numpy(), w.numpy()) for g, d, w in terms], asm.free_index)
    d_inv = 1.0 / K.diagonal()
    exact = np.linalg.eigvals(d_inv[:, None] * K.toarray()).real.max()
    estimate = _jacobi_radius(K, d_inv)
    assert exact * 0.98 <= estimate <= exact * (1 + 1e-12)


def test_hierarchy_has_pyamgs_aggregates_and_galerkin_coarse_operators():
    """The CSR set-up coarsens as pyamg's smoothed_aggregation_solver does (same level sizes
    and coarse patterns: same strength, aggregation of whole coarse nodes and candidate fit),
    and each coarse operator is R A P with R = P^T to rounding."""
    import pyamg
    import scipy.sparse as sp

    from bayespd.linalg.amg import smoothed_aggregation

    p, asm, terms = clamped(nx=120, ny=40)
    K = pair_operator([(g, d.numpy(), w.numpy()) for g, d, w in terms], asm.free_index)
    modes = rigid_body_modes(p.x)[asm.free_index]
    levels, coarse = smoothed_aggregation(K, modes, max_coarse=20)
    reference = pyamg.smoothed_aggregation_solver(sp.csr_matrix(K), B=modes, max_coarse=20,
                                                  improve_candidates=None)
    ours = [A for A, _, _ in levels] + [coarse]
    assert len(ours) >= 3
    assert [A.shape for A in ours] == [lv.A.shape for lv in reference.levels]
    assert ([len(A.tobsr(blocksize=(3, 3)).indices) for A in ours[1:]]
            == [len(lv.A.indices) for lv in reference.levels[1:]])  # coupled node pairs


def test_a_dof_no_bond_reaches_keeps_the_hierarchy_finite():
    """A zero row (a dof decoupled from K_b, or a mode an aggregate cannot carry, as at
    65k particles of the three-point beam) gets a zero Jacobi weight, as in pyamg: every
    operator stays finite and the rest is preconditioned as before (PCG iterations within 2)."""
    import scipy.sparse as sp

    from bayespd.linalg import sparse
    from bayespd.linalg.amg import VCycle, smoothed_aggregation

    p, asm, terms = clamped()
    K = pair_operator([(g, d.numpy(), w.numpy()) for g, d, w in terms], asm.free_index)
    modes = rigid_body_modes(p.x)[asm.free_index]
    K0 = sp.block_diag([K, sp.csr_matrix((1, 1))], format="csr")
    levels, coarse = smoothed_aggregation(K0, np.vstack([modes, np.zeros((1, 3))]), max_coarse=20)
    assert all(np.isfinite(P.data).all() and np.isfinite(A.data).all() for A, P, _ in levels)
    cycle = VCycle(levels, coarse)
    r = np.random.default_rng(2).standard_normal(K0.shape[0])
    assert np.isfinite(cycle(r)).all()
    padded = lambda v: cycle(np.append(v, 0.0))[:-1]  # noqa: E731
    its = []
    for M in (padded, VCycle(*smoothed_aggregation(K, modes, max_coarse=20))):
        f = sparse.PCGFactor(K.__matmul__, M, K.shape[0], rtol=1e-10)
        f.solve(r[:-1])
        its.append(f.iterations)
    assert abs(its[0] - its[1]) <= 2, its
    for (A, P, R), nxt in zip(levels, [lv[0] for lv in levels[1:]] + [coarse]):
        assert abs(R - P.T).max() == 0
        assert abs(nxt - P.T @ A @ P).max() <= 1e-12 * abs(nxt).max()


def test_the_hierarchy_is_reused_while_the_bond_operator_only_scales():
    """A new bulk modulus (not in K_b) or shear modulus (K_b scales by G'/G) reuses the AMG
    hierarchy: one set-up for three parameter values, the iterations of a fresh set-up, the
    direct solution to 1e-8 relative. A new horizon (weights not proportional) keeps it too,
    smoothing on the new K_b, within the reuse's iteration limit and to the direct solution;
    new positions build anew."""
    p, bonds, mat, _ = lps_terms(nx=30, ny=12)
    asm = Assembly(mat.grams(), ~np.repeat(p.layer("left", 2.6), 2))
    rhs = np.random.default_rng(5).standard_normal(len(asm.free_index))
    for k, (K, G, delta) in enumerate([(3000.0, 1500.0, 2.6), (4500.0, 1500.0, 2.6), (3000.0, 2100.0, 2.6)]):
        terms = mat.terms({"K": K, "G": G, "delta": delta})
        x = asm.factorize(terms, "amg", positions=p.x)
        u = x.solve(rhs)
        assert asm.amg_builds == 1
        fresh = Assembly(mat.grams(), asm.free).factorize(terms, "amg", positions=p.x)
        fresh.solve(rhs)
        assert x.iterations == fresh.iterations, (k, x.iterations, fresh.iterations)
        exact = asm.factorize(terms, "direct", backend="splu").solve(rhs)
        assert np.linalg.norm(u - exact) <= 1e-8 * np.linalg.norm(exact)
    terms = mat.terms({"K": 3000.0, "G": 1500.0, "delta": 2.3})
    x = asm.factorize(terms, "amg", positions=p.x)
    u = x.solve(rhs)
    assert asm.amg_builds == 1 and not x.renewed and x.iterations <= asm._kept.limit()
    exact = asm.factorize(terms, "direct", backend="splu").solve(rhs)
    assert np.linalg.norm(u - exact) <= 1e-8 * np.linalg.norm(exact)
    asm.factorize(terms, "amg", positions=p.x + 0.01)
    assert asm.amg_builds == 2


def test_a_reused_hierarchy_that_no_longer_serves_is_built_anew_mid_solve():
    """A shear-modulus field 1000x steeper than the kept hierarchy's K_b (the stale cycle alone
    needs 118 iterations against 13): the solve reaches the reuse's limit, builds the
    hierarchy for the new K_b, converges with it to the direct solution (1e-8), and the
    Assembly reuses no hierarchy after that."""
    p, bonds, mat, _ = lps_terms(nx=30, ny=12)
    asm = Assembly(mat.grams(), ~np.repeat(p.layer("left", 2.6), 2))
    rhs = np.random.default_rng(5).standard_normal(len(asm.free_index))
    first = asm.factorize(mat.terms({"K": 3000.0, "G": 1500.0, "delta": 2.6}), "amg", positions=p.x)
    first.solve(rhs)
    G = torch.as_tensor(1500.0 * 1000.0 ** (p.x[:, 0] / p.x[:, 0].max()))
    terms = mat.terms({"K": 2 * G, "G": G, "delta": 2.6})
    x = asm.factorize(terms, "amg", positions=p.x)
    u = x.solve(rhs)
    limit = int(1.25 * first.iterations) + 1
    assert x.renewed and asm.amg_builds == 2 and not asm.reuse_hierarchy
    fresh = Assembly(mat.grams(), asm.free).factorize(terms, "amg", positions=p.x)
    fresh.solve(rhs)
    assert x.iterations <= limit + fresh.iterations + 1, (x.iterations, limit, fresh.iterations)
    exact = asm.factorize(terms, "direct", backend="splu").solve(rhs)
    assert np.linalg.norm(u - exact) <= 1e-8 * np.linalg.norm(exact)
    asm.factorize(mat.terms({"K": 3000.0, "G": 1500.0, "delta": 2.3}), "amg", positions=p.x)
    assert asm.amg_builds == 3


@pytest.mark.parametrize("material, changed", [("lps", {"G": 2100.0}), ("lps", {"K": 4500.0}),
                                               ("pmb", {"K": 4500.0})])
def test_a_new_modulus_rescales_the_kept_bond_operator(material, changed):
    """Only a modulus changed (same horizon and particles): K_b is the kept one times c (the
    same index arrays, nothing reassembled; c = 1 for LPS's bulk modulus, which K_b does not
    hold) and equals a reassembly to 1e-15 of its largest entry: each entry is a sum of
    weight x data products, and c x the sum differs from the sum of c x each by rounding.
    (The hierarchy, reused divided by c, gives the iterations of a fresh one: test above.)"""
    p = bp.grid_2d(30.0, 12.0, 1.0)
    cls = bp.LPS if material == "lps" else bp.BondBased
    mat = cls(p, bp.find_bonds(p, 2.6), plane="stress")
    asm = Assembly(mat.grams(), ~np.repeat(p.layer("left", 2.6), 2))
    base = {"K": 3000.0, "G": 1500.0, "delta": 2.6}
    base = {k: base[k] for k in mat.param_names}
    kept, _ = asm.amg(mat.terms(base), p.x)
    terms = mat.terms(dict(base, **changed))
    K, _ = asm.amg(terms, p.x)
    assert asm.amg_builds == 1
    assert np.shares_memory(K.indices, kept.indices) and np.shares_memory(K.indptr, kept.indptr)
    fresh = pair_operator(terms, asm.free_index)
    assert abs(K - fresh).max() <= 1e-15 * abs(fresh).max()
    asm.amg(mat.terms(dict(base, delta=2.3)), p.x)
    assert asm.amg_builds == 2


def test_cell_aggregates_hold_whole_particles_of_one_cell_and_split_at_a_crack():
    """m = 2 on the unit lattice: bonds from h = 1 to r = sqrt(5), cells of side
    floor(3 r / h) = 6 h: a 24 x 12 plate gives 4 x 2 aggregates of 36 particles, both dofs
    of a particle in its cell's aggregate; a crack through a cell splits its aggregate in two."""
    from bayespd.linalg.amg import bond_ends, cell_aggregates

    p = bp.grid_2d(24.0, 12.0, 1.0)
    for crack, count in ((None, 8), ([[3.0, 0.0], [3.0, 6.0]], 9)):
        bonds = bp.find_bonds(p, 2.0)
        if crack is not None:
            bonds = bp.precrack(p, bonds, crack)
        mat = bp.LPS(p, bonds, plane="stress")
        i, j = bond_ends(mat.terms({"K": 3000.0, "G": 1500.0, "delta": 2.0}))
        agg = cell_aggregates(p.x, i, j, np.repeat(np.arange(p.n), 2)).tocsc()
        assert agg.shape == (2 * p.n, count) and np.all(agg.sum(axis=1) == 1)
        cells = np.floor(p.x / 6.0).astype(int)
        for k in range(count):
            dofs = agg.indices[agg.indptr[k]:agg.indptr[k + 1]]
            particles = np.unique(dofs // 2)
            assert len(dofs) == 2 * len(particles)  # whole particles
            assert len(np.unique(cells[particles], axis=0)) == 1  # one cell
            assert len(particles) == (18 if crack is not None and cells[particles[0]].sum() == 0 else 36)


def test_cell_aggregates_couple_only_neighbouring_cells_on_the_coarse_level():
    """With cells of side floor(3 r / h) h, two cells apart lie (s + 1) h > 3 r apart, beyond
    one Jacobi step of the prolongator (r) on each side and K_b's reach (r): an interior
    coarse row couples the 3 x 3 cells around it, 27 entries with 3 modes each (pyamg's
    standard aggregation: irregular aggregates, more neighbours)."""
    from bayespd.linalg.amg import bond_ends, cell_aggregates, smoothed_aggregation

    p, asm, terms = clamped(nx=60, ny=36)
    terms = [(g, d.numpy(), w.numpy()) for g, d, w in terms]
    K = pair_operator(terms, asm.free_index)
    modes = rigid_body_modes(p.x)[asm.free_index]
    agg = cell_aggregates(p.x, *bond_ends(terms), asm.free_index // 2)
    assert agg.shape[1] > 20  # cells are used when the coarse level is coarsened again
    levels, coarse = smoothed_aggregation(K, modes, aggregates=agg, max_coarse=20)
    first = levels[1][0] if len(levels) > 1 else coarse
    assert first.shape[0] == 3 * agg.shape[1]
    assert np.diff(first.tocsr().indptr).max() == 27
    levels, coarse = smoothed_aggregation(K, modes, max_coarse=20)
    assert np.diff((levels[1][0] if len(levels) > 1 else coarse).tocsr().indptr).max() > 27


def test_few_cells_leave_the_two_level_method_to_pyamgs_aggregates():
    """Cells that leave at most max_coarse coarse nodes are not used: the method would have
    two levels, and pyamg's smaller aggregates give a larger exactly solved coarse level
    (fewer iterations). The hierarchy is then pyamg's, entry for entry."""
    from bayespd.linalg.amg import bond_ends, cell_aggregates, smoothed_aggregation

    p, asm, terms = clamped(nx=60, ny=36)
    terms = [(g, d.numpy(), w.numpy()) for g, d, w in terms]
    K = pair_operator(terms, asm.free_index)
    modes = rigid_body_modes(p.x)[asm.free_index]
    agg = cell_aggregates(p.x, *bond_ends(terms), asm.free_index // 2)
    assert agg.shape[1] <= 300
    (_, P, _), = smoothed_aggregation(K, modes, aggregates=agg)[0]
    (_, P0, _), = smoothed_aggregation(K, modes)[0]
    assert P.shape == P0.shape and abs(P - P0).max() == 0
