"""Sparse SPD solves (``bayespd.linalg.sparse``): patterns, and the BLAS threads of the
factorisation."""
import os
import pickle

import numpy as np
import pytest
import torch

from bayespd.linalg import sparse
from tests.linalg.linalg_systems import csc_pattern, grid_spd

BACKENDS = ["splu"] + (["cholmod"] if sparse.cholmod is not None else [])


def test_pattern_must_be_sorted():
    with pytest.raises(ValueError, match="sorted"):
        sparse.Pattern(np.array([1, 0]), np.array([0, 0]), 2)


@pytest.mark.skipif(sparse._OPENBLAS is None, reason="CHOLMOD's OpenBLAS is not loaded")
def test_factor_threads_keep_a_worker_limit():
    """factor_threads = None leaves a threadpoolctl limit in place (MCMC chain workers limit
    every BLAS to their share of the cores); a number sets the count and restores it after."""
    from threadpoolctl import threadpool_limits

    count = sparse._OPENBLAS.openblas_get_num_threads
    with threadpool_limits(1):
        with sparse.blas_threads(None):
            assert count() == 1
        if (os.cpu_count() or 1) >= 2:  # OpenBLAS may cap the count at the cores
            with sparse.blas_threads(2):
                assert count() == 2
        assert count() == 1


@pytest.mark.parametrize("backend", BACKENDS)
def test_factor_solves_to_rounding(backend):
    """A factor's solve has relative residual <= 1e-12 for one and several right-hand sides;
    ``Factor.cholmod`` is CHOLMOD's factor exactly when CHOLMOD made it."""
    spd = grid_spd()
    pattern, values = csc_pattern(spd)
    factor = pattern.factorize(values, backend)
    rhs = np.random.default_rng(0).standard_normal((spd.shape[0], 3))
    for b in (rhs, rhs[:, 0]):
        x = factor.solve(b)
        assert np.linalg.norm(spd @ x - b) <= 1e-12 * np.linalg.norm(b)
    assert (factor.cholmod is not None) == (backend == "cholmod")


def test_a_pcg_factor_is_freed_by_reference_counting():
    """No reference cycle holds a PCG factor (nor the operator and preconditioner it holds)
    once its last reference goes: a cycle waited for Python's rare full collection, and an
    experiment's solves piled up +300 MiB each (fe_convergence, 3D cantilever)."""
    import gc
    import weakref

    spd = grid_spd().tocsr()
    factor = sparse.PCGFactor(spd.__matmul__, lambda r: r / spd.diagonal(), spd.shape[0])
    b = np.ones(spd.shape[0])
    assert np.linalg.norm(spd @ factor.solve(b) - b) <= 1e-10 * np.linalg.norm(b)
    gone = weakref.ref(factor)
    gc.disable()
    try:
        del factor
        assert gone() is None
    finally:
        gc.enable()


def test_pcg_renews_its_preconditioner_at_the_limit():
    """With renew = (limit, make), a solve that reaches ``limit`` iterations unconverged goes on
    from its iterate with ``make()`` (called once): with the exact inverse that is one more
    iteration; the log gets the whole count, and a later solve starts with the new one."""
    spd = grid_spd().tocsc()
    exact = sparse.splu_factor(spd).solve
    made = []
    factor = sparse.PCGFactor(spd.__matmul__, lambda r: r, spd.shape[0], log=(log := []),
                              renew=(3, lambda: made.append(1) or exact))
    b = np.ones(spd.shape[0])
    x = factor.solve(b)
    assert np.linalg.norm(spd @ x - b) <= 1e-10 * np.linalg.norm(b)
    assert factor.renewed and made == [1] and factor.iterations == 4 and log == [4]
    factor.solve(2 * b)
    assert made == [1] and log == [4, 1]


def test_pattern_declares_its_node_blocks():
    """``blocks`` must describe the pattern it is given to (node count and block entries);
    a pickled pattern carries its blocks but not CHOLMOD's analysis."""
    spd = grid_spd()
    pattern, _ = csc_pattern(spd)
    n = pattern.n
    with pytest.raises(ValueError, match="blocks"):
        diagonal_blocks = sparse.NodeBlocks(2, np.arange(n // 2 + 1), np.arange(n // 2))
        sparse.Pattern(pattern.rows, pattern.cols, n, blocks=diagonal_blocks)
    blocks = sparse.NodeBlocks(2, np.array([0, 2, 4]), np.array([0, 1, 0, 1]))  # one full 4 x 4
    p = sparse.Pattern(np.tile(np.arange(4), 4), np.repeat(np.arange(4), 4), 4, blocks=blocks)
    p.factorize(torch.as_tensor((4 * np.eye(4) + 1).reshape(-1)))
    assert (p._symbolic is not None) == (sparse.default_backend() == "cholmod")
    copy = pickle.loads(pickle.dumps(p))
    assert copy.blocks.size == 2 and np.array_equal(copy.blocks.indices, blocks.indices)
    assert copy._symbolic is None
