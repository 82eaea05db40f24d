"""The affine split: the Gram terms applied and projected without assembly equal the assembled
stiffness; the coefficients refuse fields."""
import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.reduced.affine import Terms, check_reducible, coefficients
from tests.reduced.test_scene import plate


@pytest.mark.parametrize("material", [bp.LPS, bp.BondBased])
def test_apply_and_project_equal_the_assembled_stiffness(material, rng):
    scene = plate(material=material)
    params = {"K": 3100.0, "G": 1300.0, "delta": 2.3} if material is bp.LPS else {"K": 3100.0, "delta": 2.3}
    m = scene.material
    K = m.pattern.matrix(m.numeric_stiffness({k: torch.tensor(v) for k, v in params.items()})).toarray()
    terms = Terms(m, params)
    u = rng.standard_normal(K.shape[0])
    np.testing.assert_allclose(terms.apply(u), K @ u, rtol=1e-10, atol=1e-10 * np.abs(K @ u).max())
    V, u_c = rng.standard_normal((K.shape[0], 3)), rng.standard_normal(K.shape[0])
    blocks, loads = terms.project(V, u_c)
    np.testing.assert_allclose(blocks.sum(0), V.T @ K @ V, rtol=1e-10)
    np.testing.assert_allclose(loads.sum(0), -V.T @ K @ u_c, rtol=1e-10)


def test_coefficients_refuse_a_field():
    m = plate().material
    assert coefficients(m, {"K": 3.0, "G": 1.0}).shape == (2,)
    with pytest.raises(ValueError, match="homogeneous G"):
        coefficients(m, {"K": 3.0, "G": torch.ones(4)})


def test_confinement_is_refused():
    p = bp.grid_2d(10.0, 5.0, 1.0)
    m = bp.LPS(p, bp.find_bonds(p, 3.0, "smooth"))
    scene = bp.Scene(m, [bp.Dirichlet.layer(p, "left", 3.0)], [bp.Load(p.layer("right", 1.0), (1.0, 0.0))],
                     eps=0.1)
    with pytest.raises(ValueError, match="eps=0"):
        check_reducible(scene)
