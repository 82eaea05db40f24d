"""``bayespd.infer.checks``: data, shapes and priors refused before any sampling, each with a
message that names the fix."""
import pyro
import pyro.distributions as dist
import pytest
import torch
from pyro import poutine

from bayespd.infer import ScaledBeta
from bayespd.infer.checks import check_data, check_observed_shape, check_priors, trace_priors
from tests.conftest import plate_scene


def test_finite_data_pass_and_a_missing_entry_is_named():
    check_data({"y": torch.ones(3, 2)}, "y")
    with pytest.raises(ValueError, match=r"data has no 'z' entry \(keys \['mask', 'y'\]\).*observed="):
        check_data({"y": torch.ones(3), "mask": torch.ones(3)}, "z")


def test_non_finite_data_outside_the_mask_are_located():
    y = torch.ones(4, 2)
    y[2, 1], y[3, 0] = float("nan"), float("inf")
    with pytest.raises(ValueError, match=r"y has 2 NaN/inf entries outside the mask \(first at index \(2, 1\)\)"
                       r".*model_data\(y, mask\)"):
        check_data({"y": y}, "y")
    mask = torch.tensor([True, True, True, False])[:, None]  # row 3 masked, row 2 kept
    with pytest.raises(ValueError, match=r"1 NaN/inf entries outside the mask \(first at index \(2, 1\)\)"):
        check_data({"y": y, "mask": mask}, "y")


def test_non_finite_data_under_the_mask_are_refused_too():
    """NaN * 0 is NaN in the gradients: masked entries must be finite (zeroed) as well."""
    y = torch.ones(4, 2)
    y[3] = float("nan")
    with pytest.raises(ValueError, match=r"y has 2 NaN/inf entries under the mask.*set them to 0"):
        check_data({"y": y, "mask": torch.tensor([True, True, True, False])[:, None]}, "y")


def model(y=None, n=5):
    a = pyro.sample("a", dist.LogNormal(0.0, 1.0))
    pyro.sample("b", dist.Normal(0.0, 1.0))
    with pyro.plate("points", n, dim=-2):
        pyro.sample("y", dist.Normal(a, 1.0).expand([n, 2]).to_event(0), obs=y)


def trace_of(y):
    return poutine.trace(model).get_trace(y)


def test_observed_shape_against_the_model_and_the_scene():
    scene = plate_scene()
    n = scene.observation.n
    good = torch.zeros(n, 2)
    trace = poutine.trace(model).get_trace(good, n)
    check_observed_shape(trace, {"y": good}, "y", scene)
    with pytest.raises(ValueError, match=rf"y has shape \({n - 1}, 2\) but the scene observes {n} points"
                       r" x 2 components.*Observation"):
        check_observed_shape(trace, {"y": good[:-1]}, "y", scene)
    with pytest.raises(ValueError, match=rf"shape \({n - 1}, 2\) but the model predicts \({n}, 2\)"):
        check_observed_shape(trace, {"y": good[:-1]}, "y")
    with pytest.raises(ValueError, match=r"no sample site 'obs' \(sites \['a', 'b', .*'y'\]\).*observed="):
        check_observed_shape(trace, {"obs": good}, "obs")


def test_trace_priors_hold_the_latent_sites():
    trace = trace_of(torch.zeros(5, 2))
    priors = trace_priors(trace)
    assert {"a", "b"} <= set(priors) and "y" not in priors
    assert isinstance(priors["a"], dist.LogNormal) and isinstance(priors["b"], dist.Normal)


@pytest.mark.xfail(strict=True, reason="trace_priors also returns Pyro's plate sites (type 'sample', "
                   "not observed: here 'points'), not only the latent sample sites its docstring "
                   "names; harmless in check_priors, which skips names that are no scene parameter")
def test_trace_priors_are_only_the_latent_sites():
    assert set(trace_priors(trace_of(torch.zeros(5, 2)))) == {"a", "b"}


@pytest.fixture(scope="module")
def scene():
    return plate_scene()  # h = 1, delta_max = 2.5, LPS: moduli K and G


def test_priors_in_the_physical_range_pass(scene):
    check_priors({"K": dist.LogNormal(0.0, 1.0), "G": dist.Gamma(2.0, 1.0),
                  "delta": ScaledBeta(1.0, 2.5), "sigma": dist.Normal(0.0, 1.0)}, scene)  # sigma: not a scene parameter


@pytest.mark.parametrize("prior", [dist.Normal(3.0, 1.0), dist.Uniform(-1.0, 2.0)])
def test_a_modulus_prior_with_negative_support_is_refused(scene, prior):
    with pytest.raises(ValueError, match=r"prior of G has support \[.*\], which includes negative moduli.*LogNormal"):
        check_priors({"G": prior}, scene)


@pytest.mark.parametrize("low,high", [(0.5, 2.5), (1.0, 3.0), (0.9, 2.6)])
def test_a_horizon_prior_outside_h_to_delta_max_is_refused(scene, low, high):
    with pytest.raises(ValueError, match=rf"prior of delta has support \[{low:g}, {high:g}\].*h = 1 <= delta"
                       r" <= delta_max = 2.5.*ScaledBeta\(1, 2.5\)"):
        check_priors({"delta": ScaledBeta(low, high)}, scene)


def test_a_horizon_prior_on_exactly_h_to_delta_max_passes_despite_rounding(scene):
    check_priors({"delta": ScaledBeta(1.0 * (1 - 1e-14), 2.5 * (1 + 1e-14))}, scene)
    check_priors({"delta": dist.Uniform(1.0, 2.5).expand([1]).to_event(1)}, scene)  # independent support
    with pytest.raises(ValueError, match="prior of delta"):
        check_priors({"delta": dist.Uniform(1.0, 2.6).expand([1]).to_event(1)}, scene)


def test_lists_become_tensors_and_an_unreachable_start_names_the_site():
    import pyro
    import pyro.distributions as dist
    from bayespd.infer import fit

    def model(y):
        mu = pyro.sample("mu", dist.Normal(0.0, 1.0))
        with pyro.plate("obs", 3):
            pyro.sample("y", dist.Normal(mu, 1.0), obs=y)

    tree = fit(model, {"y": [0.1, 0.2, 0.3]}, "laplace", num_samples=5, progress=False)
    assert tree["posterior"]["mu"].shape == (1, 5)
    with pytest.raises(ValueError, match="log density is not finite at any start .*'y'.*check the data"):
        fit(model, {"y": [0.1, 1e300, 0.3]}, "laplace", num_samples=5, progress=False)


def test_data_keys_the_model_does_not_take_are_named():
    from bayespd.infer import fit

    def model(y):
        pyro.sample("y", dist.Normal(pyro.sample("mu", dist.Normal(0.0, 1.0)), 1.0), obs=y)

    with pytest.raises(TypeError, match=r"data keys \['y', 'z'\] do not fit the model's arguments \(y\)"):
        fit(model, {"y": torch.tensor(0.1), "z": 1.0}, "laplace", num_samples=5, progress=False)
