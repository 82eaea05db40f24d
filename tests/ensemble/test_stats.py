"""bayespd/ensemble/stats.py: the aggregate of crack-ensemble realisations (the law of total
variance split, path bands, damage probabilities) and its helpers."""
import numpy as np
import pytest

from bayespd.ensemble.scene import FractureScene
from bayespd.ensemble.stats import (QUANTILES, aggregate, load_step_lengths, offsets, padded, quantiles, sd,
                                    stations_for)


def _fake(phi, path, outcome):
    """A realisation result with the given phi, path and scalar outcome (all outcomes)."""
    lam = np.array([1.0, 1.0, 2.0, 3.0])
    return {"t": np.arange(4.0), "load_factor": lam, "reaction": np.zeros((4, 2)), "broken": np.zeros(4, np.int64),
            "crack_length": np.array([0.0, 1.0, 2.0, 4.0]), "phi": phi, "path": path,
            **{k: outcome for k in ("peak_load", "peak_load_factor", "failure_load_factor",
                                    "final_crack_length", "first_failure_time")}, "wall_time_s": 0.0, "cpu_time_s": 0.0}


def test_aggregate_splits_total_spread_into_aleatoric_and_epistemic():
    """Outcome Y = a(params) + e with sd(a) = 2, sd(e) = 1: the posterior ensemble's sd is
    sqrt(5), the mean ensemble's 1, the epistemic part 2 (law of total variance); 2000
    realisations each: the sd estimates are within 4 sd(s) = 4 s / sqrt(2 n) < 0.07 of it.
    Straight paths at offset c across the crack line have band quantiles those of c;
    P(phi > 0.4) is the fraction of realisations above the threshold."""
    rng = np.random.default_rng(1)
    n, x = 2000, np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    scene = FractureScene(lambda p: None, ("K",), [1.0, 2.0, 3.0], 1.0, x, origin=(0.0, 1.0))
    results = []
    for kind, epistemic in (("posterior", 2.0), ("mean", 0.0)):
        y = epistemic * rng.standard_normal(n) + rng.standard_normal(n)
        c = rng.standard_normal(n)
        phi = rng.uniform(size=(n, 3)) * [0.5, 1.0, 0.0]  # P(phi > 0.4): 0.2, 0.6, 0
        for i in range(n):
            path = np.array([[0.0, 1 + c[i]], [5.0, 1 + c[i]], [10.0, 1 + c[i]]])
            results.append((kind, i, _fake(phi[i], path, y[i]), {"K": 1.0}, i, i))
    ds = aggregate(results, scene, seed=0)
    spread = ds["spread"].sel(outcome="failure_load_factor")
    assert spread.sel(source="total") == pytest.approx(np.sqrt(5), abs=4 * np.sqrt(5) / np.sqrt(2 * n))
    assert spread.sel(source="aleatoric") == pytest.approx(1.0, abs=4 / np.sqrt(2 * n))
    assert spread.sel(source="epistemic") == pytest.approx(2.0, abs=0.15)
    c_post = [r[2]["path"][0, 1] - 1 for r in results if r[0] == "posterior"]
    band = ds["path_quantiles"].sel(kind="posterior")
    assert np.allclose(band.values, np.quantile(c_post, [0.05, 0.5, 0.95])[:, None], atol=1e-12)
    assert np.all(ds["path_coverage"].values == 1.0)
    assert np.allclose(ds["probability"].values, [[0.2, 0.6, 0.0]] * 2, atol=0.04)  # 4 binomial sd at n = 2000
    assert ds["probability"].sel(kind="mean").values[0] == np.mean(
        [r[2]["phi"][0] > 0.4 for r in results if r[0] == "mean"])
    assert np.array_equal(ds["crack_length_at_load"].values[0], [0.0, 1.0, 2.0, 4.0][1:])


