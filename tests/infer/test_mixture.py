"""Posterior over separated modes: mode masses and the mixture of per-mode fits."""

import json
import math
import warnings
from functools import partial

import numpy as np
import pytest
import torch
from scipy.integrate import quad
from scipy.stats import multivariate_normal, norm

from bayespd.cli import main
from bayespd.infer import fit, save, summary
from bayespd.infer.mixture import allocate, cells, harmonic_log_mass, kept, laplace_log_mass, merged, stratified
from tests.infer.test_laplace import two_basins

DATA = {"y": torch.tensor(4.0)}
START = {"x": -0.5}  # the prior median: a single search descends into the -2 basin


def two_basin_potential(x, pull_sd):
    """U(x) of tests/test_laplace.two_basins, written out in numpy."""
    return -(norm.logpdf(x, -0.5, 2.0) + norm.logpdf(4.0, x**2, 0.5) + norm.logpdf(2.0, x, pull_sd))


def upper_basin_weight(pull_sd):
    """Exact posterior mass of x > 0 (the basins meet at x = 0, ~30 nats above both modes)."""
    density = lambda x: math.exp(-two_basin_potential(x, pull_sd) + 3.0)
    upper, lower = quad(density, 0, 10)[0], quad(density, -10, 0)[0]
    return upper / (upper + lower)


def test_harmonic_mean_recovers_the_normalising_constant():
    """exp(lp) = 7 N(z; m, S) in 3-D: from 4,000 exact draws the modified harmonic mean gives
    log 7 within 4 sd of its relative error sqrt((1 - level) / (level n)) = 0.016."""
    m, s = np.array([1.0, -2.0, 0.5]), np.array([[2.0, 0.6, 0.0], [0.6, 1.0, -0.3], [0.0, -0.3, 0.5]])
    z = multivariate_normal(m, s).rvs(4000, random_state=np.random.default_rng(3))
    lp = multivariate_normal(m, s).logpdf(z) + math.log(7.0)
    assert abs(harmonic_log_mass(z, lp) - math.log(7.0)) < 4 * math.sqrt(1 / 4000)


def test_laplace_mass_of_a_gaussian_is_exact_and_undefined_off_a_minimum():
    h = torch.tensor([[4.0, 1.0], [1.0, 3.0]])
    expected = -2.5 + math.log(2 * math.pi) - 0.5 * math.log(11.0)
    assert laplace_log_mass(2.5, h) == pytest.approx(expected, abs=1e-12)
    assert laplace_log_mass(2.5, -h) is None


def test_allocation_and_stratified_draws():
    counts = allocate([0.62, 0.3, 0.08], 50)
    assert counts.sum() == 50 and np.all(np.abs(counts - np.array([31, 15, 4])) <= 1)
    pooled = {"x": np.arange(20.0)}
    labels = np.array([0] * 12 + [1] * 8)
    out = stratified(pooled, labels, [2, 1], num_chains=2)["x"]
    assert out.tolist() == [[0, 4, 12], [7, 11, 19]]
    one = stratified(pooled, np.zeros(20, int), [10], num_chains=2)["x"]
    assert np.array_equal(one, pooled["x"].reshape(2, 10))  # one cell: the chains as they were


def test_each_draw_belongs_to_the_most_probable_mode():
    """x = 3 (1 from the narrow centre, 3 from the wide one) goes to the wide Gaussian:
    log densities -4.5 and -5.2 (log det terms 0 and 2.8); x = 3.5 to the narrow one."""
    centres, precisions = [np.zeros(2), np.array([4.0, 0.0])], [np.eye(2), 16 * np.eye(2)]
    z = np.array([[0.5, 0.0], [3.9, 0.0], [3.0, 0.0], [3.5, 0.0]])
    assert cells(z, centres, precisions).tolist() == [0, 1, 0, 1]


def test_cells_the_chains_move_between_are_joined():
    """Chains from mode 1 put 30 % of their draws in cell 0 (they cross): cells 0 and 1 are
    one; cell 2's chains put 2 % (under CROSSING) in cell 1: it stays apart."""
    groups = np.repeat([0, 1, 2], 100)
    labels = np.concatenate([np.zeros(100, int), [0] * 30 + [1] * 70, [1] * 2 + [2] * 98])
    joined, roots = merged(labels, groups, 3)
    assert roots == [0, 0, 2]
    assert np.array_equal(joined, np.where(labels == 1, 0, labels))


def test_modes_far_below_the_largest_mass_are_not_fitted():
    """Masses 0, -3 and -8 nats: the third holds under 1e-3 of the first; a mode on a kink
    (no Hessian) is judged by its potential with the lowest mode's curvature term."""
    modes = [(None, 1.0, None, None), (None, 4.0, None, None), (None, 9.0, None, None), (None, 3.0, None, None)]
    assert kept(modes, [0.0, -3.0, -8.0, None]) == [0, 1, 3]


