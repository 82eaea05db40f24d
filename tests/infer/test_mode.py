"""``bayespd.infer.mode``: the MAP search on the unconstrained space (L-BFGS restarted, then
Newton), its warnings at kinks, its back-off from refused parameters, the Latin-hypercube prior
starts, the barrier test that tells modes apart, and the modes' JSON."""
import json
import warnings
from functools import partial

import numpy as np
import pyro
import pyro.distributions as dist
import pytest
import torch
from pyro.infer.autoguide.initialization import init_to_median, init_to_value

from bayespd.infer.mode import distinct_modes, find_map, modes_json, prior_starts, separated
from bayespd.infer.space import Unconstrained
from bayespd.materials import ParameterRangeError
from tests.infer.test_laplace import two_basins


def test_newton_steps_reach_the_mode_of_a_quadratic_exactly():
    """U(z) = (z - m)^T P (z - m) / 2: with the exact Hessian the Newton step lands on m to
    rounding (1e-12), the gradient vanishes, and the Hessian returned is P."""
    P = torch.tensor([[4.0, 1.0], [1.0, 3.0]])
    m = torch.tensor([0.7, -1.2])
    space = _Potential(lambda z: 0.5 * (z - m) @ P @ (z - m), [5.0, 5.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        z, u, g, h, evaluations = find_map(space, hessian_fn=lambda z: P, progress=False)
    torch.testing.assert_close(z, m, rtol=0, atol=1e-12)
    assert u <= 1e-24 and float(g.abs().max()) <= 1e-12 and torch.equal(h, P) and evaluations >= 2


def gauss(y=None):
    x = pyro.sample("x", dist.Normal(0.0, 1.0))
    pyro.sample("y", dist.Normal(x, 1.0), obs=y)


def test_one_basin_is_one_mode_and_bad_start_counts_are_refused():
    """A conjugate model (posterior N(y/2, 1/2)): four starts end at the one mode x = y/2."""
    data = {"y": torch.tensor(3.0)}
    init = init_to_value(values={"x": torch.tensor(-4.0)})
    space = Unconstrained(gauss, data, init)
    modes, evaluations = distinct_modes(space, gauss, data, init, starts=4, seed=1, progress=False)
    assert len(modes) == 1 and evaluations > 4
    assert float(modes[0][0]) == pytest.approx(1.5, abs=1e-6)
    for bad in (0, 1.5):
        with pytest.raises(ValueError, match="number of MAP starts must be a positive integer"):
            distinct_modes(space, gauss, data, init, starts=bad, progress=False)


def test_two_basins_are_two_modes_listed_lowest_first_as_json():
    """The two-basin model of tests/infer/test_laplace.py with pull_sd = 1: modes near +2
    (lower) and -2, 7.5 nats apart, no warning (more than MODE_GAP = 3 nats)."""
    model, data = partial(two_basins, pull_sd=1.0), {"y": torch.tensor(4.0)}
    init = init_to_value(values={"x": torch.tensor(-0.5)})
    space = Unconstrained(model, data, init)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        modes, _ = distinct_modes(space, model, data, init, starts=8, seed=0, progress=False)
    assert [round(float(m[0])) for m in modes] == [2, -2]
    table = json.loads(modes_json(space, modes, weight=[0.9, 0.1]))
    assert [round(t["values"]["x"]) for t in table] == [2, -2] and [t["weight"] for t in table] == [0.9, 0.1]
    assert table[0]["potential"] == modes[0][1] < table[1]["potential"]
    assert abs(table[1]["potential"] - table[0]["potential"] - 7.5) < 0.5


# moved from tests/infer/test_laplace.py
class _Potential:
    """A duck-typed unconstrained space: ``initial`` and ``potential(z)``."""

    def __init__(self, f, start):
        self.initial = torch.tensor(start, dtype=torch.float64)
        self.potential = f


def test_map_search_warns_when_it_ends_on_a_kink():
    """|z - 1| + z^2/100 has its minimum on a kink at z = 1 (|grad| there is about 1, not
    0): the search must say so; the smooth (z - 1)^2 must not warn."""
    kink = _Potential(lambda z: (z - 1).abs().sum() + (z**2).sum() / 100, [4.0])
    with pytest.warns(RuntimeWarning, match="gradient does not vanish"):
        z, *_ = find_map(kink, progress=False)
    assert abs(float(z[0]) - 1) < 1e-6
    smooth = _Potential(lambda z: ((z - 1) ** 2).sum(), [4.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        z, *_ = find_map(smooth, progress=False)
    assert abs(float(z[0]) - 1) < 1e-6


@pytest.mark.parametrize("error", [ParameterRangeError, torch.linalg.LinAlgError])
def test_map_search_backs_off_from_refused_parameters(error):
    """A trial point the model refuses (a modulus over- or underflowed; a likelihood covariance
    not positive definite there, as torch's Cholesky reports it) is an infinite potential, not
    an error: (z - 3)^2 with every z > 2 refused ends near 2, from below."""
    refused = []

    def f(z):
        if float(z.detach().max()) > 2:
            refused.append(float(z.detach().max()))
            raise error("refused")
        return ((z - 3) ** 2).sum()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # it ends on the boundary, not a mode
        z, *_ = find_map(_Potential(f, [0.0]), progress=False)
    assert refused, "the search never tried a refused point: the test does not test"
    assert 1.9 < float(z[0]) <= 2


def test_a_refused_newton_step_shrinks_the_trust_region_not_raised():
    """U = log cosh(z - 1) with z > 3 refused (as a kernel with m <= 0 is): L-BFGS stopped
    after one iteration at z = -1, where the exact Newton step is s = tanh(2) cosh^2(2) =
    sinh(2) cosh(2) = 13.6 (the first trust radius). z = -1 + s is refused (no error raised),
    so the radius falls to s/4 and the next trial is -1 + s/4 = 2.41, which is accepted; the
    polish then reaches the mode z = 1 (|grad| to rounding, no warning)."""
    tried = []

    def f(z):
        tried.append(float(z.detach()[0]))
        if float(z.detach().max()) > 3:
            raise ParameterRangeError("the weighted volume m must be positive")
        return torch.log(torch.cosh(z - 1)).sum()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        z, u, g, h, _ = find_map(_Potential(f, [-6.0]), hessian_fn=lambda z: torch.diag(torch.cosh(z - 1) ** -2),
                                 max_iter=1, restarts=1, progress=False)
    s = float(np.sinh(2.0) * np.cosh(2.0))
    start = next(i for i, t in enumerate(tried) if t == pytest.approx(-1 + s, rel=1e-12))
    assert tried[start:start + 2] == pytest.approx([-1 + s, -1 + s / 4], rel=1e-12)
    assert abs(float(z[0]) - 1) < 1e-9 and float(g.abs().max()) < 1e-9


def test_prior_starts_are_a_latin_hypercube():
    """Eight starts of two independent sites: each site has exactly one start in each
    eighth of its prior (CDF values, up to 4 sd of the empirical quantile of 128 draws),
    and the two sites' bands are not paired in order."""
    def model():
        pyro.sample("a", dist.Normal(0.0, 1.0))
        pyro.sample("b", dist.LogNormal(1.0, 0.5))

    space = Unconstrained(model, {}, init_to_median)
    z = torch.stack(prior_starts(space, model, {}, init_to_median, 8, seed=4))
    values = space.constrain(z)
    cdf = {"a": dist.Normal(0.0, 1.0).cdf(values["a"]), "b": dist.Normal(1.0, 0.5).cdf(values["b"].log())}
    centres = (np.arange(8) + 0.5) / 8
    sd = np.sqrt(centres * (1 - centres) / 128)
    for k in cdf:
        got = np.sort(cdf[k].numpy())
        assert np.all(np.abs(got - centres) <= 4 * sd), (k, got)
    assert not np.array_equal(np.argsort(values["a"].numpy()), np.argsort(values["b"].numpy()))


def test_search_ends_are_one_mode_unless_a_barrier_separates_them():
    """On the two-basin model: x = 1.9 and x = 2.0 (one basin) are one mode, x = -2 and
    x = +2 are two (the potential at x = 0 is ~32 nats above them)."""
    space = Unconstrained(partial(two_basins, pull_sd=2.0), {"y": torch.tensor(4.0)}, init_to_median)

    def at(x):
        z = torch.tensor([x], dtype=torch.float64)
        return z, float(space.potential(z))

    assert not separated(space, *at(1.9), *at(2.0))
    assert separated(space, *at(-2.0), *at(2.0))
