"""fit's dispatch: settings objects, keywords checked against the method, and the registry
(a new method is one registered class), on the conjugate model of test_infer."""

import json
from dataclasses import dataclass

import numpy as np
import pyro
import pytest
import torch
from pyro import poutine
from scipy import stats

from bayespd.infer import HMC, METHODS, NUTS, SVI, Draws, Laplace, Method, fit, register
from tests.infer.test_fit import HIGH, LOW, N, PRIOR_SD, model

Y = {"y": 1.5 + torch.randn(N, generator=torch.Generator().manual_seed(0))}
DRAWS = 400  # per chain of the prior sampler: 800 independent draws, the checks below at 4 standard errors


@pytest.fixture(scope="module", autouse=True)
def float64():
    dtype = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(dtype)


def same_tree(a, b):
    for group in ("posterior", "sample_stats", "log_likelihood", "posterior_predictive"):
        x, y = a[group].to_dataset(), b[group].to_dataset()
        assert sorted(x.data_vars) == sorted(y.data_vars)
        for k in x.data_vars:
            np.testing.assert_array_equal(x[k].values, y[k].values, err_msg=f"{group}/{k}")
    assert a.attrs["settings"] == b.attrs["settings"] and a.attrs["method"] == b.attrs["method"]


@pytest.mark.parametrize("name, options", [
    ("nuts", dict(num_samples=30, num_warmup=30, num_chains=2, chains="sequential", seed=3, max_tree_depth=6)),
    ("hmc", dict(num_samples=20, num_warmup=20, num_chains=1, trajectory_length=1.0, seed=2)),
    ("svi", dict(num_samples=40, svi_steps=60, guide="normal", seed=4)),
    ("laplace", dict(num_samples=40, hessian="gauss-newton", seed=5)),
])
def test_settings_object_and_keywords_give_the_same_bits(name, options):
    """``fit(m, d, "nuts", **kw)``, ``fit(m, d, NUTS(**kw))`` and an object whose fields the
    keywords override give the same draws, bit for bit."""
    cls = {"nuts": NUTS, "hmc": HMC, "svi": SVI, "laplace": Laplace}[name]
    assert METHODS[name] is cls
    by_name = fit(model, Y, name, progress=False, **options)
    same_tree(by_name, fit(model, Y, cls(progress=False, **options)))
    same_tree(by_name, fit(model, Y, method=cls(seed=99, num_samples=7), progress=False, **options))


def test_a_keyword_of_another_method_is_refused_naming_the_settings():
    with pytest.raises(TypeError, match=r"svi_steps: not a setting of method 'laplace' \(Laplace\); "
                                        r"its settings are num_samples, .*hessian"):
        fit(model, Y, "laplace", svi_steps=10)
    with pytest.raises(TypeError, match=r"trajectory_length: not a setting of method 'nuts'.*max_tree_depth"):
        fit(model, Y, NUTS(), trajectory_length=1.0)
    with pytest.raises(TypeError, match=r"hessian, num_sample: not a setting of method 'svi'.*svi_lr"):
        fit(model, Y, "svi", num_sample=10, hessian="exact")
    with pytest.raises(ValueError, match=r"one of \('nuts', 'hmc', 'svi', 'laplace'\)"):
        fit(model, Y, "gibbs")
    with pytest.raises(ValueError, match="adapt_mass=False keeps a seeded mass matrix"):
        NUTS(adapt_mass=False)  # settings are checked when made, before any fit


@dataclass(frozen=True)
class Prior(Method):
    """Independent draws from the prior (the posterior of no data); ``sample_stats``: the log
    prior density of each draw."""

    name = "prior"
    recorded = (*Method.recorded, "num_chains")

    num_chains: int = 1

    def run(self, model, data, init, search):
        pyro.set_rng_seed(self.seed)
        with torch.no_grad():
            traces = [poutine.trace(model).get_trace(**data) for _ in range(self.num_chains * self.num_samples)]
        latent = [k for k, s in traces[0].nodes.items() if s["type"] == "sample" and not s["is_observed"]]
        shape = (self.num_chains, self.num_samples)
        draws = {k: torch.stack([t.nodes[k]["value"] for t in traces]).reshape(*shape, *traces[0].nodes[k]["value"].shape)
                 for k in latent}
        lp = [float(t.log_prob_sum(lambda name, site: name in latent)) for t in traces]
        return Draws(draws, {"lp": np.reshape(lp, shape)}, 0, {"prior_only": 1})


@pytest.fixture
def prior_registered():
    yield register(Prior)
    METHODS.pop("prior")


def test_a_registered_method_runs_through_fit(prior_registered):
    """A prior sampler registered as one class: fit runs it by name or object, with the checks,
    replay and DataTree of every method; its draws follow the prior (mu ~ N(0, 10^2): mean and
    sd within 4 standard errors; h on [LOW, HIGH] with the ScaledBeta(2, 2) mean)."""
    assert prior_registered is Prior and METHODS["prior"] is Prior
    tree = fit(model, Y, "prior", num_samples=DRAWS, num_chains=2, seed=1, progress=False)
    mu, h = tree["posterior"]["mu"].values.reshape(-1), tree["posterior"]["h"].values.reshape(-1)
    n = 2 * DRAWS
    assert abs(mu.mean()) < 4 * PRIOR_SD / n**0.5
    assert abs(mu.std() / PRIOR_SD - 1) < 4 / (2 * n) ** 0.5
    assert LOW < h.min() and h.max() < HIGH and abs(h.mean() - (LOW + HIGH) / 2) < 4 * h.std() / n**0.5
    np.testing.assert_allclose(tree["posterior"]["two_mu"], 2 * tree["posterior"]["mu"])  # replayed deterministic
    expected = stats.norm(mu[:, None], 1.0).logpdf(Y["y"].numpy()[None])
    np.testing.assert_allclose(tree["log_likelihood"]["y"].values.reshape(-1, N), expected, rtol=1e-12)
    assert tree.attrs["method"] == "prior" and tree.attrs["prior_only"] == 1
    assert json.loads(tree.attrs["settings"])["num_chains"] == 2
    same_tree(tree, fit(model, Y, Prior(num_samples=DRAWS, num_chains=2, seed=1, progress=False)))
    with pytest.raises(TypeError, match="num_warmup: not a setting of method 'prior'.*num_chains"):
        fit(model, Y, "prior", num_warmup=10)
    with pytest.raises(ValueError, match="registered already"):
        register(type("Other", (Prior,), {"name": "nuts"}))
    with pytest.raises(TypeError, match="Method subclass"):
        register(NUTS())
