"""bayespd.infer on a conjugate model with a known posterior: mu ~ N(0, 10^2), y_i ~ N(mu, 1)."""

import json
import math
import warnings

import arviz as az
import numpy as np
import pyro
import pyro.distributions as dist
import pytest
import torch
import xarray as xr
from scipy import stats
from torch.distributions import biject_to

from bayespd.infer import ChainDivergedError, ScaledBeta, fit, load, save, summary, to_inference_data
from bayespd.linalg.sparse import NotPositiveDefiniteError

N, PRIOR_SD, LOW, HIGH = 50, 10.0, 0.5, 2.0
DRAWS = 300  # per chain, after as many warmup steps


@pytest.fixture(scope="module", autouse=True)
def float64_single_thread():
    """float64; one intra-op thread (tiny tensors: extra threads only add sync overhead,
    10x under CPU contention)."""
    dtype, threads = torch.get_default_dtype(), torch.get_num_threads()
    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(1)
    yield
    torch.set_default_dtype(dtype)
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def y():
    return 1.5 + torch.randn(N, generator=torch.Generator().manual_seed(0))


@pytest.fixture(scope="module")
def exact(y):
    """Exact posterior mean and sd of mu."""
    precision = N + PRIOR_SD**-2
    return float(y.sum()) / precision, precision**-0.5


def model(y=None):
    mu = pyro.sample("mu", dist.Normal(0.0, PRIOR_SD))
    pyro.sample("h", ScaledBeta(LOW, HIGH))  # not in the likelihood: posterior = prior
    pyro.deterministic("two_mu", 2 * mu)
    with pyro.plate("obs", N):
        pyro.sample("y", dist.Normal(mu, 1.0), obs=y)


@pytest.fixture(scope="module")
def nuts(y):
    """Two chains in this process (test_mcmc checks the worker processes give the same bits)."""
    return fit(model, {"y": y}, num_samples=DRAWS, num_warmup=DRAWS, num_chains=2, chains="sequential",
               progress=False)


def check_moments(draws, mean, sd, mean_tol):
    """Draws' mean within mean_tol of mean, sd within 15 %."""
    assert abs(float(draws.mean()) - mean) < mean_tol
    assert float(draws.std()) == pytest.approx(sd, rel=0.15)


def mcse(draws):
    return float(draws.std()) / math.sqrt(float(az.ess(draws.values)))


def test_nuts_recovers_conjugate_posterior(nuts, exact):
    mu, h = nuts["posterior"]["mu"], nuts["posterior"]["h"]
    check_moments(mu, *exact, mean_tol=4 * mcse(mu))
    # ScaledBeta(2, 2) on [LOW, HIGH]: mean at the centre, sd = width * sqrt(1 / 20)
    check_moments(h, (LOW + HIGH) / 2, (HIGH - LOW) / math.sqrt(20), mean_tol=4 * mcse(h))
    assert float(h.min()) > LOW and float(h.max()) < HIGH
    np.testing.assert_allclose(nuts["posterior"]["two_mu"], 2 * mu)
    assert az.rhat(to_inference_data(nuts), var_names=["mu", "h"]).to_array().max() < 1.05


def test_tree_layout_and_sample_stats(nuts):
    assert set(nuts.children) == {
        "posterior", "sample_stats", "log_likelihood", "posterior_predictive", "observed_data"
    }
    assert nuts["posterior"]["mu"].dims == ("chain", "draw")
    assert dict(nuts["posterior"].sizes) == {"chain": 2, "draw": DRAWS}
    st = nuts["sample_stats"]
    assert {v: st[v].dtype.kind for v in st.data_vars} == {
        "lp": "f", "energy": "f", "step_size": "f", "tree_depth": "i", "n_steps": "i",
        "diverging": "b", "acceptance_rate": "f",
    }
    assert all(st[v].dims == ("chain", "draw") for v in st.data_vars)
    assert (st["n_steps"] <= 2 ** st["tree_depth"] - 1).all() and (st["n_steps"] >= 1).all()
    assert ((st["acceptance_rate"] >= 0) & (st["acceptance_rate"] <= 1)).all()
    assert (st["step_size"] == st["step_size"][:, 0]).all()  # adapted during warmup only
    assert int(st["diverging"].sum()) == 0
    assert nuts.attrs["method"] == "nuts" and nuts.attrs["wall_time_s"] > 0
    assert nuts.attrs["num_grad_evals"] >= int(st["n_steps"].sum())
    assert json.loads(nuts.attrs["settings"])["num_chains"] == 2


