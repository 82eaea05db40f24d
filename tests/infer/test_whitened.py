import pyro
import pyro.distributions as dist
import pytest
import torch
from pyro.infer.autoguide.initialization import init_to_median

from bayespd.infer.laplace import Gaussian
from bayespd.infer.space import Unconstrained
from bayespd.infer.whitened import AutoWhitenedMVN


def model():
    """Sites in model order s > 0, b (2,); the space sorts them b, s."""
    pyro.sample("s", dist.LogNormal(0.0, 1.0))
    pyro.sample("b", dist.Normal(torch.zeros(2), 1.0).to_event(1))


def laplace_like(space):
    """A Gaussian with distinct means, scales and correlations on the space's (b0, b1, s)."""
    a = torch.tensor([[2.0, 0.0, 0.0], [0.7, 1.5, 0.0], [-0.4, 0.3, 0.5]])
    return Gaussian(torch.tensor([0.3, -1.2, 0.8]), a @ a.T, space.labels)


def test_the_guide_starts_at_the_laplace_gaussian_in_the_guides_site_order():
    """Before any step the guide is N(m, Sigma) exactly, coordinates permuted from the space's
    sorted (b, s) to the model's (s, b) order."""
    space = Unconstrained(model, {}, init_to_median)
    gaussian = laplace_like(space)
    guide = AutoWhitenedMVN(model, init_to_median, space, gaussian)
    guide()
    q = guide.get_posterior()
    order = torch.tensor([2, 0, 1])
    torch.testing.assert_close(q.loc, gaussian.mean[order], rtol=0, atol=1e-12)
    torch.testing.assert_close(q.covariance_matrix, gaussian.covariance[order][:, order], rtol=1e-12, atol=1e-12)
    b, s = guide.median()["b"], guide.median()["s"]
    torch.testing.assert_close(b, gaussian.mean[:2], rtol=0, atol=1e-12)
    torch.testing.assert_close(s, gaussian.mean[2].exp(), rtol=1e-12, atol=0)


def test_a_start_from_another_model_is_refused():
    def other():
        pyro.sample("c", dist.Normal(0.0, 1.0))
    space = Unconstrained(model, {}, init_to_median)
    with pytest.raises(ValueError, match="fit both to the same model"):
        AutoWhitenedMVN(other, init_to_median, space, laplace_like(space))()
