"""The residual-based error estimate: run to convergence it is the true observation error;
at its default stopping rule it stays within a factor 2 of it."""
import numpy as np
import pytest
import torch

from bayespd.reduced.estimator import ErrorEstimator
from tests.reduced.test_scene import built, draws  # noqa: F401  (the module fixture)


def true_error(rom, scene, params):
    with torch.no_grad():
        return float((rom.predict(params) - scene.predict(params)).abs().max())


def test_converged_estimate_is_the_true_error(built):  # noqa: F811
    scene, rom, _ = built
    exact = ErrorEstimator(rom, rom.estimator.reference, rtol=1e-10, max_steps=400)
    for params in draws(scene, 3, seed=11):
        assert abs(exact(params) / true_error(rom, scene, params) - 1) < 1e-4


def test_default_estimate_within_a_factor_two(built):  # noqa: F811
    scene, rom, _ = built
    for params in draws(scene, 4, seed=12):
        assert 0.5 < rom.error_estimate(params) / true_error(rom, scene, params) < 2.0
    assert all(0.5 < e < 2.0 for e in rom.report["estimator_effectivity"])


@pytest.mark.filterwarnings("ignore:.*draws have moduli whose ratios")  # tested in test_scene
def test_diagnostics_report_every_draw_and_warn_above_tolerance(built):  # noqa: F811
    scene, rom, tolerance = built
    d = draws(scene, 4, seed=13)
    arrays = {k: np.array([[p[k] for p in d[:2]], [p[k] for p in d[2:]]]) for k in d[0]}
    out = rom.diagnostics(arrays)["reduced_error_estimate"]
    assert out.shape == (2, 2) and np.all(out > 0)
    rom.tolerance, saved = 1e-30, rom.tolerance
    try:
        with pytest.warns(UserWarning, match="exceeds its tolerance.*at 4 of 4 draws"):
            rom.diagnostics(arrays)
    finally:
        rom.tolerance = saved


@pytest.mark.filterwarnings("ignore:.*draws have moduli whose ratios")
def test_diagnostics_thin_to_the_requested_draws(built):  # noqa: F811
    scene, rom, _ = built
    d = draws(scene, 6, seed=14)
    arrays = {k: np.array([[p[k] for p in d[:3]], [p[k] for p in d[3:]]]) for k in d[0]}
    rom.estimates, saved = 3, rom.estimates
    try:
        out = rom.diagnostics(arrays)["reduced_error_estimate"].reshape(-1)
    finally:
        rom.estimates = saved
    assert np.isfinite(out).tolist() == [True, False, True, False, False, True]  # flat 0, 2.5 -> 2 (half to even), 5
