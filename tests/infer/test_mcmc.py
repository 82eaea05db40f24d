"""Checkpointed NUTS: a run killed at any point and resumed gives the uninterrupted run's draws,
bit for bit; chains in worker processes give the same draws as chains in this process."""

import numpy as np
import pyro
import pyro.distributions as dist
import pytest
import torch
import xarray as xr

from bayespd.infer import HMC, fit
from bayespd.infer.datatree import build_tree
from bayespd.infer import CheckpointMismatchError

N = 20
Y = 1.0 + torch.randn(N, generator=torch.Generator().manual_seed(0))
RUN = dict(num_warmup=40, num_samples=60, num_chains=2, seed=5, chains="sequential", progress=False)


class Killable:
    """The conjugate model mu ~ N(0, prior_scale = 3), y ~ N(mu, 1), counting its differentiable runs (the
    sampler's) and raising KeyboardInterrupt, as a kill would, at run ``kill_at``."""

    def __init__(self, kill_at=None, prior_scale=3.0):
        self.calls, self.kill_at, self.prior_scale = 0, kill_at, prior_scale

    def __call__(self, y):
        if torch.is_grad_enabled():
            self.calls += 1
            if self.calls == self.kill_at:
                raise KeyboardInterrupt
        mu = pyro.sample("mu", dist.Normal(0.0, self.prior_scale))
        with pyro.plate("obs", N):
            pyro.sample("y", dist.Normal(mu, 1.0), obs=y)


@pytest.fixture(scope="module")
def reference():
    model = Killable()
    return fit(model, {"y": Y}, **RUN), model.calls


def same_draws(a, b):
    for group in ("posterior", "sample_stats", "log_likelihood"):
        xr.testing.assert_identical(a[group].to_dataset(), b[group].to_dataset())


@pytest.mark.parametrize("fraction", [0.1, 0.9])
def test_killed_run_resumes_bit_identical(reference, tmp_path, fraction):
    """Killed in chain 0's warmup (0.1 of the sampler's model runs) or in chain 1's draws
    (0.9): the rerun loads what was written and ends with exactly the reference draws."""
    tree, calls = reference
    with pytest.raises(KeyboardInterrupt):
        fit(Killable(kill_at=int(fraction * calls)), {"y": Y}, checkpoint=tmp_path,
            checkpoint_every=10, **RUN)
    written = sorted(p.name for p in tmp_path.iterdir())
    if fraction == 0.9:  # chain 0 finished, chain 1 stopped part-way through its draws
        assert written == ["chain0.pt", "chain1.pt"]
        saved = torch.load(tmp_path / "chain1.pt", weights_only=True)
        assert 0 < len(saved["draws"]["mu"]) < RUN["num_samples"]
    resumed_model = Killable()
    resumed = fit(resumed_model, {"y": Y}, checkpoint=tmp_path, checkpoint_every=10, **RUN)
    same_draws(resumed, tree)
    if fraction == 0.9:
        assert resumed_model.calls < 0.5 * calls  # chain 0 and part of chain 1 were not redone
    again = Killable()
    same_draws(fit(again, {"y": Y}, checkpoint=tmp_path, **RUN), tree)  # all loaded from disk
    assert again.calls < 5


ONE = dict(RUN, num_chains=1, num_warmup=10, num_samples=5)


@pytest.mark.parametrize("change, differs", [
    (dict(seed=6), "seed (5 there, 6 here)"),
    (dict(num_warmup=11), "num_warmup (10 there, 11 here)"),
    (dict(target_accept=0.9), "options ("),
    (dict(data={"y": Y + 1e-12}), "data 'y'"),
    (dict(data={"y": Y.float()}), "data 'y'"),
    (dict(model=Killable(prior_scale=2.0)), "site 'mu'"),
    (dict(init_values={"mu": 0.5}), "site 'mu'"),
])
def test_checkpoint_of_another_run_is_refused(tmp_path, change, differs):
    """Whatever determines the draws is in the fingerprint: the refusal names the directory,
    what differs and the fix."""
    fit(Killable(), {"y": Y}, checkpoint=tmp_path, **ONE)
    change = dict(change)
    model, data = change.pop("model", Killable()), change.pop("data", {"y": Y})
    with pytest.raises(CheckpointMismatchError) as e:
        fit(model, data, checkpoint=tmp_path, **dict(ONE, **change))
    assert str(e.value).startswith(f"checkpoint {tmp_path / 'chain0.pt'} belongs to another run: {differs}")
    assert str(e.value).endswith(f"Use another checkpoint directory for this run, or delete {tmp_path} to "
                                 "start this one afresh there")


