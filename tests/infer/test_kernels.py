"""The private Pyro API that bayespd.infer relies on (pyproject.toml pins pyro-ppl for it):
a Pyro release that renames any of it fails here, naming what moved, before a fit goes wrong."""

import pyro
import pyro.distributions as dist
import pytest
import torch
from pyro.distributions import MaskedDistribution
from pyro.infer import HMC, NUTS
from pyro.infer.autoguide import AutoContinuous, AutoNormalizingFlow
from pyro.infer.autoguide.initialization import init_to_median

from bayespd.infer.kernels import KERNELS

# (class, methods overridden or called) of bayespd.infer.kernels' recording kernels
METHODS = [(HMC, ("_initialize_model_properties", "_initialize_adapter", "_sample_r", "_kinetic_energy")),
           (NUTS, ("_build_tree", "_build_basetree")), (AutoContinuous, ("_init_loc",))]
# attributes a set-up kernel must have (kernels.py reads them)
KERNEL_STATE = ("_adapter", "_initial_params", "_potential_energy_last", "_divergences", "_t", "_warmup_steps")


def moved(what):
    return (f"pyro-ppl {pyro.__version__} no longer has {what}, which bayespd.infer relies on "
            "(see the pin in pyproject.toml): port bayespd/infer/kernels.py, laplace.py and svi.py, "
            "or install a pyro-ppl in the pinned range")


def model(y=None):
    mu = pyro.sample("mu", dist.Normal(0.0, 1.0))
    pyro.sample("y", dist.Normal(mu, 1.0), obs=y)


@pytest.mark.parametrize("cls, names", METHODS)
def test_overridden_methods_exist(cls, names):
    for name in names:
        assert callable(getattr(cls, name, None)), moved(f"{cls.__name__}.{name}")


@pytest.mark.parametrize("kind", sorted(KERNELS))
def test_recording_kernels_see_pyro_state(kind):
    """A set-up kernel has the private state kernels.py reads, and records one draw."""
    pyro.set_rng_seed(0)
    kernel = KERNELS[kind](model, init_strategy=init_to_median)
    kernel.setup(0, y=torch.tensor(0.3))
    for name in KERNEL_STATE:
        assert hasattr(kernel, name), moved(f"{type(kernel).__mro__[2].__name__}.{name} on a set-up kernel")
    assert callable(getattr(kernel._adapter, "reset_step_size_adaptation", None)), moved("the adapter's reset_step_size_adaptation")
    kernel.sample(kernel.initial_params)
    assert {"lp", "energy", "step_size", "n_steps", "diverging", "acceptance_rate"} <= set(kernel.stats)


def test_masked_distribution_keeps_its_mask():
    """laplace.gauss_newton_hessian reads MaskedDistribution._mask."""
    masked = dist.Normal(torch.zeros(3), 1.0).mask(torch.tensor([True, False, True]))
    assert isinstance(masked, MaskedDistribution)
    assert torch.equal(getattr(masked, "_mask", None), torch.tensor([True, False, True])), moved("MaskedDistribution._mask")


def test_normalizing_flow_guide_state():
    """svi.AutoFlow sets the attributes AutoNormalizingFlow.__init__ sets, and no others."""
    guide = AutoNormalizingFlow(model, init_transform_fn=lambda dim: None)
    for name in ("_init_transform_fn", "transform", "_prototype_tensor"):
        assert hasattr(guide, name), moved(f"AutoNormalizingFlow.{name}")
