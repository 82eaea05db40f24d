"""``bayespd.infer.priors.ScaledBeta``: low + (high - low) Beta(a, b) with support
interval(low, high), against scipy.stats.beta with loc and scale."""
import math

import numpy as np
import pyro
import pyro.distributions as dist
import pytest
import torch
from scipy import stats
from torch.distributions import biject_to, constraints

from bayespd.infer import ScaledBeta
from tests.infer.test_fit import HIGH, LOW


@pytest.mark.parametrize("a,b", [(2.0, 2.0), (2.0, 3.0), (0.7, 1.5)])
def test_log_prob_mean_and_variance_are_scipy_beta_scaled(a, b):
    d = ScaledBeta(LOW, HIGH, a, b)
    ref = stats.beta(a, b, loc=LOW, scale=HIGH - LOW)
    x = np.linspace(LOW + 1e-3, HIGH - 1e-3, 11)
    np.testing.assert_allclose(d.log_prob(torch.as_tensor(x)).numpy(), ref.logpdf(x), rtol=1e-12, atol=1e-12)
    assert float(d.mean) == pytest.approx(ref.mean(), rel=1e-14)
    assert float(d.variance) == pytest.approx(ref.var(), rel=1e-13)
    assert (float(d.concentration1), float(d.concentration0)) == (a, b)


def test_batched_bounds_broadcast_and_expand():
    d = ScaledBeta(torch.tensor([0.0, 1.0]), torch.tensor([1.0, 3.0]))
    assert d.batch_shape == (2,)
    np.testing.assert_allclose(d.mean.numpy(), [0.5, 2.0], rtol=1e-15)
    x = torch.tensor([0.25, 2.5])
    np.testing.assert_allclose(d.log_prob(x).numpy(), [stats.beta(2, 2).logpdf(0.25),
                                                       stats.beta(2, 2, loc=1, scale=2).logpdf(2.5)], rtol=1e-12)
    e = ScaledBeta(LOW, HIGH).expand([4])
    assert isinstance(e, ScaledBeta) and e.batch_shape == (4,) and e.sample().shape == (4,)
    with pytest.raises(ValueError, match="high > low"):
        ScaledBeta(torch.tensor([0.0, 2.0]), torch.tensor([1.0, 2.0]))


# moved from tests/infer/test_fit.py
def test_scaled_beta():
    d = ScaledBeta(LOW, HIGH, 2.0, 3.0)
    x = torch.linspace(0.6, 1.9, 7)
    beta = dist.Beta(2.0, 3.0)
    expected = beta.log_prob((x - LOW) / (HIGH - LOW)) - math.log(HIGH - LOW)
    torch.testing.assert_close(d.log_prob(x), expected)
    assert isinstance(d.support, constraints.interval)
    assert (d.support.lower_bound, d.support.upper_bound) == (LOW, HIGH)
    to_x = biject_to(d.support)  # what NUTS and the autoguides use
    ends = to_x(torch.tensor([-40.0, 0.0, 40.0]))
    assert ends[0] >= LOW and ends[2] <= HIGH and ends[1] == pytest.approx((LOW + HIGH) / 2)
    torch.testing.assert_close(to_x.inv(x), torch.logit((x - LOW) / (HIGH - LOW)))
    pyro.set_rng_seed(0)
    draws = d.sample((20000,))
    assert float(draws.min()) > LOW and float(draws.max()) < HIGH
    assert float(d.mean) == pytest.approx(LOW + (HIGH - LOW) * 2 / 5)
    mcse = math.sqrt(float(d.variance) / 20000)
    assert float(draws.mean()) == pytest.approx(float(d.mean), abs=4 * mcse)
    assert d.expand([3]).sample().shape == (3,)
    with pytest.raises(ValueError):
        ScaledBeta(2.0, 1.0)