def test_a_checkpoint_serves_fewer_draws_and_continues_for_more(tmp_path):
    """num_samples is no part of the fingerprint: draw i does not depend on the later ones."""
    longer = fit(Killable(), {"y": Y}, **dict(ONE, num_samples=12))["posterior"]["mu"].values
    fit(Killable(), {"y": Y}, checkpoint=tmp_path, **ONE)
    assert np.array_equal(fit(Killable(), {"y": Y}, checkpoint=tmp_path, **dict(ONE, num_samples=12))
                          ["posterior"]["mu"].values, longer)
    model = Killable()
    fewer = fit(model, {"y": Y}, checkpoint=tmp_path, **dict(ONE, num_samples=3))["posterior"]["mu"].values
    assert np.array_equal(fewer, longer[:, :3]) and model.calls < 5


@pytest.mark.parametrize("setting, message", [
    (dict(target_accept=1.5), "target_accept must lie in (0, 1), got 1.5: the acceptance probability the "
                              "step size adapts to; 0.8 is usual"),
    (dict(target_accept=0.0), "target_accept must lie in (0, 1), got 0: "),
    (dict(target_accept=float("nan")), "target_accept contains NaN or inf (nan): the acceptance probability"),
    (dict(max_tree_depth=0), "max_tree_depth must be an integer >= 1, got 0: NUTS's largest tree has "
                             "2**max_tree_depth - 1 leapfrog steps"),
    (dict(checkpoint_every=0), "checkpoint_every must be an integer >= 1, got 0: the draws between checkpoint"),
])
def test_nuts_settings_out_of_range_are_refused(setting, message):
    """Refused where the settings are made, before any model run (counts shared with every
    method, num_samples, num_chains, num_warmup, are tested with fit's settings)."""
    model = Killable()
    with pytest.raises(ValueError) as e:
        fit(model, {"y": Y}, **dict(RUN, **setting))
    assert str(e.value).startswith(message) and model.calls == 0


@pytest.mark.parametrize("length, message", [
    (0.0, "trajectory_length must be positive, got 0: HMC's integration time per draw: a finite number > 0"),
    (-1.0, "trajectory_length must be positive, got -1: HMC's"),
    (float("inf"), "trajectory_length contains NaN or inf (inf): HMC's"),
])
def test_hmc_trajectory_length_must_be_positive(length, message):
    with pytest.raises(ValueError) as e:
        HMC(trajectory_length=length)
    assert str(e.value).startswith(message)


def test_a_mass_matrix_seed_that_is_not_positive_definite_is_refused():
    """A 'fit' whose draws of mu are all equal gives a zero covariance: no inverse mass matrix."""
    frozen = build_tree({"posterior": {"mu": np.full((1, 10), 1.0)}})
    with pytest.raises(ValueError, match=r"mass_matrix_from gives an inverse mass matrix .* not finite, "
                                         r"symmetric and positive definite \(smallest eigenvalue 0\)"):
        fit(Killable(), {"y": Y}, **dict(RUN, mass_matrix_from=frozen))


def test_chains_in_processes_match_chains_in_sequence(reference):
    tree, _ = reference
    same_draws(fit(Killable(), {"y": Y}, **dict(RUN, chains="processes")), tree)
    mu = tree["posterior"]["mu"].values
    assert not np.array_equal(mu[0], mu[1])  # the chains have their own seeds


def test_processes_refuse_a_model_that_does_not_pickle():
    inner = Killable()

    def closure(y):
        inner(y)

    with pytest.raises(ValueError, match="does not pickle.*chains='sequential'"):
        fit(closure, {"y": Y}, **dict(RUN, chains="processes"))


def test_the_plate_model_pickles_after_its_scene_has_solved():
    """models.elastic_plate is a module-level class and a scene drops CHOLMOD's analysis when
    pickled, so NUTS chains of the plate run in worker processes; the copy solves the same."""
    import pickle

    from tests.conftest import plate_scene
    from bayespd.models.elastic_plate import ElasticPlate, elastic_plate

    scene = plate_scene(nx=10, ny=6, delta_max=2.5)
    params = {"K": 3000.0, "G": 1400.0, "delta": 2.5}
    u = scene.solve(params)
    model = pickle.loads(pickle.dumps(elastic_plate(scene, {"K": 3000.0, "G": 1400.0}, 1e-3)))
    assert isinstance(model, ElasticPlate)
    assert torch.equal(model.scene.solve(params), u)


def test_an_unreadable_checkpoint_file_is_named(tmp_path):
    (tmp_path / "chain0.pt").write_bytes(b"not a torch file" * 20)
    with pytest.raises(ValueError, match=r"(?s)cannot read .*chain0.pt as a chain checkpoint .*delete it"):
        fit(Killable(), {"y": Y}, checkpoint=tmp_path, **ONE)
