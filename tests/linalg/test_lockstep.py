"""Runs in lock-step (``solvers.lockstep``): shared half solves in blocks of a fixed width give
each job the bits it gets alone, one block call per round, and failures stay with their job."""
import numpy as np
import pytest
import scipy.sparse as sp

from bayespd.scenes.notched_plate import notched_plate
from bayespd.ensemble.scene import realise, realise_batch
from bayespd.linalg import lockstep, trailing
from bayespd.linalg.lockstep import LockStep

N = 60
A = np.eye(N) * 4 + np.diag(np.full(N - 1, -1.0), 1) + np.diag(np.full(N - 1, -1.0), -1)


def solver(calls):
    def solve(block):
        calls.append(block.shape[1])
        return np.linalg.solve(A, block)
    return solve


def job(seed, solves, calls, fail_at=None):
    """``solves`` solves of random vectors through the round, with work of its own between."""
    def run():
        rng = np.random.default_rng(seed)
        x = np.zeros(N)
        for k in range(solves):
            if k == fail_at:
                raise FloatingPointError(f"job {seed} failed")
            x = lockstep.current().solve("A", solver(calls), rng.standard_normal(N) + 0.5 * x)
        return x
    return run


def test_jobs_get_their_bits_alone_and_share_one_block_call_per_round():
    calls = []
    together = LockStep(4).run([job(s, n, calls) for s, n in ((1, 5), (2, 3), (3, 7), (4, 1), (5, 4))])
    # rounds 1-7 have 5, 4, 4, 3, 2, 1, 1 jobs waiting: 2 blocks, then 1 a round, all 4 wide
    assert calls == [4] * 8
    for (s, n), x in zip(((1, 5), (2, 3), (3, 7), (4, 1), (5, 4)), together):
        (alone,) = LockStep(4).run([job(s, n, [])])
        assert np.array_equal(x, alone)  # the same bits in any company
        rng, y = np.random.default_rng(s), np.zeros(N)
        for _ in range(n):
            y = np.linalg.solve(A, rng.standard_normal(N) + 0.5 * y)
        assert np.abs(x - y).max() <= 1e-12 * np.abs(y).max()


def test_a_failing_job_keeps_its_error_and_the_others_finish():
    calls = []
    out = LockStep(2).run([job(1, 4, calls), job(2, 4, calls, fail_at=2), job(3, 6, calls)])
    assert isinstance(out[1], FloatingPointError) and "job 2" in str(out[1])
    assert all(isinstance(x, np.ndarray) for x in (out[0], out[2]))
    (alone,) = LockStep(2).run([job(3, 6, [])])
    assert np.array_equal(out[2], alone)
    with pytest.raises(ValueError, match="positive integer"):
        LockStep(0)


@pytest.mark.skipif(not trailing.available(), reason="the trailing factor needs CHOLMOD")
def test_trailing_half_solves_join_the_round():
    """TrailingFactor.forward / backward of one vector inside a run go through the round (one
    block call for all jobs) and agree with the solve outside it to rounding."""
    M = sp.csc_matrix(A)
    f = trailing.TrailingFactor(M, np.arange(N - 10, N))
    rhs = np.random.default_rng(0).standard_normal((N, 3))
    widths = []
    raw = f._forward

    def counted(block):
        widths.append(np.shape(block))
        return raw(block)

    f._forward = counted
    out = LockStep(8).run([lambda c=c: f.solve(rhs[:, c]) for c in range(3)])
    assert widths == [(N, 8)]
    for c in range(3):
        assert np.abs(out[c] - f.solve(rhs[:, c])).max() <= 1e-13 * np.abs(out[c]).max()


@pytest.mark.skipif(not trailing.available(), reason="the zone (and its shared factor) needs CHOLMOD")
def test_a_realisation_in_a_batch_is_the_realisation_alone():
    """Three realisations of the notched plate in lock-step give, each, the same bits as run
    alone (what makes the Dask and local ensembles identical and any realisation re-runnable)."""
    scene = notched_plate(side=16.0, h=1.0, steps=20, sigma=100.0)
    items = [({"K": 2500.0, "s0": 0.0094}, 5), ({"K": 3000.0, "s0": 0.0090}, 6), ({"K": 2000.0, "s0": 0.0100}, 7)]
    batch = realise_batch(scene, items)
    for (params, seed), together in zip(items, batch):
        alone = realise(scene, params, seed)
        assert together["broken"][-1] > 0
        for key in ("reaction", "phi", "broken", "crack_length", "path"):
            assert np.array_equal(together[key], alone[key]), key
