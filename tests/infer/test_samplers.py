"""``bayespd.infer.samplers``: the NUTS and HMC settings (refused when inconsistent, recorded,
turned into Pyro kernel options), the covariance of a previous fit's draws on the
unconstrained space that seeds the mass matrix. (NUTS and HMC runs on a conjugate model are
in ``tests/infer/test_fit.py``.)"""
import numpy as np
import pyro
import pyro.distributions as dist
import pytest
import torch

from bayespd.infer import HMC, NUTS
from bayespd.infer.datatree import build_tree
from bayespd.infer.samplers import unconstrained_covariance


def model(y=None):
    """scale > 0 (log on the unconstrained space), shift in R^2."""
    scale = pyro.sample("scale", dist.LogNormal(0.0, 1.0))
    shift = pyro.sample("shift", dist.Normal(0.0, 1.0).expand([2]).to_event(1))
    with pyro.plate("obs", 3):
        pyro.sample("y", dist.Normal(shift.sum(), scale), obs=y)


def test_covariance_of_draws_on_the_unconstrained_space():
    """Sites in sorted order (scale, shift[0], shift[1]), scale mapped by log: equal to
    numpy's covariance of (log scale, shift) to rounding."""
    rng = np.random.default_rng(0)
    scale = np.exp(0.3 * rng.standard_normal((2, 200)))
    shift = rng.standard_normal((2, 200, 2)) @ np.array([[1.0, 0.5], [0.0, 0.2]])
    tree = build_tree({"posterior": {"shift": shift, "scale": scale}})
    cov = unconstrained_covariance(model, {"y": torch.zeros(3)}, tree)
    expect = np.cov(np.column_stack([np.log(scale).reshape(-1), shift.reshape(-1, 2)]).T)
    np.testing.assert_allclose(cov.numpy(), expect, rtol=1e-12, atol=1e-15)


def test_inconsistent_settings_are_refused_when_made():
    with pytest.raises(ValueError, match="adapt_mass=False keeps a seeded mass matrix: give mass_matrix_from"):
        HMC(adapt_mass=False)
    with pytest.raises(ValueError, match="mass_matrix_from must be a DataTree or 'laplace', not 'svi'"):
        NUTS(mass_matrix_from="svi")
    NUTS(adapt_mass=False, mass_matrix_from="laplace")


def test_kernel_options_and_recorded_settings():
    nuts = NUTS(target_accept=0.9, max_tree_depth=6, dense_mass=True)
    assert nuts.kernel_options() == {"target_accept_prob": 0.9, "max_tree_depth": 6, "full_mass": True,
                                     "adapt_mass_matrix": True}
    hmc = HMC(trajectory_length=1.5, mass_matrix_from="laplace", adapt_mass=False)
    assert hmc.kernel_options() == {"trajectory_length": 1.5, "target_accept_prob": 0.8, "full_mass": True,
                                    "adapt_mass_matrix": False}
    assert NUTS().kernel_options()["full_mass"] is False
    tree = build_tree({"posterior": {"a": np.zeros((1, 2))}})
    assert NUTS(mass_matrix_from=tree).record()["mass_matrix_from"] == "tree"
    assert hmc.record()["mass_matrix_from"] == "laplace" and hmc.record()["trajectory_length"] == 1.5
    assert {"max_tree_depth", "target_accept", "num_warmup", "num_chains"} <= set(NUTS().record())
