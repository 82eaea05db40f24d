"""``bayespd.infer.space``: a model's latent sites as one flat vector on Pyro's unconstrained
space, in sorted name order; flatten/unflatten and constrain/unconstrain are inverse to
rounding, and the potential is minus the log joint plus the log-Jacobians (Pyro's
``potential_fn``), checked against a hand computation."""
import pyro
import pyro.distributions as dist
import pytest
import torch
from pyro.infer.autoguide.initialization import init_to_value
from torch.distributions import biject_to

from bayespd.infer import ScaledBeta
from bayespd.infer.space import Unconstrained, max_plate_nesting

Y = torch.tensor([1.0, 2.5, 0.5])
START = {"scale": torch.tensor(1.5), "offset": torch.tensor([0.3, -0.2]), "horizon": torch.tensor(1.2)}


def model(y=None):
    """Sites declared out of name order: scale > 0, offset in R^2, horizon in [0.5, 2]."""
    scale = pyro.sample("scale", dist.LogNormal(0.0, 1.0))
    offset = pyro.sample("offset", dist.Normal(0.0, 2.0).expand([2]).to_event(1))
    horizon = pyro.sample("horizon", ScaledBeta(0.5, 2.0))
    with pyro.plate("obs", 3):
        pyro.sample("y", dist.Normal(offset.sum() + horizon, scale), obs=y)


@pytest.fixture(scope="module")
def space():
    return Unconstrained(model, {"y": Y}, init_to_value(values=START))


def priors():
    return {"scale": dist.LogNormal(0.0, 1.0), "offset": dist.Normal(0.0, 2.0).expand([2]).to_event(1),
            "horizon": ScaledBeta(0.5, 2.0)}


def test_sites_in_sorted_order_with_labels(space):
    assert space.names == ["horizon", "offset", "scale"]
    assert space.labels == ["horizon", "offset[0]", "offset[1]", "scale"]
    assert space.dim == 4
    assert space.shapes == {"horizon": (), "offset": (2,), "scale": ()}


def test_initial_point_is_the_unconstrained_start(space):
    z = space.initial
    torch.testing.assert_close(z[0], torch.logit(torch.tensor((1.2 - 0.5) / 1.5)), rtol=1e-12, atol=0)
    torch.testing.assert_close(z[1:3], START["offset"], rtol=0, atol=0)
    torch.testing.assert_close(z[3], torch.log(START["scale"]), rtol=1e-15, atol=0)


def test_flatten_unflatten_and_constrain_unconstrain_are_inverse(space):
    z = torch.randn(5, 7, space.dim, generator=torch.Generator().manual_seed(0))
    parts = space.unflatten(z)
    assert parts["offset"].shape == (5, 7, 2) and parts["scale"].shape == (5, 7)
    assert torch.equal(torch.cat([parts[k].reshape(5, 7, -1) for k in space.names], -1), z)
    values = space.constrain(z)
    assert bool(torch.all(values["scale"] > 0))
    assert bool(torch.all((values["horizon"] > 0.5) & (values["horizon"] < 2.0)))
    torch.testing.assert_close(space.unconstrain(values), z, rtol=1e-12, atol=1e-12)
    assert torch.equal(space.flatten(space.unflatten(z[0, 0])), z[0, 0])


def test_potential_is_minus_log_joint_minus_log_jacobian(space):
    """U(z) = -[sum log prior(x) + log|dx/dz| + sum log N(y | offset sum + horizon, scale)]."""
    pr = priors()
    for seed in range(3):
        z = torch.randn(space.dim, generator=torch.Generator().manual_seed(seed))
        x = space.constrain(z)
        logp = dist.Normal(x["offset"].sum() + x["horizon"], x["scale"]).log_prob(Y).sum()
        for k, d in pr.items():
            t = biject_to(d.support)
            zk = t.inv(x[k])
            logp = logp + d.log_prob(x[k]).sum() + t.log_abs_det_jacobian(zk, x[k]).sum()
        assert float(space.potential(z)) == pytest.approx(-float(logp), rel=1e-12)


def test_potential_gradient_is_a_taylor_slope_2_derivative(space):
    z = torch.randn(space.dim, generator=torch.Generator().manual_seed(5)).requires_grad_()
    u = space.potential(z)
    (g,) = torch.autograd.grad(u, z)
    v = torch.randn(space.dim, generator=torch.Generator().manual_seed(6))
    ts = [1e-2, 5e-3, 2.5e-3]
    rem = [abs(float(space.potential(z.detach() + t * v) - u.detach() - t * (g @ v))) for t in ts]
    slopes = [(rem[i + 1] / rem[i]) for i in range(2)]
    assert all(abs(s - 0.25) < 0.02 for s in slopes), slopes  # halving t quarters the remainder


def nested(y=None):
    a = pyro.sample("a", dist.Normal(0.0, 1.0))
    with pyro.plate("rows", 2, dim=-2), pyro.plate("cols", 3, dim=-1):
        pyro.sample("y", dist.Normal(a, 1.0), obs=y)


def fragile(y=None):
    """Raises at most prior draws (as a PD model may at an extreme modulus), not at 1."""
    a = pyro.sample("a", dist.Normal(0.0, 1.0))
    if float(a.detach()) != 1.0:
        raise ValueError("refused")
    with pyro.plate("obs", 3):
        pyro.sample("y", dist.Normal(a, 1.0), obs=y)


def test_max_plate_nesting_runs_the_model_at_the_initial_values():
    at_one = init_to_value(values={"a": torch.tensor(1.0)})
    assert max_plate_nesting(nested, {"y": torch.zeros(2, 3)}, at_one) == 2
    assert max_plate_nesting(model, {"y": Y}, init_to_value(values=START)) == 1
    assert max_plate_nesting(lambda: pyro.sample("a", dist.Normal(0.0, 1.0)), {}, at_one) == 0
    assert max_plate_nesting(fragile, {"y": Y}, at_one) == 1
    space = Unconstrained(fragile, {"y": Y}, at_one)
    assert space.names == ["a"] and float(space.initial) == 1.0
