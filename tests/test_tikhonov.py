"""Tikhonov inversion recovers the moduli from noise-free same-grid data."""
import numpy as np
import pytest

from bayespd.inverse import tikhonov
from conftest import plate_scene


@pytest.mark.parametrize("material", ["lps", "bond"])
def test_recovers_moduli_noise_free(material):
    scene = plate_scene(nx=14, ny=8, material=material)
    truth = {"K": 3000.0, "G": 1400.0} if material == "lps" else {"K": 3000.0}
    y = scene.observe(scene.solve(dict(truth, delta=2.2))).detach()
    init = {k: 0.3 * v for k, v in truth.items()}
    res = tikhonov(scene, y, init, fixed={"delta": 2.2})
    for k, v in truth.items():
        assert abs(res.params[k] - v) / v < 1e-6, (k, res.params[k])
    assert res.evaluations < 100


def test_regularisation_pulls_towards_reference():
    scene = plate_scene(nx=14, ny=8)
    truth = {"K": 3000.0, "G": 1400.0}
    y = scene.observe(scene.solve(dict(truth, delta=2.2))).detach()
    ref = {"K": 2000.0, "G": 1000.0}
    free = tikhonov(scene, y, ref, fixed={"delta": 2.2}, sigma=1e-3)
    strong = tikhonov(scene, y, ref, fixed={"delta": 2.2}, sigma=1e-3, psi=1e12)
    assert abs(free.params["K"] - 3000.0) < 1e-3
    np.testing.assert_allclose([strong.params["K"], strong.params["G"]], [2000.0, 1000.0], rtol=1e-3)
