"""bayespd/infer/fingerprint.py: the hashes a checkpoint must match change with the data (to the
last bit, and its dtype), a prior's parameters and the start, and not between identical runs."""
import pyro
import pyro.distributions as dist
import torch
from pyro.infer.autoguide import init_to_median, init_to_value

from bayespd.infer.fingerprint import data_hash, run_fingerprint

Y = torch.linspace(0.0, 1.0, 5, dtype=torch.float64)


def model_with(scale):
    def model(y=None):
        mu = pyro.sample("mu", dist.Normal(0.0, scale))
        with pyro.plate("n", 5):
            pyro.sample("y", dist.Normal(mu, 1.0), obs=y)
    return model


def test_data_hash_is_exact_and_sees_the_dtype():
    assert data_hash(Y) == data_hash(Y.clone())
    assert data_hash(Y) != data_hash(Y + 1e-15 * (Y == 1.0))  # one ulp-scale change
    assert data_hash(Y) != data_hash(Y.float())
    assert data_hash(Y.numpy()) == data_hash(Y.numpy().copy())


def test_run_fingerprint_changes_with_the_prior_and_the_start_only():
    base = run_fingerprint(model_with(3.0), {"y": Y}, init_to_median, seed=5)
    assert base == run_fingerprint(model_with(3.0), {"y": Y}, init_to_median, seed=5)
    prior = run_fingerprint(model_with(2.0), {"y": Y}, init_to_median, seed=5)
    assert prior != base and any(k.startswith("site") and prior[k] != base[k] for k in base)
    data = run_fingerprint(model_with(3.0), {"y": Y + 1.0}, init_to_median, seed=5)
    assert data["data 'y'"] != base["data 'y'"]
    start = run_fingerprint(model_with(3.0), {"y": Y}, init_to_value(values={"mu": torch.tensor(0.5)}), seed=5)
    assert start != base
