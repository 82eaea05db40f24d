"""models/priors.py: default priors on physical scales, a user's overrides, and the early
refusal of priors and fixed values outside a scene's physical range."""
import math

import pyro.distributions as dist
import pytest
import torch

from bayespd.infer import ScaledBeta
from bayespd.models.priors import choose, elastic_priors, fixed_params, positive, positive_support
from tests.conftest import plate_scene


@pytest.fixture(scope="module")
def scene():
    return plate_scene()  # LPS, h = 1, delta_max = 2.5


def test_defaults_are_on_the_physical_scales(scene):
    """K, G ~ LogNormal(log nominal, 0.5) (median = nominal); delta ~ ScaledBeta(h, delta_max,
    2, 2), support [h, delta_max] and mean (h + delta_max) / 2; sigma ~ HalfNormal(scale)."""
    priors = elastic_priors(scene, {"K": 3000.0, "G": 1400.0}, 0.01)
    assert set(priors) == {"K", "G", "delta", "sigma"}
    for k, nominal in (("K", 3000.0), ("G", 1400.0)):
        assert isinstance(priors[k], dist.LogNormal)
        assert float(priors[k].loc) == pytest.approx(math.log(nominal), rel=1e-15) and float(priors[k].scale) == 0.5
    d = priors["delta"]
    assert isinstance(d, ScaledBeta)
    assert float(d.support.lower_bound) == 1.0 and float(d.support.upper_bound) == 2.5
    assert float(d.mean) == pytest.approx(1.75, rel=1e-12)
    assert isinstance(priors["sigma"], dist.HalfNormal) and float(priors["sigma"].scale) == 0.01


def test_bad_scales_name_the_fix(scene):
    with pytest.raises(ValueError, match=r"missing \['G'\]"):
        elastic_priors(scene, {"K": 3000.0}, 0.01)
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="noise_scale must be finite and positive"):
            elastic_priors(scene, {"K": 3000.0, "G": 1400.0}, bad)
    with pytest.raises(ValueError, match="the nominal K must be finite and positive"):
        elastic_priors(scene, {"K": -3.0, "G": 1400.0}, 0.01)
    assert positive("x", "2.5") == 2.5


def test_overrides_replace_only_what_they_name(scene):
    defaults = elastic_priors(scene, {"K": 3000.0, "G": 1400.0}, 0.01)
    mine = dist.Gamma(2.0, 1e-3)
    chosen = choose(defaults, {"K": mine}, scene)
    assert chosen["K"] is mine and all(chosen[k] is defaults[k] for k in ("G", "delta", "sigma"))
    assert choose(defaults, None) == defaults


def test_overrides_outside_the_physical_range_are_refused(scene):
    """Unknown names, non-distributions, a modulus prior reaching below zero and a horizon
    prior leaving [h, delta_max] are refused before any sampling."""
    defaults = elastic_priors(scene, {"K": 3000.0, "G": 1400.0}, 0.01)
    with pytest.raises(ValueError, match=r"no such parameter\(s\) \['E'\]"):
        choose(defaults, {"E": dist.LogNormal(0.0, 1.0)})
    with pytest.raises(ValueError, match="must be a Pyro distribution, got float"):
        choose(defaults, {"K": 3000.0})
    with pytest.raises(ValueError, match="includes negative moduli"):
        choose(defaults, {"G": dist.Normal(1400.0, 100.0)}, scene)
    with pytest.raises(ValueError, match="allows h = 1 <= delta <= delta_max = 2.5"):
        choose(defaults, {"delta": dist.Uniform(1.0, 3.0)}, scene)
    choose(defaults, {"delta": dist.Uniform(1.0, 2.5)}, scene)  # exactly the allowed range


def test_positive_support():
    priors = {"a": dist.LogNormal(0.0, 1.0), "b": dist.HalfNormal(1.0), "c": dist.Normal(0.0, 1.0),
              "d": dist.Uniform(-1.0, 1.0)}
    positive_support(priors, ["a", "b"])
    for k in ("c", "d"):
        with pytest.raises(ValueError, match=f"the prior of {k} has support .* {k} is positive"):
            positive_support(priors, [k])


def test_fixed_params_are_exactly_the_known_ones(scene):
    """Exactly param_names less the inferred ones, as float64 tensors; delta in [h,
    delta_max] and moduli finite and positive, or refused."""
    out = fixed_params(scene, {"G": 1400, "delta": 2.0}, inferred=("K",))
    assert set(out) == {"G", "delta"} and all(v.dtype == torch.float64 for v in out.values())
    assert float(out["G"]) == 1400.0
    with pytest.raises(ValueError, match=r"exactly \['G', 'delta'\].*got \['delta'\]"):
        fixed_params(scene, {"delta": 2.0}, inferred=("K",))
    with pytest.raises(ValueError, match="exceeds delta_max"):
        fixed_params(scene, {"G": 1400.0, "delta": 3.0}, inferred=("K",))
    with pytest.raises(ValueError, match="the fixed G must be finite and positive"):
        fixed_params(scene, {"G": torch.tensor([1.0, -1.0]), "delta": 2.0}, inferred=("K",))