def test_lp_is_log_joint_on_unconstrained_space(nuts, y):
    c, d = 1, 17
    mu, h = (torch.tensor(float(nuts["posterior"][v][c, d])) for v in ("mu", "h"))
    prior = ScaledBeta(LOW, HIGH)
    to_h = biject_to(prior.support)
    expected = (
        dist.Normal(0.0, PRIOR_SD).log_prob(mu)
        + prior.log_prob(h)
        + to_h.log_abs_det_jacobian(to_h.inv(h), h)
        + dist.Normal(mu, 1.0).log_prob(y).sum()
    )
    assert float(nuts["sample_stats"]["lp"][c, d]) == pytest.approx(float(expected), rel=1e-10)


def test_log_likelihood_and_predictive(nuts, y, exact):
    ll = nuts["log_likelihood"]["y"]
    assert ll.dims == ("chain", "draw", "y_dim_0") and ll.shape == (2, DRAWS, N)
    mu = float(nuts["posterior"]["mu"][0, 5])
    expected = dist.Normal(mu, 1.0).log_prob(y)
    np.testing.assert_allclose(ll[0, 5], expected, rtol=1e-12)
    assert float(ll[0, 5].sum()) == pytest.approx(float(expected.sum()), rel=1e-12)
    np.testing.assert_array_equal(nuts["observed_data"]["y"], y.numpy())
    pp = nuts["posterior_predictive"]["y"]
    assert pp.shape == (2, DRAWS, N)
    # replicated data: N(mu, 1) given mu, so its mean over everything is near the posterior mean
    assert float(pp.mean()) == pytest.approx(exact[0], abs=0.05)


def test_summary_and_inference_data(nuts):
    idata = to_inference_data(nuts)
    assert set(idata.groups()) == set(nuts.children)
    assert idata.attrs["method"] == "nuts"
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        df = summary(nuts, var_names=["mu", "h"])
    assert list(df.index) == ["mu", "h"]
    for col in ["mean", "sd", "hdi_5%", "hdi_95%", "mcse_mean", "ess_bulk", "ess_tail", "r_hat"]:
        assert col in df.columns
    assert az.loo(idata).elpd_loo < 0


def test_summary_warns_on_divergences_and_bad_rhat(nuts):
    bad = nuts.copy(deep=True)
    st = bad["sample_stats"].to_dataset()
    st["diverging"][0, 0] = True
    post = bad["posterior"].to_dataset()
    post["mu"][1] += 1.0  # chains disagree
    bad["sample_stats"], bad["posterior"] = st, post
    with pytest.warns(UserWarning) as record:
        summary(bad, var_names=["mu"])
    messages = " ".join(str(w.message) for w in record)
    assert "divergent" in messages and "r_hat" in messages
    assert not nuts["sample_stats"]["diverging"].any()  # the copy was deep


def test_save_load_round_trip(nuts, tmp_path):
    path = tmp_path / "fit.nc"
    save(nuts, path)
    save(nuts, path)  # overwrites in place
    assert [p.name for p in tmp_path.iterdir()] == ["fit.nc"]  # no temp file left
    loaded = load(path)
    path.unlink()  # everything is in memory
    xr.testing.assert_identical(loaded, nuts)
    assert loaded.attrs == nuts.attrs
    assert loaded["sample_stats"]["diverging"].dtype == bool


