"""``bayespd.infer.search.Search``: the MAP searches of one fit. ``map_init`` starts at the
exact mode of a conjugate model and records it; ``modes_to_fit`` keeps the modes worth fitting
with their Laplace masses (exact for a Gaussian); ``record_weights`` writes the weights."""
import json
import math
from functools import partial

import numpy as np
import pyro
import pyro.distributions as dist
import pytest
import torch
from pyro.infer.autoguide.initialization import init_to_value

from bayespd.infer import NUTS, fit
from bayespd.infer.search import Search
from bayespd.infer.space import init_trace
from tests.infer.test_laplace import two_basins

Y = torch.tensor(3.0)


def gauss(y=None):
    """x ~ N(0, 1), y ~ N(x, 1): posterior N(y/2, 1/2)."""
    x = pyro.sample("x", dist.Normal(0.0, 1.0))
    pyro.sample("y", dist.Normal(x, 1.0), obs=y)


START = init_to_value(values={"x": torch.tensor(-4.0)})


def test_search_of_a_method_takes_its_settings():
    s = Search.of(NUTS(init="map", map_starts=6, seed=3, progress=False, modes="weighted"))
    assert (s.starts, s.seed, s.progress, s.weighted, s.modes, s.weights) == (6, 3, False, True, None, None)
    assert Search.of(NUTS(progress=False)).weighted is False


def test_map_init_starts_at_the_exact_mode_and_records_it():
    s = Search(starts=3, seed=0, progress=False)
    init = s.map_init(gauss, {"y": Y}, START)
    x = init_trace(gauss, {"y": Y}, init).nodes["x"]["value"]
    assert float(x) == pytest.approx(1.5, abs=1e-7)
    (mode,) = json.loads(s.modes)
    assert mode["values"]["x"] == pytest.approx(1.5, abs=1e-7)
    # U at the mode: -log N(1.5 | 0, 1) - log N(3 | 1.5, 1) (x is unconstrained: no Jacobian)
    assert mode["potential"] == pytest.approx(1.5**2 + math.log(2 * math.pi), rel=1e-10)


def test_modes_to_fit_and_their_weights_on_two_basins():
    """pull_sd = 2: the two basins lie 1.5 nats apart, so both are worth fitting; their
    Laplace log masses differ by about the potential gap, and the weights recorded sum to 1."""
    model, data = partial(two_basins, pull_sd=2.0), {"y": torch.tensor(4.0)}
    s = Search(starts=8, seed=0, progress=False, weighted=True)
    space, fitted, masses, evaluations = s.modes_to_fit(model, data, init_to_value(values={"x": torch.tensor(-0.5)}),
                                                        "y", "exact")
    assert [round(float(z)) for z, *_ in fitted] == [2, -2] and evaluations > 8
    assert [round(m["values"]["x"]) for m in json.loads(s.modes)] == [2, -2]
    for (z, u, g, h), m in zip(fitted, masses):  # log mass = -U + (d/2) log 2 pi - log det(H) / 2
        assert m == pytest.approx(-u + 0.5 * math.log(2 * math.pi) - 0.5 * math.log(float(h)), rel=1e-12)
    s.record_weights(space, fitted, masses, masses, [30, 10])
    table = json.loads(s.weights)
    np.testing.assert_allclose([t["weight"] for t in table], np.exp(masses) / np.exp(masses).sum(), rtol=1e-12)
    assert [t["draws"] for t in table] == [30, 10] and table[0]["log_mass"] == masses[0]


def test_a_fit_records_the_searched_mode():
    """A Laplace fit (which always searches) hands the Search's modes to the tree (``map_modes``)."""
    tree = fit(gauss, {"y": Y}, "laplace", num_samples=5, map_starts=2, progress=False)
    (mode,) = json.loads(tree.attrs["map_modes"])
    assert mode["values"]["x"] == pytest.approx(1.5, abs=1e-7)
