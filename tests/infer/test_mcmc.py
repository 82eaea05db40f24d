"""Checkpointed NUTS: a run killed at any point and resumed gives the uninterrupted run's draws,
bit for bit; chains in worker processes give the same draws as chains in this process."""

import numpy as np
import pyro
import pyro.distributions as dist
import pytest
import torch
import xarray as xr

from bayespd.infer import fit

N = 20
Y = 1.0 + torch.randn(N, generator=torch.Generator().manual_seed(0))
RUN = dict(num_warmup=40, num_samples=60, num_chains=2, seed=5, chains="sequential", progress=False)


class Killable:
    """The conjugate model mu ~ N(0, 3), y ~ N(mu, 1), counting its differentiable runs (the
    sampler's) and raising KeyboardInterrupt, as a kill would, at run ``kill_at``."""

    def __init__(self, kill_at=None):
        self.calls, self.kill_at = 0, kill_at

    def __call__(self, y):
        if torch.is_grad_enabled():
            self.calls += 1
            if self.calls == self.kill_at:
                raise KeyboardInterrupt
        mu = pyro.sample("mu", dist.Normal(0.0, 3.0))
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


def test_checkpoint_of_another_run_is_refused(tmp_path):
    fit(Killable(), {"y": Y}, checkpoint=tmp_path, **dict(RUN, num_chains=1, num_samples=5))
    with pytest.raises(ValueError, match="another run.*another checkpoint directory"):
        fit(Killable(), {"y": Y}, checkpoint=tmp_path, **dict(RUN, num_chains=1, seed=6))


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