def test_svi_recovers_conjugate_posterior(y, exact):
    steps = 1000
    tree = fit(model, {"y": y}, method="svi", num_samples=1000, svi_steps=steps, progress=False)
    mu = tree["posterior"]["mu"]
    assert dict(tree["posterior"].sizes) == {"chain": 1, "draw": 1000}
    # The Gaussian posterior is in the variational family, so the optimum is exact; the
    # residual error is the Monte-Carlo error of the draws (sd / sqrt(1000) ~ 0.03 sd) plus
    # optimiser noise from single-sample ELBO gradients, hence 0.15 sd rather than 4 MCSE.
    check_moments(mu, *exact, mean_tol=0.15 * exact[1])
    loss = tree["sample_stats"]["svi_loss"]
    assert loss.dims == ("svi_step",) and loss.size == steps
    assert float(loss[-100:].mean()) < float(loss[:100].mean())
    assert tree.attrs["num_grad_evals"] == steps
    assert summary(tree, var_names=["mu"]).loc["mu", "sd"] == pytest.approx(exact[1], rel=0.15)


def vector_model(y, mask):
    theta = pyro.sample("theta", dist.Normal(0.0, 10.0).expand([2]).to_event(1))
    with pyro.plate("point", y.shape[0]):
        pyro.sample("y", dist.Normal(theta, 1.0).to_event(1).mask(mask), obs=y)


def test_vector_sites_dims_coords_and_masked_log_likelihood():
    y = torch.randn(6, 2, generator=torch.Generator().manual_seed(1))
    mask = torch.tensor([True, False, True, True, False, True])
    tree = fit(
        vector_model, {"y": y, "mask": mask}, method="svi", num_samples=10, svi_steps=20,
        progress=False, dims={"y": ["point", "component"], "theta": ["component"]},
        coords={"component": ["u", "v"]},
    )
    assert tree["posterior"]["theta"].dims == ("chain", "draw", "component")
    assert list(tree["posterior"]["component"].values) == ["u", "v"]
    assert tree["posterior_predictive"]["y"].dims == ("chain", "draw", "point", "component")
    ll = tree["log_likelihood"]["y"]
    assert ll.dims == ("chain", "draw", "point")  # the event dim is summed
    theta = torch.as_tensor(tree["posterior"]["theta"][0, 3].values)
    expected = dist.Normal(theta, 1.0).log_prob(y).sum(-1) * mask  # masked entries are 0
    np.testing.assert_allclose(ll[0, 3], expected, rtol=1e-12)


def test_not_positive_definite_is_a_divergence(y, exact):
    mean, sd = exact
    bound = 2.5 * sd  # reached by a few percent of the trajectories

    def fragile(y):
        mu = pyro.sample("mu", dist.Normal(0.0, PRIOR_SD))
        if abs(float(mu.detach()) - mean) > bound:
            raise NotPositiveDefiniteError("stiffness is not positive definite")
        with pyro.plate("obs", N):
            pyro.sample("y", dist.Normal(mu, 1.0), obs=y)

    tree = fit(fragile, {"y": y}, num_samples=DRAWS, num_warmup=DRAWS, num_chains=2,
               progress=False, init_values={"mu": mean})
    assert int(tree["sample_stats"]["diverging"].sum()) > 0
    mu = tree["posterior"]["mu"]
    assert float(abs(mu - mean).max()) < bound
    # the sampler sees the posterior truncated to |mu - mean| < bound
    truncated = stats.truncnorm(-2.5, 2.5, loc=mean, scale=sd)
    check_moments(mu, truncated.mean(), truncated.std(), mean_tol=4 * mcse(mu))
    with pytest.warns(UserWarning, match="divergent"):
        summary(tree)


def test_fit_rejects_unknown_method(y):
    with pytest.raises(ValueError, match="method"):
        fit(model, {"y": y}, method="gibbs")


