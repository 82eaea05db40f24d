"""The compiled assembly of the AMG path's bond operator K_b (``bayespd.linalg.pair_loops``):
scipy's restricted product to rounding, on the free dofs, with sorted indices."""
import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd import bond_loops
from bayespd.linalg import amg, pair_loops
from bayespd.linalg.amg import pair_operator

pytestmark = pytest.mark.skipif(bond_loops.numba is None, reason="needs numba (the 'fast' or 'dev' extra)")


def scipy_pair_operator(terms, free, monkeypatch):
    with monkeypatch.context() as m:
        m.setattr(bond_loops, "ENABLED", False)
        return pair_operator(terms, free)


@pytest.mark.parametrize("dim, material", [(2, "lps"), (2, "pmb"), (3, "lps")])
def test_the_compiled_bond_operator_is_scipys_product(dim, material, monkeypatch):
    """Clamped plate / block (constrained dofs dropped from rows and columns, one dof of a
    particle left free alone), surface-corrected LPS (bond weights differ per bond): the same
    pattern, sorted, and the entries to 1e-14 of the largest (sums in another order)."""
    p = bp.grid_2d(14.0, 9.0, 1.0) if dim == 2 else bp.grid_3d(6.0, 5.0, 4.0, 1.0)
    kw = {"plane": "stress"} if dim == 2 else {}
    cls = bp.LPS if material == "lps" else bp.BondBased
    mat = cls(p, bp.find_bonds(p, 2.6), surface_correction=material == "lps", **kw)
    params = {"K": 3000.0, "G": 1500.0, "delta": 2.6}
    terms = [(g, d.detach().numpy(), w.detach().numpy()) for g, d, w in mat.terms({k: params[k] for k in mat.param_names})]
    fixed = np.repeat(p.layer("left", 1.0), dim)
    fixed[dim * np.flatnonzero(p.layer("right", 1.0))] = True  # the x dof of the right edge only
    free = np.flatnonzero(~fixed)
    K, reference = pair_operator(terms, free), scipy_pair_operator(terms, free, monkeypatch)
    assert K.has_sorted_indices and K.shape == reference.shape == (len(free), len(free))
    reference.sort_indices()
    assert np.array_equal(K.indptr, reference.indptr) and np.array_equal(K.indices, reference.indices)
    np.testing.assert_allclose(K.data, reference.data, rtol=0, atol=1e-14 * np.abs(reference.data).max())


def test_two_terms_with_shared_and_repeated_pairs_add_up(monkeypatch):
    """The bond rows given twice (two terms, weights w and 2 w) give 3x the one-term K_b; a
    negative weight leaves its row out, as in scipy's path."""
    p = bp.grid_2d(8.0, 6.0, 1.0)
    mat = bp.BondBased(p, bp.find_bonds(p, 2.2), plane="stress")
    (g, d, w), = [(g, d.numpy(), w.numpy()) for g, d, w in mat.terms({"K": 3000.0, "delta": 2.2})]
    free = np.arange(2 * p.n)
    one = pair_operator([(g, d, w)], free)
    w_neg = 2 * w.copy()
    w_neg[0] = -1.0
    three = pair_operator([(g, d, w), (g, d, w_neg)], free)
    reference = scipy_pair_operator([(g, d, w), (g, d, w_neg)], free, monkeypatch)
    reference.sort_indices()
    np.testing.assert_allclose(three.toarray(), reference.toarray(), rtol=0, atol=1e-13 * abs(reference).max())
    w_first = np.zeros_like(w)
    w_first[0] = 2 * w[0]
    first = pair_operator([(g, d, w_first)], free)
    np.testing.assert_allclose((three + first).toarray(), 3 * one.toarray(), rtol=0, atol=1e-13 * abs(one).max())


def test_no_bond_rows_is_refused():
    p = bp.grid_2d(4.0, 4.0, 1.0)
    mat = bp.BondBased(p, bp.find_bonds(p, 1.5), plane="stress")
    (g, d, w), = [(g, d.numpy(), w.numpy()) for g, d, w in mat.terms({"K": 3000.0, "delta": 1.5})]
    with pytest.raises(ValueError, match="no two-particle rows"):
        amg.pair_operator([(g, d, -np.ones_like(w))], np.arange(2 * p.n))


def test_a_kept_pattern_gives_a_fresh_assembly_at_new_weights():
    """K_b at a new horizon on the pattern kept from another horizon (``amg.pair_pattern``):
    bit for bit the K_b assembled afresh (the same loops in the same order)."""
    p = bp.grid_2d(14.0, 9.0, 1.0)
    mat = bp.LPS(p, bp.find_bonds(p, 2.6), plane="stress")
    free = np.flatnonzero(~np.repeat(p.layer("left", 1.0), 2))

    def terms(delta):
        return [(g, d.numpy(), w.numpy()) for g, d, w in mat.terms({"K": 3000.0, "G": 1500.0, "delta": delta})]

    pattern = amg.pair_pattern(terms(2.6), free)
    for delta in (2.6, 1.7):
        K, fresh = pair_operator(terms(delta), free, pattern), pair_operator(terms(delta), free)
        assert np.array_equal(K.indptr, fresh.indptr) and np.array_equal(K.indices, fresh.indices)
        assert np.array_equal(K.data, fresh.data)
    assert K.nnz < pair_operator(terms(2.6), free).nnz  # fewer nonzero bonds at 1.7: zeros dropped


@pytest.mark.parametrize("runs, threads", [(1, 1), (8, 2), (5, 2)])
def test_runs_and_threads_change_no_bit(runs, threads, monkeypatch):
    """K_b summed in one run on one thread, in 8 or 5 runs of particles on two: the same bits
    (each entry is summed over its bond rows in row order, whatever run holds its particle)."""
    p = bp.grid_2d(60.0, 40.0, 1.0)
    mat = bp.LPS(p, bp.find_bonds(p, 2.6), plane="stress", surface_correction=True)
    terms = [(g, d.numpy(), w.numpy()) for g, d, w in mat.terms({"K": 3000.0, "G": 1500.0, "delta": 2.6})]
    free = np.flatnonzero(~np.repeat(p.layer("left", 1.0), 2))
    reference = pair_operator(terms, free)
    monkeypatch.setattr(pair_loops, "RUNS", runs)
    monkeypatch.setattr(pair_loops, "MIN_INCIDENCES", 1)
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    pattern = amg.pair_pattern(terms, free)
    assert len(pattern.runs) == runs
    K = pair_operator(terms, free, pattern)
    assert np.array_equal(K.indptr, reference.indptr) and np.array_equal(K.indices, reference.indices)
    assert np.array_equal(K.data, reference.data)


def test_free_dofs_out_of_order_are_refused():
    p = bp.grid_2d(4.0, 4.0, 1.0)
    mat = bp.BondBased(p, bp.find_bonds(p, 1.5), plane="stress")
    terms = [(g, d.numpy(), w.numpy()) for g, d, w in mat.terms({"K": 3000.0, "delta": 1.5})]
    with pytest.raises(ValueError, match="increasing"):
        amg.pair_operator(terms, np.arange(2 * p.n)[::-1])
