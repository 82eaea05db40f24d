"""``bayespd.linalg.reuse``: later factorisations on a pattern become CG preconditioned by the
first; solutions agree with fresh factors to the CG tolerance (times kappa), within the
iteration bound of the module docstring, and a matrix too far away is factorised afresh."""
import numpy as np
import pytest
import torch

from bayespd.linalg import reuse
from tests.conftest import plate_scene


@pytest.fixture(scope="module")
def scene():
    return plate_scene(nx=20, ny=10)


def solutions(scene, draws):
    with torch.no_grad():
        return [scene.solve({"K": K, "G": G, "delta": 2.2}).numpy() for K, G in draws]


def test_nearby_moduli_reuse_the_first_factor(scene, monkeypatch):
    """Moduli within 20 %: kappa <= 1.2 / 0.8 = 1.5, so CG needs <= ceil(sqrt(1.5) / 2 ln(2e10))
    = 15 iterations; only the first draw factorises."""
    draws = [(3000.0, 1400.0), (3300.0, 1300.0), (2700.0, 1500.0), (3100.0, 1250.0)]
    fresh = solutions(scene, draws)
    calls = []
    original = scene.constraints.pattern._fresh_factor
    monkeypatch.setattr(scene.constraints.pattern, "_fresh_factor", lambda *a: calls.append(1) or original(*a))
    with reuse.reusing_factors(rtol=1e-12, maxiter=15):
        reused = solutions(scene, draws)
    assert len(calls) == 1
    for a, b in zip(fresh, reused):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-10 * np.abs(a).max())


def test_a_far_matrix_is_factorised_afresh(scene, monkeypatch):
    draws = [(3000.0, 1400.0), (30.0, 14000.0)]
    fresh = solutions(scene, draws)
    with reuse.reusing_factors(maxiter=5):
        reused = solutions(scene, draws)
    np.testing.assert_allclose(reused[1], fresh[1], rtol=0, atol=1e-10 * np.abs(fresh[1]).max())
    assert not reuse.active()