@pytest.mark.slow  # HMC also runs through fit by name and settings in the default set (test_method)
def test_hmc_recovers_conjugate_posterior(y, exact):
    tree = fit(model, {"y": y}, "hmc", trajectory_length=1.0, num_samples=DRAWS, num_warmup=150,
               num_chains=2, chains="sequential", progress=False)
    mu = tree["posterior"]["mu"]
    check_moments(mu, *exact, mean_tol=4 * mcse(mu))
    st = tree["sample_stats"]
    assert set(st.data_vars) == {"lp", "energy", "step_size", "n_steps", "diverging", "acceptance_rate"}
    # steps = trajectory length / step size, the step size fixed after warmup
    steps = (1.0 / st["step_size"]).astype(int).clip(min=1)
    assert (st["n_steps"] == steps).all() and float(st["acceptance_rate"].mean()) > 0.6
    assert tree.attrs["method"] == "hmc"


def test_a_laplace_mass_matrix_kept_through_warmup(y, exact, tmp_path):
    """adapt_mass=False: the inverse mass matrix after warmup (read back from the chain's
    checkpoint) is the Laplace covariance on the unconstrained space, bit for bit, only the
    step size adapts; the draws still recover the exact posterior within 4 Monte-Carlo
    errors. Without a seeded matrix, keeping it is refused."""
    laplace = fit(model, {"y": y}, "laplace", num_samples=10, progress=False)
    tree = fit(model, {"y": y}, num_samples=DRAWS, num_warmup=150, num_chains=1, mass_matrix_from="laplace",
               adapt_mass=False, checkpoint=tmp_path, progress=False)
    (names, kept), = torch.load(tmp_path / "chain0.pt", weights_only=True)["inverse_mass_matrix"]
    assert list(names) == ["h", "mu"]
    np.testing.assert_array_equal(kept.numpy(), laplace["sample_stats"]["covariance_unconstrained"].values)
    mu = tree["posterior"]["mu"]
    check_moments(mu, *exact, mean_tol=4 * mcse(mu))
    assert json.loads(tree.attrs["settings"])["adapt_mass"] is False
    with pytest.raises(ValueError, match="mass_matrix_from"):
        fit(model, {"y": y}, num_samples=10, num_warmup=10, num_chains=1, adapt_mass=False, progress=False)


def test_chain_that_always_diverges_is_refused_with_the_fix(y):
    start = 1.0

    def stuck(y):  # the stiffness "fails" everywhere but at the start
        mu = pyro.sample("mu", dist.Normal(0.0, PRIOR_SD))
        if float(mu.detach()) != start:
            raise NotPositiveDefiniteError("stiffness is not positive definite")
        with pyro.plate("obs", N):
            pyro.sample("y", dist.Normal(mu, 1.0), obs=y)

    with pytest.raises(ChainDivergedError, match="chain 0 diverged.*[Rr]eparametrise.*tighten the "
                       "priors.*dense mass matrix"):
        fit(stuck, {"y": y}, num_samples=5, num_warmup=5, num_chains=1, init_values={"mu": start},
            progress=False)


def test_summary_warns_on_low_ess_and_names_the_thresholds(y):
    short = fit(model, {"y": y}, num_samples=30, num_warmup=30, num_chains=2,
                chains="sequential", progress=False)
    with pytest.warns(UserWarning, match=r"bulk ESS < 200 \(100 per chain\)"):
        summary(short, var_names=["mu", "h"])


def test_bad_data_is_refused_before_sampling(y):
    bad = y.clone()
    bad[3] = float("nan")
    with pytest.raises(ValueError, match=r"1 NaN/inf entries outside the mask \(first at index \(3,\)\)"
                       r".*model_data"):
        fit(model, {"y": bad}, "svi", progress=False)
    with pytest.raises(ValueError, match=r"has shape \(49,\) but the model predicts \(50,\)"):
        fit(model, {"y": y[:49]}, "svi", progress=False)
    with pytest.raises(ValueError, match="data has no 'z' entry"):
        fit(model, {"y": y}, "svi", observed="z", progress=False)