def test_offsets_across_a_slanted_line_and_step_lengths():
    """A path on the line y = x + 1 seen from origin (0, 0) along (1, 1)/sqrt2 has offset
    1/sqrt2 everywhere it reaches, NaN beyond, whatever its point order; with ``hold`` the
    crack length of a load step is the one at its last repeat."""
    path = np.array([[3.0, 4.0], [0.0, 1.0], [1.0, 2.0]])
    s = np.array([-1.0, 1.0, 2.0, 4.0, 6.0])
    o = offsets(path, np.zeros(2), np.array([1.0, 1.0]) / np.sqrt(2), s)
    inside = (s >= 1 / np.sqrt(2)) & (s <= 7 / np.sqrt(2))
    assert np.allclose(o[inside], 1 / np.sqrt(2), atol=1e-14) and np.all(np.isnan(o[~inside]))
    lengths = load_step_lengths(np.array([1.0, 2.0, 2.0, 2.0, 3.0]), np.array([0, 1, 2, 3, 3.5]), [1.0, 2.0, 3.0, 4.0])
    assert np.array_equal(lengths[:3], [0, 3, 3.5]) and np.isnan(lengths[3])


def test_quantiles_and_sd_ignore_non_finite_values():
    """NaN and inf are dropped before the 5/50/95 % quantiles and the sample sd (ddof = 1);
    nothing finite gives NaN (and one value an undefined sd)."""
    v = np.array([1.0, np.nan, 2.0, np.inf, 3.0, 4.0, -np.inf])
    np.testing.assert_allclose(quantiles(v), np.quantile([1.0, 2.0, 3.0, 4.0], QUANTILES), rtol=1e-15)
    assert sd(v) == pytest.approx(np.std([1.0, 2.0, 3.0, 4.0], ddof=1), rel=1e-15)
    assert np.all(np.isnan(quantiles([np.nan]))) and np.isnan(sd([5.0])) and np.isnan(sd([]))


def test_padded_stacks_ragged_arrays_with_a_fill():
    out = padded([np.ones((2, 2)), np.zeros((0, 2)), 2 * np.ones((3, 2))])
    assert out.shape == (3, 3, 2)
    assert np.all(out[0, :2] == 1) and np.all(np.isnan(out[0, 2])) and np.all(np.isnan(out[1]))
    ints = padded([np.array([1, 2]), np.array([3])], -1, np.int64)
    np.testing.assert_array_equal(ints, [[1, 2], [3, -1]])


def test_stations_span_the_paths_along_the_crack_direction():
    """Stations run from the smallest to the largest projection of any path (of at least two
    points) on the direction, measured from the origin; no path: one station at 0."""
    scene = FractureScene(print, ("K",), [1.0], 1.0, np.zeros((3, 2)), origin=(1.0, 0.0), direction=(0.0, 2.0))
    paths = [np.array([[0.0, 2.0], [0.0, 5.0]]), np.array([[3.0, -1.0], [3.0, 1.0]]), np.zeros((1, 2))]
    s = stations_for(scene, paths, count=5)
    np.testing.assert_allclose(s, np.linspace(-1.0, 5.0, 5), rtol=1e-15)
    np.testing.assert_array_equal(stations_for(scene, [np.zeros((1, 2))]), [0.0])


def test_failed_realisations_are_counted_and_all_failed_is_refused():
    """A realisation given as {"error": ...} is kept out of the statistics but named in the
    attributes; when every one failed, aggregate refuses with a message that says where to look."""
    scene = FractureScene(print, ("K",), [1.0, 2.0, 3.0], 1.0, np.zeros((3, 2)))
    good = [(kind, i, _fake(np.full(3, 0.5), np.array([[0.0, 0.0], [1.0, 0.0]]), 1.0), {"K": 1.0}, i, i)
            for kind in ("posterior", "mean") for i in range(2)]
    bad = ("posterior", 2, {"error": "diverged"}, {"K": 1.0}, 2, 2)
    ds = aggregate(good + [bad], scene, seed=4)
    assert ds.sizes["realisation"] == 4 and ds.attrs["failed"] == 1
    assert ds.attrs["failed_realisations"] == "posterior-2: diverged" and ds.attrs["seed"] == 4
    assert ds.attrs["realisations_posterior"] == ds.attrs["realisations_mean"] == 2
    with pytest.raises(ValueError, match="every realisation failed"):
        aggregate([bad], scene, seed=0)
    wrong = FractureScene(print, ("K",), [1.0], 1.0, np.zeros((5, 2)))
    with pytest.raises(ValueError, match="3 particles, the scene's x 5"):
        aggregate(good, wrong, seed=0)
