"""Simulation-based calibration: the rank statistics (fast, on a conjugate Gaussian model
with exact posterior draws) and a small SBC of NUTS on the calibration plate (slow)."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
from bayespd.infer.calibration import chi2_power_overconfident, chi2_uniformity, rank, rank_counts, thin  # noqa: E402

L, BINS = 19, 5  # 20 possible ranks in 5 bins of 4


def conjugate_ranks(reps, seed, sd_factor=1.0, n_obs=10):
    """Ranks of mu* ~ N(0, 1) among L draws of N(posterior mean, (sd_factor x posterior sd)^2)
    given y_i ~ N(mu*, 1), i = 1..n_obs: uniform for sd_factor = 1."""
    rng = np.random.default_rng(seed)
    ranks = []
    for _ in range(reps):
        mu = rng.standard_normal()
        y = mu + rng.standard_normal(n_obs)
        precision = 1 + n_obs
        draws = y.sum() / precision + sd_factor * precision**-0.5 * rng.standard_normal(L)
        ranks.append(rank(mu, draws))
    return ranks


def test_exact_posterior_ranks_are_uniform():
    assert chi2_uniformity(conjugate_ranks(500, seed=3), L, BINS) > 1e-3


def test_overconfident_posterior_is_detected():
    """sd halved: the chi-square test at level 1e-3 with 500 ranks has power ~1 (computed)."""
    assert chi2_power_overconfident(500, BINS, 0.5, 1e-3) > 0.999
    assert chi2_uniformity(conjugate_ranks(500, seed=3, sd_factor=0.5), L, BINS) < 1e-3


def test_rank_and_bins():
    assert rank(0.5, [0.1, 0.7, 0.2]) == 2
    assert rank_counts([0, 3, 4, 19, 19], L, BINS).tolist() == [2, 1, 0, 0, 2]
    with pytest.raises(ValueError, match="equal bins"):
        rank_counts([0], 18, BINS)
    np.testing.assert_array_equal(thin(np.arange(100), 5), [0, 25, 50, 74, 99])


@pytest.mark.slow
def test_nuts_sbc_on_calibration_plate(tmp_path_factory):
    """50 prior draws of (K, G, sigma), one NUTS fit each (the settings of experiments/sbc.py):
    each parameter's ranks pass chi-square uniformity at level 0.01. Power of that test
    against a posterior with half the true sd: 0.76 (chi2_power_overconfident(50, 5, 0.5))."""
    from bayespd.scenes import calibration_scene as cs

    n = 50
    records = cs.replications("nuts", n, root=tmp_path_factory.getbasetemp() / "calibration", log=None)
    ok = cs.successful(records)
    assert len(ok) == n, [r["failed"] for r in records if "failed" in r]
    for k in cs.names(False):
        p = chi2_uniformity([r["params"][k]["rank"] for r in ok], cs.METHODS["nuts"]["rank_draws"], BINS)
        assert p > 0.01, (k, p)