@pytest.fixture(scope="module")
def plate():
    import bayespd as bp
    from bayespd.models.elastic_plate import elastic_plate

    p = bp.grid_2d(8.0, 4.0, 1.0)
    scene = bp.Scene(bp.LPS(p, bp.find_bonds(p, 2.5)), [bp.Dirichlet.layer(p, "left", 2.5)],
                     [bp.Load(p.layer("right", 1.0), (30.0, 10.0))], bp.Observation(p, p.x[p.x[:, 0] > 3]))
    with torch.no_grad():
        u = scene.observe(scene.solve({"K": 3000.0, "G": 1400.0, "delta": 2.0}))
    return scene, lambda **priors: elastic_plate(scene, {"K": 3000.0, "G": 1400.0}, 1e-3, priors), u


def test_priors_outside_the_physical_range_and_wrong_shapes_are_refused(plate):
    scene, make, u = plate
    data = {"y": u}
    with pytest.raises(ValueError, match=r"prior of K has support \[-inf, inf\].*negative moduli.*LogNormal"):
        fit(make(K=dist.Normal(3000.0, 500.0)), data, "laplace", scene=scene, progress=False)
    with pytest.raises(ValueError, match=r"prior of delta has support \[0.5, 2.5\].*h = 1.*ScaledBeta\(1, 2.5\)"):
        fit(make(delta=ScaledBeta(0.5, 2.5)), data, "laplace", scene=scene, progress=False)
    with pytest.raises(ValueError, match=r"shape \(.*\) but the scene observes .* Observation"):
        fit(make(), {"y": u[:-1]}, "laplace", scene=scene, progress=False)
    missing = u.clone()
    missing[0, 1] = float("nan")
    with pytest.raises(ValueError, match="under the mask"):
        fit(make(), {"y": missing, "mask": torch.isfinite(missing)}, "laplace", scene=scene, progress=False)


def test_scene_layout_constant_data_and_loo(plate):
    """Given a scene: observations on (point, component) with x/y coords, the mask and geometry
    in constant_data, masked log-likelihood entries 0 and az.loo on the pointwise values."""
    scene, make, u = plate
    import bayespd as bp

    y = u + 1e-3 * torch.randn(u.shape, generator=torch.Generator().manual_seed(2))
    y[1, 0] = float("nan")
    tree = fit(make(), bp.model_data(y), "laplace", scene=scene, num_samples=200, progress=False)
    assert tree["observed_data"]["y"].dims == ("point", "component")
    assert list(tree["observed_data"]["component"].values) == ["x", "y"]
    const = tree["constant_data"]
    assert const["mask"].dims == ("point", "component") and not bool(const["mask"][1, 0])
    np.testing.assert_array_equal(const["particle_x"], scene.particles.x)
    np.testing.assert_array_equal(const["observation_points"], scene.observation.points)
    ll = tree["log_likelihood"]["y"]
    assert ll.dims == ("chain", "draw", "point", "component") and (ll[:, :, 1, 0] == 0).all()
    loo = az.loo(to_inference_data(tree), pointwise=True)
    assert np.isfinite(loo.elpd_loo) and loo.loo_i.size == y.numel()