@pytest.mark.parametrize("pull_sd", [pytest.param(2.0, marks=pytest.mark.slow), 1.5])  # 12 s each: one in the default run
def test_weighted_nuts_puts_each_basin_at_its_mass(pull_sd):
    """Two basins 1.5 and 3.1 nats apart. With modes='best' every draw is in the +2 basin;
    with modes='weighted' the share of draws in it is the exact posterior mass of x > 0 (by
    quadrature) within 0.06 (4 sd of the harmonic-mean error of ~8 % on the mass ratio at
    2 x 300 draws per mode, plus 1/600 of allocation)."""
    model = partial(two_basins, pull_sd=pull_sd)
    options = dict(num_samples=300, num_warmup=200, num_chains=2, chains="sequential", init="map",
                   map_starts=8, init_values=START, progress=False, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # modes within 3 nats (at pull_sd 2)
        best = fit(model, DATA, "nuts", **options)
    assert float((best["posterior"]["x"] > 0).mean()) == 1.0
    weighted = fit(model, DATA, "nuts", modes="weighted", **options)
    share = float((weighted["posterior"]["x"] > 0).mean())
    assert abs(share - upper_basin_weight(pull_sd)) < 0.06, (share, upper_basin_weight(pull_sd))
    record = json.loads(weighted.attrs["mode_weights"])
    assert [round(m["values"]["x"]) for m in record] == [2, -2]
    assert sum(m["draws"] for m in record) == 300
    assert weighted["posterior"]["x"].shape == (2, 300)


def test_weighted_laplace_mixes_the_modes_by_their_laplace_mass(tmp_path, capsys):
    """The share of draws at each mode is the Laplace-mass weight, computed here from the
    numpy potential (Hessian by central differences), to the allocation's 1/400; summary()
    and `bayespd summary` (after a NetCDF round trip) list the modes with their weights."""
    model = partial(two_basins, pull_sd=2.0)
    tree = fit(model, DATA, "laplace", num_samples=400, map_starts=8, modes="weighted",
               init_values=START, progress=False)
    record = json.loads(tree.attrs["mode_weights"])
    masses = []
    for m in record:
        x, e = m["values"]["x"], 1e-4
        u = partial(two_basin_potential, pull_sd=2.0)
        curvature = (u(x + e) - 2 * u(x) + u(x - e)) / e**2
        masses.append(-u(x) + 0.5 * math.log(2 * math.pi / curvature))
    weight = 1 / (1 + math.exp(masses[1] - masses[0]))
    assert float((tree["posterior"]["x"] > 0).mean()) == pytest.approx(weight, abs=1 / 400 + 1e-3)
    assert record[0]["weight"] == pytest.approx(weight, abs=1e-5)
    table = summary(tree).attrs["modes"]  # the same record, one row per mode, for the user
    assert table["weight"].tolist() == [m["weight"] for m in record]
    assert table["x"].tolist() == [m["values"]["x"] for m in record]
    assert table["draws"].sum() == 400
    assert sorted(np.sign(table["x"])) == [-1, 1]
    save(tree, tmp_path / "posterior.nc")
    assert main(["summary", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "a mixture of 2 modes" in out and f"{record[0]['weight']:.6f}"[:6] in out


def test_weighted_modes_refused_where_they_cannot_work():
    model = partial(two_basins, pull_sd=2.0)
    for method, extra in (("svi", {"init": "map"}), ("nuts", {"init": "map"}),
                          ("hmc", {"init": "median"}), ("laplace", {})):
        with pytest.raises(ValueError, match="map_starts >= 2"):
            fit(model, DATA, method, modes="weighted", progress=False, **extra)
    with pytest.raises(ValueError, match="modes must be one of"):
        fit(model, DATA, "laplace", modes="all", progress=False)


def test_weighted_svi_mixes_the_guides_by_their_evidence():
    """A full-rank Gaussian guide from each mode, weighted by its importance-sampling
    evidence: the share of draws at +2 is the exact mass of x > 0 within 0.05 (each basin is
    near Gaussian, so the per-mode evidence is nearly exact; 400 draws give a Monte-Carlo
    error under 1 % and 1/400 of allocation), where modes='best' puts every draw there."""
    model = partial(two_basins, pull_sd=2.0)
    options = dict(num_samples=400, svi_steps=400, init="map", map_starts=8, init_values=START,
                   progress=False, seed=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the modes lie within 3 nats
        best = fit(model, DATA, "svi", **options)
    assert float((best["posterior"]["x"] > 0).mean()) == 1.0
    weighted = fit(model, DATA, "svi", modes="weighted", **options)
    share = float((weighted["posterior"]["x"] > 0).mean())
    assert abs(share - upper_basin_weight(2.0)) < 0.05, (share, upper_basin_weight(2.0))
    assert weighted["sample_stats"]["svi_loss"].shape[-2:] == (2, 400)


def test_one_mode_weighted_is_the_plain_fit_bit_for_bit():
    """A unimodal posterior (the linear Gaussian model): every search ends at one mode, and
    the weighted fit's chains are the plain fit's, draw for draw."""
    from tests.infer.test_laplace import Y, linear

    start = {"theta": [0.5, -1.0, 2.0], "s": 1.0}  # not Pyro's median of random prior draws
    options = dict(num_samples=50, num_warmup=50, num_chains=2, chains="sequential", init="map",
                   map_starts=3, mass_matrix_from="laplace", progress=False, seed=4, init_values=start)
    plain = fit(linear, {"y": Y}, "nuts", **options)
    weighted = fit(linear, {"y": Y}, "nuts", modes="weighted", **options)
    assert len(json.loads(weighted.attrs["mode_weights"])) == 1
    assert np.array_equal(plain["posterior"]["theta"].values, weighted["posterior"]["theta"].values)
