"""Posterior-predictive crack ensembles (bayespd/ensemble/predictive.py): per-realisation seeds,
the vanishing-noise limit, the store's resume, devices (the aggregate's statistics:
tests/ensemble/test_stats.py)."""
import numpy as np
import pytest
import torch
import xarray as xr

from bayespd.ensemble import predictive
from bayespd.infer.datatree import build_tree
from bayespd.damage import CriticalStretch
from bayespd.scenes.notched_plate import _unit_lambda_min, notched_plate, plate_scene
from bayespd.solvers.fracture import StochasticFracture
from bayespd.ensemble.scene import realise
from bayespd.ensemble.stats import TIMES
from bayespd.ensemble.store import PlanMismatchError
from bayespd.ensemble.predictive import ensemble, pending, posterior_draws, realisation_inputs, rerun

K0, S0 = 3000.0, 0.0094


def posterior(n_draws=40, rel=0.05, seed=0):
    """A fitted tree's posterior group: K and s0 with relative sd ``rel`` (2 chains)."""
    rng = np.random.default_rng(seed)
    return build_tree({"posterior": {"K": K0 * (1 + rel * rng.standard_normal((2, n_draws // 2))),
                                     "s0": S0 * (1 + rel * rng.standard_normal((2, n_draws // 2)))}})


@pytest.fixture(scope="module")
def quiet_scene():
    """16 x 16 notched plate with a vanishing Brownian force (sigma = 1e-3): the runs follow
    the quasi-static path (tests/test_fracture.py)."""
    return notched_plate(side=16.0, h=1.0, steps=20, sigma=1e-3)


@pytest.fixture(scope="module")
def noisy_scene():
    """The same plate with a Brownian force that deflects the crack by a few h."""
    return notched_plate(side=16.0, h=1.0, steps=20, sigma=100.0)


def test_the_unit_body_runs_the_dynamics_of_every_modulus(noisy_scene):
    """Eq 4 with a force linear in K and eta proportional to K does not depend on K
    (``bayespd.scenes.notched_plate``): the driver's unit body at temperature eta / K follows the body at
    K at temperature eta = sigma^2 / M, M dt K lambda_min(A; 1) = relax, bond for bond,
    with u equal to rounding and its reactions times K equal to that body's."""
    K, s0, sigma, relax, dt = 2500.0, 0.0094, 100.0, 1e4, 1.0
    mobility = relax / (dt * K * _unit_lambda_min(16.0, 1.0, 3))
    direct = StochasticFracture(plate_scene(16.0, 1.0, 3, CriticalStretch(s0), sigma), {"K": K, "delta": 3.0},
                                eta=sigma**2 / mobility)
    unit, at_K = (driver.run(noisy_scene.load_factors, dt, seed=5, path_threshold=0.3, tangent="lagged",
                             max_rank=noisy_scene.max_rank, zone=noisy_scene.zone)
                  for driver in (noisy_scene.build({"K": K, "s0": s0}), direct))
    assert at_K.broken[-1] > 0 and np.array_equal(unit.broken, at_K.broken)
    assert torch.equal(unit.intact, at_K.intact)
    assert float((unit.u - at_K.u).abs().max()) <= 1e-9 * float(at_K.u.abs().max())
    scale = np.abs(at_K.reaction).max()
    assert np.abs(unit.reaction - at_K.reaction).max() <= 1e-9 * scale


@pytest.mark.parametrize("n, workers", [(200, 2), (16, 2), (16, 1), (9, 2), (3, 4), (25, 3)])
def test_tasks_are_even_and_a_multiple_of_the_workers(n, workers):
    """The realisations, in order, cut into tasks of at most BATCH that differ by at most one
    in size, as many as a multiple of the workers when there are enough realisations."""
    tasks = predictive._tasks(list(range(n)), workers)
    sizes = [len(t) for t in tasks]
    assert [k for t in tasks for k in t] == list(range(n))
    assert max(sizes) <= predictive.BATCH and max(sizes) - min(sizes) <= 1
    assert len(tasks) % workers == 0 or len(tasks) == n
    assert len(tasks) < -(-n // predictive.BATCH) + workers


def test_realisation_inputs_depend_only_on_seed_and_index():
    """(draw, Brownian seed) of realisation i come from (seed, i) alone; the mean ensemble
    pairs the same Brownian seed with the posterior mean; draws are uniform (2000 picks of
    40 draws: 50 each, binomial sd 6.9, all within 5 sd)."""
    draws = posterior_draws(posterior(), ("K", "s0"))
    a = realisation_inputs(draws, 7, 3)
    assert a == realisation_inputs(draws, 7, 3) and a != realisation_inputs(draws, 8, 3)
    params, d, b = a
    assert params == {"K": draws["K"][d], "s0": draws["s0"][d]}
    mean, d_mean, b_mean = realisation_inputs(draws, 7, 3, "mean")
    assert d_mean == -1 and b_mean == b and mean["K"] == pytest.approx(draws["K"].mean(), rel=1e-15)
    counts = np.bincount([realisation_inputs(draws, 0, i)[1] for i in range(2000)], minlength=40)
    assert np.all(np.abs(counts - 50) < 5 * np.sqrt(2000 / 40 * (39 / 40)))


def test_vanishing_noise_makes_the_spread_epistemic(quiet_scene, tmp_path):
    """sigma -> 0: the mean ensemble is deterministic (same phi and failure load for every
    Brownian seed: aleatoric sd 0, P(phi > 0.4) only 0 or 1) and the posterior spread is all
    epistemic. Under displacement control the stretch is linear in the load (small strain),
    so the quasi-static failure load scales with s0: failure / s0 is constant up to one load
    step of quantisation. Each realisation is re-run exactly by ``realise`` from its inputs."""
    tree = posterior(rel=0.1)
    ds = ensemble(tree, quiet_scene, 6, n_mean=3, store=tmp_path, workers=1, progress=False)
    mean = ds.sel(realisation=ds["ensemble"] == "mean")
    assert np.all(mean["phi"].values == mean["phi"].values[0])
    assert ds["spread"].sel(outcome="failure_load_factor", source="aleatoric") == 0.0
    assert set(np.unique(ds["probability"].sel(kind="mean").values)) <= {0.0, 1.0}
    post = ds.sel(realisation=ds["ensemble"] == "posterior")
    fail, s0 = post["failure_load_factor"].values, post["param_s0"].values
    step = np.diff(quiet_scene.load_factors)[0]
    assert np.all(np.isfinite(fail)) and np.ptp(fail) > 0
    assert np.all(np.abs(fail - s0 * np.median(fail / s0)) <= 1.01 * step)
    spread = ds["spread"].sel(outcome="failure_load_factor")
    assert float(spread.sel(source="epistemic")) == float(spread.sel(source="total")) > 0
    draws = posterior_draws(tree, ("K", "s0"))
    again = rerun(tree, quiet_scene, 4)
    assert np.array_equal(again["phi"], post["phi"].values[4])
    assert int(post["draw"][4]) == realisation_inputs(draws, 0, 4)[1]
    assert np.array_equal(mean["param_s0"].values, np.full(3, draws["s0"].mean()))


@pytest.fixture(scope="module")
def noisy_run(noisy_scene, tmp_path_factory):
    store = tmp_path_factory.mktemp("noisy")
    ds = ensemble(posterior(), noisy_scene, 4, n_mean=2, store=store, workers=1, progress=False,
                  device=torch.device("cpu"))
    return ds, store


def test_the_store_resumes_after_a_crash(noisy_scene, noisy_run, tmp_path, monkeypatch):
    """A crash after 3 of 6 realisations (one a task here) leaves 3 files (and a stale
    temporary one); the re-run runs only the other 3 and gives the uninterrupted result (one
    batch of 6 in lock-step) bit for bit. Deleting files re-runs just those; files already
    there are not rewritten."""
    reference, store = noisy_run
    calls = []
    real = predictive.realise_batch

    def crashing(scene, items, device=None):
        if len(calls) == 3:
            raise KeyboardInterrupt
        calls.append(items)
        return real(scene, items, device)

    monkeypatch.setattr(predictive, "BATCH", 1)
    monkeypatch.setattr(predictive, "realise_batch", crashing)
    with pytest.raises(KeyboardInterrupt):
        ensemble(posterior(), noisy_scene, 4, n_mean=2, store=tmp_path, workers=1, progress=False)
    (tmp_path / "posterior-00003.npz.x.tmp").write_bytes(b"half a file")
    assert len(pending(posterior(), noisy_scene, 4, n_mean=2, store=tmp_path)) == 3
    monkeypatch.setattr(predictive, "realise_batch", real)
    kept = {p.name: p.stat().st_mtime_ns for p in tmp_path.glob("*.npz")}
    ds = ensemble(posterior(), noisy_scene, 4, n_mean=2, store=tmp_path, workers=1, progress=False)
    assert {p.name: p.stat().st_mtime_ns for p in tmp_path.glob("*.npz") if p.name in kept} == kept
    assert not list(tmp_path.glob("*.tmp")) and len(list(tmp_path.glob("*.npz"))) == 6
    xr.testing.assert_identical(ds.drop_vars(TIMES), reference.drop_vars(TIMES))
    (tmp_path / "mean-00001.npz").unlink()
    assert pending(posterior(), noisy_scene, 4, n_mean=2, store=tmp_path) == [("mean", 1)]
    with xr.open_dataset(tmp_path / "ensemble.nc", engine="h5netcdf") as saved:
        xr.testing.assert_identical(saved.load().drop_vars(TIMES), reference.drop_vars(TIMES))
    with pytest.raises(PlanMismatchError, match="another plan .*seed.*new directory"):
        ensemble(posterior(), noisy_scene, 4, n_mean=2, store=tmp_path, seed=1, workers=1, progress=False)


def test_device_is_an_argument(noisy_scene, noisy_run):
    """device=torch.device('cpu') given explicitly: the run's tensors live there, outputs are
    float64 and equal to the default-device run (nothing hard-codes the device)."""
    ds, _ = noisy_run
    draws = posterior_draws(posterior(), ("K", "s0"))
    params, _, b = realisation_inputs(draws, 0, 1)
    explicit = realise(noisy_scene, params, b, device=torch.device("cpu"))
    default = realise(noisy_scene, params, b)
    assert str(explicit["device"]) == "cpu" and str(explicit["u_dtype"]) == "torch.float64"
    for k in ("phi", "path", "reaction", "crack_length"):
        assert explicit[k].dtype == np.float64 and np.array_equal(explicit[k], default[k])
    assert np.array_equal(ds["phi"].values[1], explicit["phi"])
    assert all(ds[k].dtype == np.float64 for k in ("phi", "path", "probability", "spread"))


def test_bad_input_names_the_fix(noisy_scene, tmp_path):
    tree = posterior()
    with pytest.raises(ValueError, match="no variable.*'s0'.*fit a model"):
        ensemble(build_tree({"posterior": {"K": np.ones((1, 4))}}), noisy_scene, 4, store=tmp_path)
    with pytest.raises(ValueError, match="at least 2"):
        ensemble(tree, noisy_scene, 1, store=tmp_path)
    with pytest.raises(ValueError, match="workers must be a positive integer"):
        ensemble(tree, noisy_scene, 2, n_mean=0, store=tmp_path, workers=0)


@pytest.mark.parametrize("device, match", [
    ("gpu", "device='gpu' is not a torch device"),
    ("cuda:99", r"device='cuda:99': this machine has \d+ CUDA device"),
])
def test_a_bad_device_is_refused_before_any_work(quiet_scene, tmp_path, device, match):
    with pytest.raises(ValueError, match=match):
        ensemble(posterior(), quiet_scene, 2, n_mean=0, store=tmp_path / "store", device=device, workers=1)
    assert not (tmp_path / "store").exists()
    with pytest.raises(ValueError, match=match):
        rerun(posterior(), quiet_scene, 0, device=device)


def test_only_numerical_blow_ups_are_recorded(monkeypatch):
    """A numerical error is the realisation's outcome (kept); any other RuntimeError (CUDA out
    of memory, a bad device) is raised so that a re-run tries it again."""
    from bayespd.solvers.dynamics import NumericalInstabilityError
    outcome = [{"phi": np.zeros(2)}, NumericalInstabilityError("reduce dt")]
    monkeypatch.setattr(predictive, "realise_batch", lambda scene, items, device: outcome)
    assert predictive._task(None, [], None) == [outcome[0], {"error": "NumericalInstabilityError: reduce dt"}]
    outcome[1] = RuntimeError("CUDA out of memory")
    with pytest.raises(RuntimeError, match="CUDA out of memory"):
        predictive._task(None, [], None)