@pytest.mark.parametrize("method, settings, error, match", [
    ("svi", {"num_samples": 0}, ValueError, "num_samples must be an integer >= 1, got 0: ask for at least one draw"),
    ("nuts", {"num_samples": -5}, ValueError, "num_samples must be an integer >= 1, got -5"),
    ("nuts", {"num_chains": 0}, ValueError, "num_chains must be an integer >= 1, got 0: run at least one chain"),
    ("hmc", {"num_warmup": -1}, ValueError, "num_warmup must be an integer >= 0, got -1"),
    ("nuts", {"num_chains": 2.0}, TypeError, r"num_chains must be an integer, got 2.0 \(float\)"),
    ("svi", {"svi_steps": 0}, ValueError, "svi_steps must be an integer >= 1, got 0: take at least one"),
    ("svi", {"svi_lr": -0.1}, ValueError, "svi_lr must be positive, got -0.1: pass a learning rate"),
    ("svi", {"svi_lr": float("nan")}, ValueError, "svi_lr contains NaN or inf"),
    ("svi", {"guide": "diag"}, ValueError, r"guide must be one of \('normal'"),
    ("svi", {"init_values": {"mu": float("nan")}}, ValueError, r"init_values\['mu'\] contains NaN or inf"),
])
def test_bad_counts_and_rates_are_refused_before_sampling(y, method, settings, error, match):
    with pytest.raises(error, match=match):
        fit(model, {"y": y}, method, progress=False, **settings)


def test_numpy_data_are_taken_as_tensors(y):
    """y as a float64 numpy array gives the same (finite) draws as the tensor."""
    kw = dict(svi_steps=20, num_samples=20, seed=1, progress=False)
    a, b = fit(model, {"y": y.numpy()}, "svi", **kw), fit(model, {"y": y}, "svi", **kw)
    assert np.isfinite(a["posterior"]["mu"].values).all()
    np.testing.assert_array_equal(a["posterior"]["mu"].values, b["posterior"]["mu"].values)
    with pytest.raises(TypeError, match=r"data\['y'\] is an array of <U1: pass numbers"):
        fit(model, {"y": np.array(["a"] * N)}, "svi", **kw)


def test_a_discrete_prior_is_refused(y):
    def counting(y=None):
        mu = pyro.sample("mu", dist.Poisson(3.0))
        with pyro.plate("obs", N):
            pyro.sample("y", dist.Normal(mu, 1.0), obs=y)
    with pytest.raises(ValueError, match=r"mu has a discrete prior \(Poisson\).*continuous prior"):
        fit(counting, {"y": y}, "nuts", progress=False)


def test_a_diverging_learning_rate_is_named(plate):
    """A huge svi_lr overflows the modulus the guide draws: reported as the optimiser
    diverging (not as bad moduli), with the fix."""
    scene, make, u = plate
    with pytest.raises(ValueError, match=r"SVI diverged at step \d+ of 50 with svi_lr=1e\+06: .*"
                                         r"lower svi_lr \(e.g. 100000\)"):
        fit(make(), {"y": u}, "svi", svi_steps=50, svi_lr=1e6, num_samples=5, progress=False)


@pytest.mark.parametrize("predictive", [False, 7, True])
def test_predictive_on_demand(y, predictive):
    """predictive=False replays nothing; n replays about n draws evenly spaced (the draw
    coordinate names them, and their log-likelihood is that of those posterior draws);
    True replays all 20."""
    tree = fit(model, {"y": y}, "laplace", num_samples=20, progress=False, predictive=predictive)
    if predictive is False:
        assert "log_likelihood" not in tree and "posterior_predictive" not in tree
        return
    draws = tree["log_likelihood"]["draw"].values
    expected = np.arange(20) if predictive is True else np.round(np.linspace(0, 19, 7)).astype(int)
    np.testing.assert_array_equal(draws, expected)
    assert tree["posterior_predictive"]["y"].shape[:2] == (1, len(expected))
    full = fit(model, {"y": y}, "laplace", num_samples=20, progress=False)
    np.testing.assert_allclose(tree["log_likelihood"]["y"].values, full["log_likelihood"]["y"].sel(draw=draws).values,
                               rtol=1e-14)


@pytest.mark.parametrize("bad", [0, -3, 2.5, "all"])
def test_predictive_refuses_what_is_no_count(y, bad):
    with pytest.raises((ValueError, TypeError), match="predictive must be an integer"):
        fit(model, {"y": y}, "laplace", num_samples=20, progress=False, predictive=bad)
